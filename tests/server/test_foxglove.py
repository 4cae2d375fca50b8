"""Foxglove: a real `hivemap server --foxglove-port` with two agents (one closes a loop), checked by a
WebSocket client speaking Foxglove's protocol (advertised channels, one decoded message of each); then
`hivemap export mcap` of the stopped server's map, read back with the `mcap` library."""

from __future__ import annotations

import base64
import json
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from agent_client import SyncAgent
from srv_helpers import TOKENS, ServerProcess, free_port, write_config
from websockets.sync.client import connect

pytest.importorskip("mcap_protobuf")  # dev dependency: decodes the protobuf schemas the SDK advertises


def _decoder(schema_name: str, schema_b64_or_bytes: str | bytes) -> Any:
    from mcap.records import Schema
    from mcap_protobuf.decoder import DecoderFactory

    data = (
        base64.b64decode(schema_b64_or_bytes) if isinstance(schema_b64_or_bytes, str) else schema_b64_or_bytes
    )
    dec = DecoderFactory().decoder_for(
        "protobuf", Schema(id=1, name=schema_name, encoding="protobuf", data=data)
    )
    assert dec is not None
    return dec


def _streams() -> dict[str, list[Any]]:
    """ugv1: two passes over the same place (the second drifted: a loop closure); uav1 elsewhere."""
    from hivemap.server.backend_synth import loop_passes
    from hivemap.server.loadgen import synthetic_stream

    first, second, _, _ = loop_passes()
    uav, _ = synthetic_stream("uav1", 6, seed=3)
    return {"ugv1": first + second, "uav1": uav}


EXPECTED = {
    "/tf": "foxglove.FrameTransforms",
    "/scene": "foxglove.SceneUpdate",
    "/events": "foxglove.Log",
    "/agents/ugv1/trajectory": "foxglove.PosesInFrame",
    "/agents/ugv1/pose": "foxglove.PoseInFrame",
    "/agents/uav1/trajectory": "foxglove.PosesInFrame",
    "/agents/uav1/pose": "foxglove.PoseInFrame",
}


@pytest.fixture(scope="module")
def mission(tmp_path_factory: pytest.TempPathFactory) -> Any:
    tmp = tmp_path_factory.mktemp("fox")
    fox_port = free_port()
    cfg = write_config(tmp / "server.toml", backend=True, foxglove_port=fox_port)
    server = ServerProcess(tmp / "data", cfg).start()
    try:
        for agent_id, msgs in _streams().items():
            kind = "ugv" if agent_id.startswith("ugv") else "uav"
            with SyncAgent(server.ws_url, agent_id, TOKENS[agent_id], kind=kind) as agent:
                agent.welcome()
                assert agent.send_all(msgs)[1] == []
        server.wait_backend_idle()
        yield server, fox_port
    finally:
        server.stop()


