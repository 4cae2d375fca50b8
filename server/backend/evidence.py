"""What holds a map together beyond its agents' own tracking: every loop and merge edge it was given, kept
with its measurement so that each pose graph judges all of them again (:mod:`.optimise`, robust solve),
and each merge as a hypothesis (its transform and evidence) until enough loops between its two sides
confirm it. A rejected loop is reported with its reason; a merge whose edge is rejected is to be undone
(:mod:`.split`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hivemap.maps.geometry import Sim3, rotation_angle_deg
from hivemap.server.backend.optimise import NewEdge
from hivemap.server.backend.sessionguess import is_guess

KfKey = tuple[str, int]


@dataclass
class MergeHypothesis:
    """A merge on trial: ``source_agents`` were moved by ``target_from_source`` into the map of
    ``target_agents``. ``confirmations``: query keyframes of the independent loops between the two sides
    kept with it (:meth:`EvidenceBook.dependent_on`)."""

    id: int
    target: int
    source: int
    target_from_source: Sim3
    source_agents: frozenset[str]
    target_agents: frozenset[str]
    record: dict[str, Any]
    edge: NewEdge | None = None
    confirmations: set[KfKey] = field(default_factory=set)
    confirmed: bool = False

    def across(self, a: KfKey, b: KfKey) -> bool:
        """Whether the edge ``a``-``b`` joins the two sides of this merge."""
        s, t = self.source_agents, self.target_agents
        return (a[0] in s and b[0] in t) or (a[0] in t and b[0] in s)


@dataclass
class Evidence:
    """One loop or merge edge. ``record``: the loop's or merge's record (``Backend.loops`` / ``merges``),
    marked ``rejected`` with its ``reject_reason`` while the robust pose graph rejects the edge."""

    edge: NewEdge
    kind: str  # "loop", "merge" or "rendezvous" (an observation of one agent by another)
    record: dict[str, Any]
    merge: MergeHypothesis | None = None
    rejected: bool = False
    judged: int = 0  # pose graphs that judged it
    fuse: list[tuple[Any, Any]] = field(default_factory=list)  # a loop's duplicate points, fused once kept
    fused: bool = False
    # a loop across a merge on trial seen at the merge's own place: the same evidence again, not a vote
    dependent: MergeHypothesis | None = None


@dataclass
class Verdict:
    """What one pose graph's judgement changed."""

    rejected: list[Evidence] = field(default_factory=list)  # newly rejected
    readmitted: list[Evidence] = field(default_factory=list)  # rejected before, kept now
    contradicted: list[MergeHypothesis] = field(default_factory=list)  # merges to undo
    confirmed: list[MergeHypothesis] = field(default_factory=list)  # merges no longer on trial


