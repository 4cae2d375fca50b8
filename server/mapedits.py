"""Map surgery of :class:`~hivemap.server.core.HiveServer` on the event loop: merging two maps and fusing
duplicate points, each persisted in one commit before it returns."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any

from hivemap.maps import MapStack
from hivemap.maps.geometry import Sim3
from hivemap.maps.store import map_rows
from hivemap.server.agents import AgentState
from hivemap.server.events import EventLog
from hivemap.server.persist import GraphSnapshot, ServerStore

if TYPE_CHECKING:
    from hivemap.server.writer import StoreWriter

KfKey = tuple[str, int]
PointKey = tuple[str, int]


class MapEdits:
    """Merges and point fusion; the server holds the stack, the agents, the writer and the event log."""

    stack: MapStack
    agents: dict[str, AgentState]
    events: EventLog
    _ingest_open: asyncio.Event

    if TYPE_CHECKING:

        @property
        def writer(self) -> StoreWriter[ServerStore]: ...

    async def apply_merge(
        self,
        target_id: int,
        source_id: int,
        target_from_source: Sim3,
        fused_pairs: Sequence[tuple[tuple[str, int], tuple[str, int]]] = (),
        by: str | None = None,
        on_merged: Callable[[Any], None] | None = None,
    ) -> Any:
        """Merge map ``source_id`` into ``target_id`` (``MapStack.merge``), re-frame the moved agents'
        incoming data (``global_from_vio``), persist the merged map and the merge record in one commit, and
        publish a ``merge`` event (its ``by``: what the merge rests on, if not place recognition). Returns
        the merged map. ``on_merged(merged)`` runs in the same step as the merge, before the write: what
        other tasks read with the map (the back-end's edges) must be there when they first see it."""
        self._ingest_open.clear()
        try:
            source = self.stack.maps[source_id]
            moved = [
                am
                for agent in self.agents.values()
                for am in agent.maps.values()
                if am.folded in source.agents
            ]
            merged = self.stack.merge(target_id, source_id, target_from_source, list(fused_pairs))
            if by is not None:
                merged.merge_history[-1]["by"] = by
            for am in moved:
                am.global_from_vio = target_from_source @ am.global_from_vio
            rows = [am.row() for am in moved]
            # serialised here: other back-end tasks go on changing the merged map during the write
            snapshot = map_rows(merged)

            def op(store: ServerStore) -> None:
                store.maps.delete_map(source_id)
                store.maps.save_map(snapshot)
                for row in rows:
                    store.put_agent_map(row)

            try:
                if on_merged is not None:
                    on_merged(merged)
            finally:  # the store follows the maps in memory even if the caller's part fails
                await self.writer.call(op)
        finally:
            self._ingest_open.set()
        data = {"source": source_id, "target": target_id, "scale": target_from_source.s}
        how = f"{len(fused_pairs)} fused points"
        if by is not None:
            data["by"] = by
            how += f", by {by}"
        self.events.add("merge", f"map {source_id} merged into map {target_id} ({how})", map_id=target_id,
                        data=data)  # fmt: skip
        return merged

    async def fuse_points(self, map_id: int, pairs: Iterable[tuple[PointKey, PointKey]]) -> int:
        """Fuse duplicate map points ``(keep, drop)`` of map ``map_id`` (``Map.fuse_points``; pairs already
        fused or gone are skipped) and persist the changed point references, the removed points and their
        redirects in one commit before returning. Returns how many points were fused away."""
        m = self.stack.maps.get(map_id)
        if m is None:
            return 0
        touched: set[KfKey] = set()
        dropped: list[PointKey] = []
        for keep, drop in pairs:
            k2, d2 = m.resolve_point(keep), m.resolve_point(drop)
            if k2 != d2 and k2 in m.points and d2 in m.points:
                touched.update(m.points[d2].observations)
                m.fuse_points(k2, d2)
                dropped.append(d2)
        if not dropped:
            return 0
        refs = [
            (k, m.keyframes[k].point_ids.copy(), dict(m.keyframes[k].point_agents))
            for k in sorted(touched)
            if k in m.keyframes
        ]
        graph = GraphSnapshot(m)

        def op(store: ServerStore) -> None:
            store.maps.put_fusion(map_id, refs, dropped)
            store.sync_graph(graph)

        await self.writer.call(op)
        return len(dropped)