def test_foxglove_websocket_advertises_and_sends_the_mission(mission: Any) -> None:
    server, fox_port = mission
    maps = {m["id"]: m for m in server.json("/maps")["maps"]}
    loops = [e for e in server.json("/events", limit=1000)["events"] if e["kind"] == "loop"]
    assert len(maps) == 2 and loops
    expected = dict(EXPECTED, **{f"/maps/{i}/points": "foxglove.PointCloud" for i in maps})
    with connect(f"ws://127.0.0.1:{fox_port}", subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
        assert ws.subprotocol == "foxglove.sdk.v1"
        info = json.loads(ws.recv(timeout=5))
        assert info["op"] == "serverInfo" and info["name"] == "hivemap"
        channels: dict[int, dict[str, Any]] = {}
        got: dict[str, Any] = {}
        deadline = time.monotonic() + 15
        while set(got) != set(expected) and time.monotonic() < deadline:
            try:
                frame = ws.recv(timeout=1)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                op = json.loads(frame)
                if op["op"] == "advertise":
                    new = [c for c in op["channels"] if c["topic"] in expected]
                    for c in new:
                        channels[c["id"]] = c
                    subs = [{"id": c["id"], "channelId": c["id"]} for c in new]
                    if subs:
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                continue
            opcode, sub_id, _log_time = struct.unpack_from("<BIQ", frame)
            assert opcode == 1
            c = channels[sub_id]
            got.setdefault(c["topic"], _decoder(c["schemaName"], c["schema"])(frame[13:]))
    assert {c["topic"]: c["schemaName"] for c in channels.values()} == expected
    assert set(got) == set(expected)

    tf = {(t.parent_frame_id, t.child_frame_id) for t in got["/tf"].transforms}
    ugv_map = next(i for i, m in maps.items() if "ugv1" in m["agents"])
    uav_map = next(i for i in maps if i != ugv_map)
    # the UGV's map defines `global`; the other map hangs under it until merged
    assert ("global", f"map{uav_map}") in tf and ("global", "ugv1/local") in tf
    assert (f"map{uav_map}", "uav1/local") in tf
    traj = got["/agents/ugv1/trajectory"]
    assert traj.frame_id == "global" and len(traj.poses) == maps[ugv_map]["keyframes"]
    assert got["/agents/uav1/pose"].frame_id == f"map{uav_map}"
    cloud = got[f"/maps/{ugv_map}/points"]
    assert cloud.point_stride == 12 and len(cloud.data) == 12 * maps[ugv_map]["points"]
    xyz = np.frombuffer(cloud.data, "<f4").reshape(-1, 3)
    assert np.isfinite(xyz).all() and np.ptp(xyz, axis=0).max() > 5.0
    ents = {e.id: e for e in got["/scene"].entities}
    assert {"agent/ugv1", "agent/uav1", f"map{ugv_map}/loops"} <= set(ents)
    # trajectory line + 8 frustum edges (16 endpoints) per keyframe
    strip, frustums = ents["agent/ugv1"].lines
    assert len(strip.points) == maps[ugv_map]["keyframes"] and len(frustums.points) == 16 * len(strip.points)
    assert got["/events"].name.startswith("hivemap.")


def test_export_mcap_reads_back(mission: Any, tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    server, _ = mission
    maps = {m["id"]: m for m in server.json("/maps")["maps"]}
    ugv_map = next(i for i, m in maps.items() if "ugv1" in m["agents"])
    server.stop()
    out = tmp_path / "map.mcap"
    cmd = [sys.executable, "-m", "hivemap.cli.main", "export", "mcap", "--map", str(ugv_map),
           "--data-dir", str(server.data_dir), "--out", str(out)]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    msgs: dict[str, list[Any]] = {}
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        schemas = {c.topic: s.name for s, c, _ in _schema_channels(reader)}
        for _schema, channel, _message, decoded in reader.iter_decoded_messages():
            msgs.setdefault(channel.topic, []).append(decoded)
    assert schemas[f"/maps/{ugv_map}/points"] == "foxglove.PointCloud"
    assert schemas["/agents/ugv1/trajectory"] == "foxglove.PosesInFrame"
    assert "/agents/uav1/pose" not in msgs  # only the exported map
    (cloud,) = msgs[f"/maps/{ugv_map}/points"]
    assert len(cloud.data) == 12 * maps[ugv_map]["points"] and cloud.frame_id == "global"
    (traj,) = msgs["/agents/ugv1/trajectory"]
    assert len(traj.poses) == maps[ugv_map]["keyframes"]
    (scene,) = msgs["/scene"]
    assert f"map{ugv_map}/loops" in {e.id for e in scene.entities}
    (tf,) = msgs["/tf"]
    assert ("global", "ugv1/local") in {(t.parent_frame_id, t.child_frame_id) for t in tf.transforms}
    missing = subprocess.run([*cmd[:6], "999", *cmd[7:]], capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and "no map 999" in missing.stderr


def _schema_channels(reader: Any) -> list[tuple[Any, Any, None]]:
    summary = reader.get_summary()
    assert summary is not None
    return [(summary.schemas[c.schema_id], c, None) for c in summary.channels.values()]
