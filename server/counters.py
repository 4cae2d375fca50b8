"""The agents' message counters of :class:`~hivemap.server.core.HiveServer` (received, duplicates, errors,
bandwidth): persisted apart from the data, every few seconds, so a kill -9 may lose a few seconds of them
but never a message."""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Any

from hivemap.server.agents import AgentState

if TYPE_CHECKING:
    from hivemap.server.persist import ServerStore
    from hivemap.server.writer import StoreWriter


class Counters:
    """Counter persistence; the server holds the agents and the writer."""

    agents: dict[str, AgentState]
    _counters_written: dict[str, dict[str, Any]]
    _writer: StoreWriter[ServerStore] | None

    COUNTERS_INTERVAL_S = 5.0

    @staticmethod
    def _counters_of(agent: AgentState) -> dict[str, Any]:
        return {
            "received": dict(agent.received),
            "duplicates": agent.duplicates,
            "errors": agent.errors,
            "bandwidth": agent.bandwidth.to_record(),
        }

    def _restore_counters(self, counters: dict[str, dict[str, Any]]) -> None:
        for agent_id, rec in counters.items():
            agent = self.agents.get(agent_id)
            if agent is None:
                continue
            agent.received.update({str(k): int(v) for k, v in rec.get("received", {}).items()})
            agent.duplicates += int(rec.get("duplicates", 0))
            agent.errors += int(rec.get("errors", 0))
            agent.bandwidth.restore(rec.get("bandwidth", {}))
            self._counters_written[agent_id] = self._counters_of(agent)

    def _submit_counters(self) -> None:
        """Queue a write of the counters that changed since the last one."""
        changed = []
        for agent in self.agents.values():
            rec = self._counters_of(agent)
            if self._counters_written.get(agent.agent_id) != rec:
                self._counters_written[agent.agent_id] = rec
                changed.append((agent.agent_id, rec))
        if changed and self._writer is not None:
            self._writer.submit(lambda store: [store.put_counters(a, r) for a, r in changed])

    async def _write_counters_periodically(self) -> None:
        while True:
            await asyncio.sleep(self.COUNTERS_INTERVAL_S)
            self._submit_counters()
