"""Viewer benchmark: time until a 3 M-point map shows in the browser (progressive level of detail).

Writes a store with ``--points`` map points (one map, four agents' points in a few clusters of different
density), starts a real ``hivemap server`` on it, waits until the store is loaded, then opens the viewer
in headless Chromium (as tests/deploy/test_viewer*.py) ``--loads`` times and prints, per page load, the
time from navigation to the first frame drawn with points and to the first with all of them (the
viewer's ``data-points-first-ms`` / ``data-points-all-ms``), and the points drawn; "polled" is the same
seen from here (the page answers scripts only between frames, so it is later). The first load after the
start includes the server hashing the map's point keys (``hivemap.server.lod``); later loads reuse them.

    nice -n 10 .venv/bin/python bench/viewer.py [--points 3000000] [--loads 2]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "tests" / "server"), str(ROOT / "tests" / "deploy")]
from srv_helpers import ServerProcess, write_config  # noqa: E402
from test_viewer import _browser  # noqa: E402

from hivemap.maps import MapPoint  # noqa: E402
from hivemap.maps.store import MapStore  # noqa: E402


def write_store(path: Path, n: int, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-150, 150, (12, 3)) * (1, 1, 0.1)
    store = MapStore(path)
    agents = ["uav1", "uav2", "ugv1", "ugv2"]
    chunk = 250_000
    for start in range(0, n, chunk):
        k = min(chunk, n - start)
        which = rng.integers(0, len(centres), k)
        xyz = centres[which] + rng.normal(0, 1, (k, 3)) * rng.uniform(2, 20, len(centres))[which, None]
        store.put_points(0, [MapPoint(agents[i % 4], start + i, xyz[i]) for i in range(k)])
    store.close()


def _attrs(driver: Any) -> tuple[str | None, ...]:
    """The viewer's timing attributes (None while the page is too busy to answer a script)."""
    from selenium.common.exceptions import TimeoutException

    names = ("pointsFirstMs", "pointsAllMs", "points", "pointsLevel")
    try:
        script = "return [" + ", ".join(f"document.body.dataset.{n}" for n in names) + "]"
        return tuple(driver.execute_script(script))
    except TimeoutException:
        return (None,) * len(names)


def _s(t: float | None) -> str:
    return "-" if t is None else f"{t:.1f} s"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, default=3_000_000)
    ap.add_argument("--loads", type=int, default=2, help="page loads (the first one after the start is cold)")
    ap.add_argument("--timeout", type=float, default=120.0, help="per page load, seconds")
    ap.add_argument("--store", type=Path, help="store folder to reuse (written when absent)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="hivemap-bench-viewer-") as tmp:
        data = args.store or Path(tmp) / "data"
        data.mkdir(parents=True, exist_ok=True)
        if not (data / "hivemap.sqlite").exists():
            t = time.perf_counter()
            write_store(data / "hivemap.sqlite", args.points)
            print(f"store: {args.points} points written in {time.perf_counter() - t:.1f} s")
        server = ServerProcess(data, write_config(Path(tmp) / "server.toml"))
        t = time.perf_counter()
        server.start(timeout=1800.0)
        print(f"server: store loaded in {time.perf_counter() - t:.1f} s, maps {server.json('/maps')['maps']}")
        try:
            for load in range(args.loads):
                driver = _browser()
                try:
                    t0 = time.monotonic()
                    driver.get(server.url + "/")
                    # also timed from here by polling the drawn count, which any viewer version reports
                    seen_first = seen_all = None
                    while time.monotonic() - t0 < args.timeout:
                        first, last, n, _ = _attrs(driver)
                        if seen_first is None and int(n or 0) > 0:
                            seen_first = time.monotonic() - t0
                        if last is not None and int(n or 0) == args.points:
                            seen_all = time.monotonic() - t0
                            break
                        time.sleep(0.05)
                    kind = "cold" if load == 0 else "warm"
                    print(
                        f"page load {load + 1} ({kind}): first points drawn at {first} ms, all {n} points "
                        f"drawn at {last} ms after navigation (polled: {_s(seen_first)} / {_s(seen_all)})"
                    )
                finally:
                    driver.quit()
        finally:
            server.stop()


if __name__ == "__main__":
    main()
