"""The server's Prometheus metrics (``GET /metrics``): agents, messages, back-end figures, storage."""

from __future__ import annotations

from hivemap.server.core import HiveServer
from hivemap.server.metrics import MetricsWriter


def metrics(server: HiveServer) -> str:
    w = MetricsWriter()
    agents_ = list(server.agents.values())
    w.family("hivemap_up", "gauge", "1 while the server runs.", [(None, 1)])
    w.family(
        "hivemap_agents_connected",
        "gauge",
        "Agents with an open connection.",
        [(None, sum(a.connection is not None for a in agents_))],
    )
    w.family(
        "hivemap_messages_received_total",
        "counter",
        "Data messages received, by agent and type.",
        [({"agent": a.agent_id, "type": t}, n) for a in agents_ for t, n in sorted(a.received.items())],
    )
    w.family(
        "hivemap_duplicate_messages_total",
        "counter",
        "Messages or items ignored as already received.",
        [({"agent": a.agent_id}, a.duplicates) for a in agents_],
    )
    w.family(
        "hivemap_message_errors_total",
        "counter",
        "Messages refused with an error reply.",
        [({"agent": a.agent_id}, a.errors) for a in agents_],
    )
    w.family(
        "hivemap_rejected_frames_total",
        "counter",
        "Frames that failed to decode (any connection).",
        [(None, server.rejected_frames)],
    )
    w.family(
        "hivemap_bytes_received_total",
        "counter",
        "Bytes received from each agent.",
        [({"agent": a.agent_id}, a.bandwidth.up.total) for a in agents_],
    )
    w.family(
        "hivemap_bytes_sent_total",
        "counter",
        "Bytes sent to each agent.",
        [({"agent": a.agent_id}, a.bandwidth.down.total) for a in agents_],
    )
    w.family(
        "hivemap_agent_last_seq",
        "gauge",
        "Highest seq durably stored per agent.",
        [({"agent": a.agent_id}, a.last_seq) for a in agents_],
    )
    w.family(
        "hivemap_pending_keyframes",
        "gauge",
        "Keyframes waiting for their map points.",
        [({"agent": a.agent_id}, server.pending_count(a)) for a in agents_],
    )
    ms = sorted(server.stack.maps.items())
    w.family("hivemap_maps", "gauge", "Maps in the map stack.", [(None, len(ms))])
    w.family(
        "hivemap_map_keyframes",
        "gauge",
        "Keyframes per map.",
        [({"map": str(i)}, len(m.keyframes)) for i, m in ms],
    )
    w.family(
        "hivemap_map_points",
        "gauge",
        "Map points per map.",
        [({"map": str(i)}, len(m.points)) for i, m in ms],
    )
    wr = server.writer
    w.family("hivemap_store_commits_total", "counter", "SQLite commits.", [(None, wr.commits)])
    w.family("hivemap_store_operations_total", "counter", "Store operations.", [(None, wr.ops)])
    w.family(
        "hivemap_store_commit_seconds_total", "counter", "Time spent committing.", [(None, wr.commit_seconds)]
    )
    w.family(
        "hivemap_events_total",
        "counter",
        "Events by kind.",
        [({"kind": k}, n) for k, n in sorted(server.events.counts.items())],
    )
    w.histogram(
        "hivemap_ack_latency_seconds", "From a frame's arrival to its ack being queued.", server.ack_latency
    )
    return w.render()