class EvidenceBook:
    """Per map, its kept edges and its merges on trial (only touched on the event loop)."""

    def __init__(self) -> None:
        self.edges: dict[int, list[Evidence]] = {}
        self.merges: dict[int, list[MergeHypothesis]] = {}
        self._next_id = 0
        self.refuted: list[MergeHypothesis] = []  # undone merges: the same detection again is refused

    def refuted_like(
        self, agents: tuple[set[str], set[str]], target_from_source: Sim3
    ) -> MergeHypothesis | None:
        """An undone merge between the same agents by (nearly) the same transform (1 m at the source's
        frame origin, 5 deg): the detection that made it, found again. An undone session guess is no
        detection: place recognition may merge its sessions by a transform close to it."""
        for h in self.refuted:
            if is_guess(h):
                continue
            same_agents = h.target_agents & agents[0] and h.source_agents & agents[1]
            flipped = h.target_agents & agents[1] and h.source_agents & agents[0]
            if not (same_agents or flipped):
                continue
            rel = h.target_from_source.inverse() @ (
                target_from_source if same_agents else target_from_source.inverse()
            )
            if float(np.linalg.norm(rel.t)) < 1.0 and rotation_angle_deg(rel.R) < 5.0:
                return h
        return None

    def add_loop(
        self,
        map_id: int,
        edge: NewEdge,
        record: dict[str, Any],
        fuse: list[tuple[Any, Any]],
        dependent: MergeHypothesis | None = None,
        kind: str = "loop",
    ) -> Evidence:
        ev = Evidence(edge, kind, record, fuse=fuse, dependent=dependent)
        if dependent is not None:
            record["merge_evidence"] = dependent.id
            dependent.record["dependent_loops"] = dependent.record.get("dependent_loops", 0) + 1
        self.edges.setdefault(map_id, []).append(ev)
        return ev

    def add_merge(
        self,
        map_id: int,
        source: int,
        edge: NewEdge | None,
        target_from_source: Sim3,
        agents: tuple[set[str], set[str]],
        record: dict[str, Any],
    ) -> MergeHypothesis:
        """A merge into ``map_id`` (kept frame) of map ``source``; ``agents``: the target's and the
        source's agents at merge time. The maps' kept edges and hypotheses are now the merged map's."""
        self.on_merge(map_id, source)
        hyp = MergeHypothesis(self._next_id, map_id, source, target_from_source,
                              frozenset(agents[1]), frozenset(agents[0]), record, edge)  # fmt: skip
        self._next_id += 1
        record["merge_id"] = hyp.id
        record["on_trial"] = True
        self.merges.setdefault(map_id, []).append(hyp)
        if edge is not None:
            self.edges.setdefault(map_id, []).append(Evidence(edge, "merge", record, hyp))
        return hyp

    def on_merge(self, target: int, source: int) -> None:
        self.edges.setdefault(target, []).extend(self.edges.pop(source, []))
        self.merges.setdefault(target, []).extend(self.merges.pop(source, []))

    def forget_map(self, map_id: int) -> None:
        self.edges.pop(map_id, None)
        self.merges.pop(map_id, None)

    def on_trial(self, map_id: int) -> list[MergeHypothesis]:
        return [h for h in self.merges.get(map_id, []) if not h.confirmed]

    def dependent_on(self, m: Any, a: KfKey, b: KfKey) -> MergeHypothesis | None:
        """The merge on trial that a loop ``a``-``b`` across its sides merely repeats: either end is one of
        the merge's keyframes or covisible with it (the same place, e.g. the rest of a room that looks like
        another). Such a loop is no independent confirmation, nor a separate vote in the pose graph. A
        session guess (``record["by"] == "session_guess"``) saw nothing: every loop across it is evidence."""
        for hyp in self.on_trial(m.id):
            if hyp.edge is None or not hyp.across(a, b) or is_guess(hyp):
                continue
            for end in (hyp.edge.query, hyp.edge.candidate):
                place = {end, *m.covisibility(end)} if end in m.keyframes else {end}
                if a in place or b in place:
                    return hyp
        return None

    def kept_edges(self, map_id: int, keys: Any) -> list[Evidence]:
        """The map's kept edges (not those repeating a merge) whose keyframes are still in it."""
        edges = self.edges.get(map_id, [])
        return [
            ev for ev in edges if ev.dependent is None and ev.edge.candidate in keys and ev.edge.query in keys
        ]

    def held_edges(self, map_id: int, keys: Any) -> list[NewEdge]:
        """The edges the map's last pose graph held: its kept edges (:meth:`kept_edges`) not rejected."""
        return [ev.edge for ev in self.kept_edges(map_id, keys) if not ev.rejected]

    def judge(
        self, map_id: int, judged: list[Evidence], inlier: list[bool], chi2: list[float], confirmations: int
    ) -> Verdict:
        """Record one pose graph's verdict on ``judged`` (flags and whitened squared residuals in order);
        a merge on trial is confirmed by ``confirmations`` kept loops between its sides (a session guess by
        one)."""
        v = Verdict()
        for ev, ok, c2 in zip(judged, inlier, chi2, strict=True):
            ev.judged += 1
            ev.record["chi2"] = c2
            if not ok and not ev.rejected:
                ev.rejected = True
                ev.record["rejected"] = True
                ev.record["reject_reason"] = (
                    f"robust pose graph: the map's other edges contradict it (whitened squared residual "
                    f"{c2:.0f})"
                )
                v.rejected.append(ev)
            elif ok and ev.rejected:
                ev.rejected = False
                ev.record["rejected"] = False
                ev.record.pop("reject_reason", None)
                v.readmitted.append(ev)
        for hyp in self.on_trial(map_id):
            own = [ev for ev in judged if ev.merge is hyp]
            if any(ev.rejected for ev in own):
                v.contradicted.append(hyp)
                continue
            for ev in judged:
                # a rendezvous is an independent measurement between the sides as a loop is
                independent = ev.kind in ("loop", "rendezvous")
                if independent and not ev.rejected and hyp.across(ev.edge.candidate, ev.edge.query):
                    hyp.confirmations.add(ev.edge.query)
            hyp.record["confirmations"] = len(hyp.confirmations)
            # a session guess is no visual match that a look-alike place could have made: one loop kept
            # with it (itself confirmed by consecutive detections) is the independent check it needs
            need = 1 if is_guess(hyp) else confirmations
            if own and len(hyp.confirmations) >= need:
                hyp.confirmed = True
                hyp.record["on_trial"] = False
                v.confirmed.append(hyp)
        return v

    def split(self, map_id: int, new_id: int, hyp: MergeHypothesis) -> list[Evidence]:
        """After ``hyp`` was undone (its source agents now in map ``new_id``): the edges within each side
        stay with it, those across are dropped and returned; the hypothesis is gone."""
        side = hyp.source_agents
        stay: list[Evidence] = []
        move: list[Evidence] = []
        dropped: list[Evidence] = []
        for ev in self.edges.pop(map_id, []):
            a, b = ev.edge.candidate[0] in side, ev.edge.query[0] in side
            (move if a and b else stay if not a and not b else dropped).append(ev)
        self.edges[map_id], self.edges[new_id] = stay, move
        self.refuted.append(hyp)
        hyps = [h for h in self.merges.pop(map_id, []) if h is not hyp]
        self.merges[map_id] = [h for h in hyps if not h.source_agents <= side]
        self.merges[new_id] = [h for h in hyps if h.source_agents <= side]
        return dropped
