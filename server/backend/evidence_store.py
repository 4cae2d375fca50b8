"""The evidence book as JSON, kept in the map store's meta table (``META_KEY``) in the same commits as the
maps it describes, so that a restart still judges every loop and still holds merges on trial."""

from __future__ import annotations

from typing import Any

import numpy as np

from hivemap.maps.geometry import Sim3
from hivemap.server.backend.evidence import Evidence, EvidenceBook, MergeHypothesis
from hivemap.server.backend.optimise import NewEdge

META_KEY = "backend_evidence"
VERSION = 1


def _edge(e: NewEdge | None) -> dict[str, Any] | None:
    if e is None:
        return None
    return {"candidate": list(e.candidate), "query": list(e.query), "measured": e.measured.matrix().tolist(),
            "sigma_rot": e.sigma_rot, "sigma_trans": e.sigma_trans,
            "covariance": None if e.covariance is None else np.asarray(e.covariance).tolist()}  # fmt: skip


def _new_edge(d: dict[str, Any] | None) -> NewEdge | None:
    if d is None:
        return None
    measured = Sim3.from_matrix(np.asarray(d["measured"], dtype=np.float64))
    cov = d.get("covariance")
    return NewEdge(
        _kf(d["candidate"]),
        _kf(d["query"]),
        measured,
        float(d["sigma_rot"]),
        float(d["sigma_trans"]),
        None if cov is None else np.asarray(cov, dtype=np.float64),
    )


def _kf(k: Any) -> tuple[str, int]:
    return (str(k[0]), int(k[1]))


def _hyp(h: MergeHypothesis) -> dict[str, Any]:
    return {"id": h.id, "target": h.target, "source": h.source,
            "target_from_source": h.target_from_source.matrix().tolist(),
            "source_agents": sorted(h.source_agents), "target_agents": sorted(h.target_agents),
            "record": h.record, "edge": _edge(h.edge), "confirmed": h.confirmed,
            "confirmations": [list(k) for k in sorted(h.confirmations)]}  # fmt: skip


def _from_hyp(d: dict[str, Any]) -> MergeHypothesis:
    return MergeHypothesis(
        int(d["id"]), int(d["target"]), int(d["source"]),
        Sim3.from_matrix(np.asarray(d["target_from_source"], dtype=np.float64)),
        frozenset(d["source_agents"]), frozenset(d["target_agents"]), dict(d["record"]), _new_edge(d["edge"]),
        {_kf(k) for k in d["confirmations"]}, bool(d["confirmed"]),
    )  # fmt: skip


def to_json(book: EvidenceBook) -> dict[str, Any]:
    """Everything the book holds, JSON-serialisable (copied: safe to hand to the writer thread)."""
    edges = {}
    for mid, evs in book.edges.items():
        edges[str(mid)] = [{"edge": _edge(ev.edge), "kind": ev.kind, "record": dict(ev.record),
                            "merge": None if ev.merge is None else ev.merge.id, "rejected": ev.rejected,
                            "judged": ev.judged, "fuse": [[list(a), list(b)] for a, b in ev.fuse],
                            "fused": ev.fused, "dependent": None if ev.dependent is None else ev.dependent.id}
                           for ev in evs]  # fmt: skip
    return {"version": VERSION, "next_id": book._next_id, "edges": edges,
            "merges": {str(mid): [_hyp(h) for h in hs] for mid, hs in book.merges.items()},
            "refuted": [_hyp(h) for h in book.refuted]}  # fmt: skip


def from_json(d: dict[str, Any] | None) -> EvidenceBook:
    """The book written by :func:`to_json` (an empty one for None); a newer version raises ValueError."""
    book = EvidenceBook()
    if not d:
        return book
    if int(d.get("version", 0)) > VERSION:
        raise ValueError(
            f"back-end evidence version {d.get('version')} is newer than this hivemap's {VERSION}"
        )
    book._next_id = int(d["next_id"])
    by_id: dict[int, MergeHypothesis] = {}
    for mid, hs in d["merges"].items():
        book.merges[int(mid)] = [_from_hyp(h) for h in hs]
        by_id.update({h.id: h for h in book.merges[int(mid)]})
    book.refuted = [_from_hyp(h) for h in d["refuted"]]
    for mid, evs in d["edges"].items():
        out = []
        for e in evs:
            edge = _new_edge(e["edge"])
            assert edge is not None
            merge = by_id.get(e["merge"]) if e["merge"] is not None else None
            dep = by_id.get(e["dependent"]) if e["dependent"] is not None else None
            fuse = [(_kf(a), _kf(b)) for a, b in e["fuse"]]
            out.append(Evidence(edge, e["kind"], dict(e["record"]), merge, bool(e["rejected"]),
                                int(e["judged"]), fuse, bool(e["fused"]), dep))  # fmt: skip
        book.edges[int(mid)] = out
    return book
