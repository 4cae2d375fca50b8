"""The stack of a session's maps: one per agent until they merge (``hivemap.maps.merge``)."""

from __future__ import annotations

from collections.abc import Sequence

from hivemap.maps.elements import PointKey
from hivemap.maps.geometry import Sim3
from hivemap.maps.model import Map


class MapStack:
    """All maps of a session (the server holds one per agent until they merge)."""

    def __init__(self) -> None:
        self.maps: dict[int, Map] = {}
        self.next_map_id = 0

    def __repr__(self) -> str:
        return f"MapStack({list(self.maps.values())})"

    def new_map(self, map_id: int | None = None) -> Map:
        """A new empty map (next free id unless ``map_id`` is given)."""
        mid = self.next_map_id if map_id is None else int(map_id)
        if mid in self.maps:
            raise ValueError(f"map {mid} already exists")
        m = Map(mid)
        self.maps[mid] = m
        self.next_map_id = max(self.next_map_id, mid + 1)
        return m

    def add_map(self, m: Map) -> Map:
        if m.id in self.maps:
            raise ValueError(f"map {m.id} already exists")
        self.maps[m.id] = m
        self.next_map_id = max(self.next_map_id, m.id + 1)
        return m

    def remove_map(self, map_id: int) -> Map:
        return self.maps.pop(int(map_id))

    def map_of_agent(self, agent_id: str) -> Map | None:
        for m in self.maps.values():
            if agent_id in m.agents:
                return m
        return None

    def merge(
        self,
        target_id: int,
        source_id: int,
        target_from_source: Sim3,
        fused_pairs: Sequence[tuple[PointKey, PointKey]] = (),
    ) -> Map:
        """Merge map ``source_id`` into map ``target_id`` (:func:`hivemap.maps.merge.merge_maps`)."""
        from hivemap.maps.merge import merge_maps

        return merge_maps(self, target_id, source_id, target_from_source, fused_pairs)


__all__ = ["MapStack"]
