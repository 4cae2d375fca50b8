"""The web viewer in headless Chromium against a real server holding a known map: the page loads,
draws exactly the stored points, and shows every agent."""

from __future__ import annotations

import os
import shutil
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "server"))
from agent_client import SyncAgent  # noqa: E402
from srv_helpers import TOKENS, ServerProcess, write_config  # noqa: E402

from hivemap.server.loadgen import synthetic_stream  # noqa: E402

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"


@pytest.fixture
def server(tmp_path: Path) -> ServerProcess:
    s = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml")).start()
    yield s
    s.stop()


def _browser(extra_args: list[str] | None = None):  # type: ignore[no-untyped-def]
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    assert shutil.which(CHROMIUM) and shutil.which(CHROMEDRIVER), (
        "Debian chromium + chromium-driver are required; `make test` installs them"
    )
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in (
        "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--window-size=1280,800",
        *(extra_args or []),
    ):  # fmt: skip
        opts.add_argument(a)
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)


def open_viewer(url: str, attr: str, value: str | None, timeout: float = 30.0):  # type: ignore[no-untyped-def]
    """A browser on the viewer at ``url``, once the page's ``body[attr]`` is ``value`` (None: is set) or
    ``timeout`` s passed; returns (driver, body). The caller quits the driver."""
    driver = _browser()
    try:
        driver.get(url + "/")
        body = driver.find_element("tag name", "body")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            got = body.get_attribute(attr)
            if (got is not None) if value is None else got == value:
                break
            time.sleep(0.2)
    except BaseException:
        driver.quit()
        raise
    return driver, body


def test_viewer_draws_the_map_and_agents(server: ServerProcess, tmp_path: Path) -> None:
    total_points = 0
    for agent_id, seed, offset in (("uav1", 1, (0.0, 0.0, 0.0)), ("ugv1", 2, (5.0, 30.0, 0.0))):
        msgs, truth = synthetic_stream(agent_id, 15, features=150, seed=seed, offset=offset)
        with SyncAgent(server.ws_url, agent_id, TOKENS[agent_id]) as ag:
            ag.welcome()
            _, errors = ag.send_all(msgs)
            assert not errors
        total_points += len(truth.points)
    maps = server.json("/maps")["maps"]
    assert sum(m["points"] for m in maps) == total_points
    driver = _browser()
    try:
        driver.get(server.url + "/")
        deadline = time.monotonic() + 30
        body = driver.find_element("tag name", "body")
        while time.monotonic() < deadline:
            body = driver.find_element("tag name", "body")
            if body.get_attribute("data-ready") == "1" and body.get_attribute("data-points") == str(
                total_points
            ):
                break
            time.sleep(0.2)
        assert body.get_attribute("data-points") == str(total_points)
        assert body.get_attribute("data-agents-drawn") == "2"
        # every configured agent is listed (uav2 never connected); the two with data are drawn.
        # (read in one script: the panel is re-rendered every second)
        listed = driver.execute_script(
            "return [...document.querySelectorAll('#agents tr')].map(r => r.dataset.agent)"
        )
        assert sorted(listed) == sorted(TOKENS)
        time.sleep(1.5)  # let a few animation frames draw the trajectories
        shot = Path(os.environ.get("HIVEMAP_VIEWER_SCREENSHOT", tmp_path / "viewer.png"))
        driver.save_screenshot(str(shot))
        assert shot.stat().st_size > 10_000  # a real rendered page, not a blank one
        errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
        assert not errors, errors
    finally:
        driver.quit()
