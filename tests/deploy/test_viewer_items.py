"""The viewer's mission items in headless Chromium: keyframe frustums and loop edges of a mission where the
UGV closes a loop, agent colours from a hash of the id (the same as in Foxglove), the event filter, and a
screenshot that shows them; the points endpoint's coarse level of detail."""

from __future__ import annotations

import io
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "server"))
from agent_client import SyncAgent  # noqa: E402
from srv_helpers import TOKENS, ServerProcess, parse_ply, write_config  # noqa: E402
from test_foxglove import _streams  # noqa: E402

from hivemap.server.foxglove import PALETTE_HEX, agent_color  # noqa: E402

DEFAULT_EVENTS = {"merge", "loop", "correction", "gnss_stage", "session", "error", "refused", "connect",
                  "disconnect", "mission", "start_anchor"}  # fmt: skip


@pytest.fixture(scope="module")
def mission(tmp_path_factory: pytest.TempPathFactory) -> Any:
    tmp = tmp_path_factory.mktemp("viewer")
    server = ServerProcess(tmp / "data", write_config(tmp / "server.toml", backend=True)).start()
    try:
        for agent_id, msgs in _streams().items():
            kind = "ugv" if agent_id.startswith("ugv") else "uav"
            with SyncAgent(server.ws_url, agent_id, TOKENS[agent_id], kind=kind) as agent:
                agent.welcome()
                assert agent.send_all(msgs)[1] == []
        server.wait_backend_idle()
        yield server
    finally:
        server.stop()


def test_points_have_a_coarse_level(mission: ServerProcess) -> None:
    (m, *_) = mission.json("/maps")["maps"]
    _, full = parse_ply(mission.get(f"/maps/{m['id']}/points").content)
    _, coarse = parse_ply(mission.get(f"/maps/{m['id']}/points", max_points=100).content)
    assert len(full) == m["points"] > 1000 and 50 <= len(coarse) <= 100
    # an even subsample of the same points
    assert {tuple(p) for p in coarse.tolist()} <= {tuple(p) for p in full.tolist()}


def test_viewer_draws_frustums_loops_and_stable_colours(mission: ServerProcess, tmp_path: Path) -> None:
    from PIL import Image
    from test_viewer import _browser

    maps = mission.json("/maps")["maps"]
    n_kf = sum(m["keyframes"] for m in maps)
    n_loops = sum(len(mission.json(f"/maps/{m['id']}/edges")["segments"]) for m in maps)
    events = mission.json("/events", limit=1000)["events"]
    assert n_loops > 0 and any(e["kind"] not in DEFAULT_EVENTS for e in events)
    driver = _browser()
    try:
        driver.get(mission.url + "/")
        body = driver.find_element("tag name", "body")
        deadline = time.monotonic() + 40
        while time.monotonic() < deadline:
            if (
                body.get_attribute("data-frustums") == str(n_kf)
                and body.get_attribute("data-points-level") == "full"
            ):
                break
            time.sleep(0.2)
        assert body.get_attribute("data-frustums") == str(n_kf)
        assert body.get_attribute("data-loop-edges") == str(n_loops)
        colors = json.loads(body.get_attribute("data-colors") or "{}")
        for agent_id in ("ugv1", "uav1"):
            r, g, b = agent_color(agent_id)
            assert colors[agent_id] == f"#{round(r * 255):02x}{round(g * 255):02x}{round(b * 255):02x}"
        assert len({colors[a] for a in colors}) == len(colors)  # these four ids do not collide
        assert len(set(PALETTE_HEX)) == 16
        # the event filter: by default only merges, loops, corrections, sessions, connections, errors
        kinds = driver.execute_script(
            "return [...document.querySelectorAll('#events li')].map(l => l.dataset.kind)"
        )
        assert kinds and set(kinds) <= DEFAULT_EVENTS
        driver.find_element("id", "all-events").click()
        time.sleep(1.5)
        kinds = driver.execute_script(
            "return [...document.querySelectorAll('#events li')].map(l => l.dataset.kind)"
        )
        assert set(kinds) - DEFAULT_EVENTS, kinds
        time.sleep(1.0)  # a few frames with everything in place
        png = driver.get_screenshot_as_png()
        # only maps the server lists are asked for (not ids that were merged away)
        urls = driver.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
        asked = {int(u.split("/maps/")[1].split("/")[0].split("?")[0]) for u in urls if "/maps/" in u
                 and u.split("/maps/")[1][:1].isdigit()}  # fmt: skip
        assert asked and asked <= {m["id"] for m in maps}, (asked, maps)
        (tmp_path / "viewer.png").write_bytes(png)
    finally:
        driver.quit()
    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    view = img[:, : img.shape[1] - 440]  # the 3D view, without the side panel

    def pixels(hex_color: str, tol: int = 40) -> int:
        c = np.array([int(hex_color[i : i + 2], 16) for i in (1, 3, 5)])
        return int((np.abs(view - c).max(axis=2) <= tol).sum())

    # loop arcs: magenta, darkened by antialiasing on the dark background (red and blue well above green)
    r, g, b = view[..., 0], view[..., 1], view[..., 2]
    magenta = (r > 2 * g + 60) & (b > 2 * g + 60) & (np.abs(r - b) < 60)
    assert int(magenta.sum()) > 20, "no loop edges on screen"
    for agent_id in ("ugv1", "uav1"):
        assert pixels(colors[agent_id]) > 50, f"{agent_id}'s trajectory/frustums not on screen"


def test_orbit_camera_turns_around_its_target(mission: ServerProcess) -> None:
    from selenium.webdriver import ActionChains
    from test_viewer import open_viewer

    driver, body = open_viewer(mission.url, "data-points-level", "full")
    try:
        canvas = driver.find_element("id", "view")

        def drag(dx: int, dy: int) -> str | None:
            chain = ActionChains(driver).move_to_element(canvas).click_and_hold()
            chain.move_by_offset(dx, dy).release().perform()
            time.sleep(0.5)
            return body.get_attribute("data-camera")

        before_json = drag(120, 60)  # the first drag also reports the camera (after fitting to the map)
        after_json = drag(-200, 80)
    finally:
        driver.quit()
    (p0, t0), (p1, t1) = json.loads(before_json or "null"), json.loads(after_json or "null")
    p0, t0, p1, t1 = map(np.asarray, (p0, t0, p1, t1))
    # a left drag orbits: the camera moved on a sphere around the unchanged target (in 3D, height too)
    np.testing.assert_allclose(t1, t0, atol=1e-6)
    assert np.linalg.norm(p1 - p0) > 1.0 and abs(p1[2] - p0[2]) > 0.1
    assert abs(np.linalg.norm(p1 - t1) - np.linalg.norm(p0 - t0)) < 1e-3 * np.linalg.norm(p0 - t0)
