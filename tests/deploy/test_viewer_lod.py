"""Progressive point loading (level of detail): the points endpoint's parts partition a 200k-point map into
even subsamples that nest (part k of P is parts k and k+P of 2P), and the viewer draws the whole map part
by part, the first part long before the last."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "server"))
from srv_helpers import ServerProcess, parse_ply, write_config  # noqa: E402

from hivemap.maps import MapPoint  # noqa: E402
from hivemap.maps.store import MapStore  # noqa: E402

N = 200_000


@pytest.fixture(scope="module")
def big(tmp_path_factory: pytest.TempPathFactory) -> Any:
    tmp = tmp_path_factory.mktemp("lod")
    data = tmp / "data"
    data.mkdir()
    rng = np.random.default_rng(0)
    # two agents' points in two clusters of different density: a part must follow the density
    xyz = np.concatenate([rng.normal(0, 20, (N // 4 * 3, 3)), rng.normal((80, 0, 0), 5, (N // 4, 3))])
    store = MapStore(data / "hivemap.sqlite")
    store.put_points(0, [MapPoint("uav1" if i % 2 else "ugv1", i, xyz[i]) for i in range(N)])
    store.close()
    server = ServerProcess(data, write_config(tmp / "server.toml")).start(timeout=120)
    try:
        yield server, xyz
    finally:
        server.stop()


def _part(server: ServerProcess, k: int, parts: int) -> np.ndarray:
    r = server.get("/maps/0/points", part=k, parts=parts)
    assert r.status_code == 200, r.text
    props, rec = parse_ply(r.content)
    assert props == [("float", "x"), ("float", "y"), ("float", "z")]
    return np.stack([rec["x"], rec["y"], rec["z"]], axis=1)


def test_parts_partition_the_map_into_even_nested_subsamples(big: Any) -> None:
    server, xyz = big
    parts4 = [_part(server, k, 4) for k in range(4)]
    # together exactly the stored points (as float32), each once
    got = np.concatenate(parts4)
    assert len(got) == N
    want = xyz.astype(np.float32)
    assert np.array_equal(np.unique(got, axis=0), np.unique(want, axis=0))
    # each part is an even subsample: its size and its share of the dense cluster are those of the map
    # (binomial spread: 5 sigma of N/4 points is ~1 %)
    for p in parts4:
        assert abs(len(p) - N / 4) < 5 * np.sqrt(N / 4 * 0.75)
        assert abs(np.mean(p[:, 0] > 50) - 0.25) < 0.01
    # nested levels: part k of 4 is parts k and k+4 of 8
    for k in (0, 3):
        both = np.concatenate([_part(server, k, 8), _part(server, k + 4, 8)])
        assert np.array_equal(np.unique(both, axis=0), np.unique(parts4[k], axis=0))
    # the viewer's coarse-to-fine requests (lodSteps in viewer/src/main.js), each doubling the density,
    # hold every point once
    steps = [_part(server, k, p) for k, p in ((0, 8), (4, 8), (2, 4), (1, 2))]
    for x, share in zip(steps, (1 / 8, 1 / 8, 1 / 4, 1 / 2), strict=True):
        assert abs(len(x) - share * N) < 5 * np.sqrt(N * share * (1 - share))
    assert sum(map(len, steps)) == N
    assert len(np.unique(np.concatenate(steps), axis=0)) == len(np.unique(want, axis=0))
    assert server.get("/maps/0/points", part=4, parts=4).status_code == 422


def test_viewer_draws_the_map_part_by_part(big: Any) -> None:
    from test_viewer import open_viewer

    server, _ = big
    driver, body = open_viewer(server.url, "data-points-all-ms", None, timeout=60)
    try:
        assert body.get_attribute("data-points") == str(N)
        first, last = (int(body.get_attribute(f"data-points-{w}-ms") or -1) for w in ("first", "all"))
        # two levels of 100k points (at most 150k in the first): the first is drawn before the second comes
        assert 0 < first < last, (first, last)
    finally:
        driver.quit()
