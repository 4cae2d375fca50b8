"""The agent link and pushed team advisories (protocol v4) against a real `hivemap server`: a link with an
``on_team_advisory`` callback asks for them and gets its goals; one without never gets any."""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "server"))
from srv_helpers import TOKENS, ServerProcess, map_of, write_config  # noqa: E402

from hivemap.client.link import AgentLink  # noqa: E402
from hivemap.protocol import TeamAdvisory  # noqa: E402
from hivemap.server.loadgen import CAMERA, synthetic_stream  # noqa: E402


def test_link_receives_advisories_only_when_it_asks(tmp_path: Path) -> None:
    cfg = write_config(tmp_path / "server.toml")
    cfg.write_text(cfg.read_text() + "[team]\nmin_interval_s = 0.2\npush_interval_s = 0.3\n")
    server = ServerProcess(tmp_path / "data", cfg).start()
    got: list[TeamAdvisory] = []
    try:

        async def main() -> tuple[AgentLink, AgentLink]:
            links = {
                "uav1": AgentLink(server.ws_url, "uav1", "uav", CAMERA.to_dict(), TOKENS["uav1"],
                                  tmp_path / "uav1.outbox", on_team_advisory=got.append),
                "uav2": AgentLink(server.ws_url, "uav2", "uav", CAMERA.to_dict(), TOKENS["uav2"],
                                  tmp_path / "uav2.outbox"),
            }  # fmt: skip
            tasks = [asyncio.create_task(link.run()) for link in links.values()]
            for seed, (agent_id, link) in enumerate(links.items()):
                for m in synthetic_stream(agent_id, 15, seed=seed + 1)[0]:
                    await link.submit(m)
                await link.flush(timeout=30)
            for _ in range(100):  # up to 10 s for the first advisory after the points are in
                if any(len(a.goals) for a in got):
                    break
                await asyncio.sleep(0.1)
            await asyncio.sleep(1.0)  # several push periods for uav2 too
            for link in links.values():
                await link.close()
            await asyncio.wait_for(asyncio.gather(*tasks), 10)
            return links["uav1"], links["uav2"]

        asker, other = asyncio.run(main())
        assert got and asker.stats.advisories == len(got) and asker.last_advisory is got[-1]
        last = next(a for a in reversed(got) if len(a.goals))
        assert last.map_id == map_of(server, "uav1")["id"] and last.session == 0
        assert last.goals.shape[1] == 3 and np.isfinite(last.safe_velocity).all()
        assert other.stats.advisories == 0 and other.last_advisory is None
    finally:
        server.stop()
