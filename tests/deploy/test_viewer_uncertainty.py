"""The agents' 2-sigma position ellipses in the viewer: a real server with its back-end gets a synthetic
agent's keyframes; the viewer draws one horizontal ellipse per agent with a covariance on ``/agents``,
of the semi-axes that the REST covariance's x-y block gives."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from test_viewer import open_viewer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "server"))
from agent_client import SyncAgent  # noqa: E402
from srv_helpers import TOKENS, ServerProcess, write_config  # noqa: E402

from hivemap.server.backend_synth import UGV_FROM_WORLD, agent_stream, make_world  # noqa: E402


def test_viewer_draws_each_agents_position_ellipse(tmp_path: Path) -> None:
    server = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml", backend=True)).start()
    try:
        rng = np.random.default_rng(4)
        pts, desc = make_world(rng, 2000, (-20, 30))
        msgs, _, _ = agent_stream(rng, pts, desc, np.linspace(-6, 12, 12), UGV_FROM_WORLD)
        with SyncAgent(server.ws_url, "ugv1", TOKENS["ugv1"], kind="ugv") as ag:
            ag.welcome()
            _, errors = ag.send_all(msgs)
            assert not errors
        deadline = time.monotonic() + 60
        unc = None
        while time.monotonic() < deadline and (unc is None or unc["kf_id"] != 11):
            unc = server.json("/agents/ugv1")["uncertainty"]
            time.sleep(0.3)
        assert unc is not None and unc["kf_id"] == 11, unc
        # what the ellipse must be: 2 sigma along the eigenvectors of the x-y block (z is up)
        w = np.linalg.eigvalsh(np.array(unc["position_cov"])[:2, :2])
        want = 2.0 * np.sqrt(w[::-1])
        assert want[0] > 0.01  # a real ellipse: the latest keyframe is 18 m from the gauge
        driver, body = open_viewer(server.url, "data-ellipses", None)
        try:
            deadline = time.monotonic() + 20
            got: dict[str, list[float]] = {}
            while time.monotonic() < deadline and "ugv1" not in got:
                got = json.loads(body.get_attribute("data-ellipses") or "{}")
                time.sleep(0.2)
            assert set(got) == {"ugv1"}, got
            np.testing.assert_allclose(got["ugv1"], want, rtol=1e-3)
            errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
            assert not errors, errors
        finally:
            driver.quit()
    finally:
        server.stop()
