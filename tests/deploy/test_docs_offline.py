"""`/docs` renders in headless Chromium with every host but the server's unreachable: the Swagger UI
assets come from the server itself (the swagger-ui-bundle package), not from a CDN."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "server"))
from srv_helpers import ServerProcess, write_config  # noqa: E402


@pytest.fixture
def server(tmp_path: Path) -> ServerProcess:
    s = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml")).start()
    yield s
    s.stop()


def test_docs_render_offline(server: ServerProcess) -> None:
    from test_viewer import _browser

    html = server.get("/docs").text
    assert "cdn" not in html.lower() and "/docs-assets/swagger-ui-bundle.js" in html
    # every name resolves to nothing except loopback: a CDN reference would leave the page blank
    driver = _browser(extra_args=["--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1"])
    try:
        driver.get(server.url + "/docs")
        deadline = time.monotonic() + 30
        title, ops = "", 0
        while time.monotonic() < deadline:
            title, ops = driver.execute_script(
                "const t = document.querySelector('.swagger-ui .info .title');"
                "return [t ? t.textContent : '', document.querySelectorAll('.opblock').length];"
            )
            if title and ops:
                break
            time.sleep(0.2)
        assert "hivemap server" in title
        assert ops == len([r for r in server.json("/openapi.json")["paths"].values() for _ in r])
    finally:
        driver.quit()
