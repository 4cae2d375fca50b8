"""The team benchmark's keyframe streams (``bench/team.py``): ``record`` keeps a finished run's agents'
outboxes, ``make_streams`` turns them into N shifted, re-textured copies of the team, each message at its
recorded time."""

from __future__ import annotations

import json
import sqlite3
import uuid
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from hivemap.protocol import Hello, Keyframe, MapPoints, Message, PoseUpdates, Rendezvous, decode, encode

KM = 1000.0


def record(scenario_dir: Path, run_dir: Path, out: Path) -> None:
    """Copy each agent's outbox frames and hello fields from a finished run into ``out``."""
    from hivemap.client.dataset import load_dataset, load_scenario

    man = load_scenario(scenario_dir)
    out.mkdir(parents=True, exist_ok=True)
    agents = []
    for a in man.agents:
        box = run_dir / a.id / "outbox.sqlite"
        if not box.exists():
            raise SystemExit(f"error: {box} missing (run-dir must hold one outbox per agent)")
        src = sqlite3.connect(f"file:{box}?mode=ro", uri=True)
        dst = out / f"{a.id}.sqlite"
        dst.unlink(missing_ok=True)
        src.execute("VACUUM INTO ?", (str(dst),))
        src.close()
        ds = load_dataset(scenario_dir / a.id)
        T_BS = getattr(ds, "T_BS", {}) or {}
        lever = None
        if "gnss0" in T_BS and "cam0" in T_BS:
            lever = (np.linalg.inv(np.asarray(T_BS["cam0"])) @ np.asarray(T_BS["gnss0"]))[:3, 3].tolist()
        # the hello's stereo baseline: without it the server drops the keyframes' stereo observations
        # (no weld, no stereo BA), and the replay would measure a lighter server than the agents meet
        baseline = None if getattr(ds, "rig", None) is None else float(ds.rig.baseline)
        agents.append(
            {
                "agent_id": a.id,
                "kind": a.kind,
                "camera": ds.camera.to_dict(),
                "cam_from_antenna": lever,
                "stereo_baseline": baseline,
            }
        )
    # the true start configuration: cam0's pose at each agent's first frame (as the experiment runner's)
    starts = {}
    for a in man.agents:
        ds = load_dataset(scenario_dir / a.id)
        T = np.asarray(ds.groundtruth.world_from_body[0]) @ np.asarray(ds.T_BS["cam0"])
        starts[a.id] = T.tolist()
    meta = {
        "scenario_dir": str(scenario_dir),
        "run_dir": str(run_dir),
        "agents": agents,
        "start_poses": starts,
    }
    (out / "team.json").write_text(json.dumps(meta, indent=1))
    n = {a["agent_id"]: _count_keyframes(out / f"{a['agent_id']}.sqlite") for a in agents}
    print(f"recorded {len(agents)} agents into {out}: keyframes {n}")


def _frames(path: Path) -> list[bytes]:
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    rows = db.execute("SELECT frame FROM outbox ORDER BY seq").fetchall()
    db.close()
    return [bytes(r[0]) for r in rows]


def _count_keyframes(path: Path) -> int:
    return sum(isinstance(decode(f)[1], Keyframe) for f in _frames(path))


# ------------------------------------------------------------------------------------------ copies
def _shift(T: np.ndarray, off: np.ndarray) -> np.ndarray:
    out = np.array(T, dtype=np.float64)
    out[..., :3, 3] += off
    return out


def copy_message(msg: Message, off: np.ndarray, mask: np.ndarray | None, suffix: str = "") -> Message:
    """``msg`` of a copy: shifted by ``off``, descriptors XOR ``mask`` (None: the original team), and an
    observed agent renamed with the copy's ``suffix`` (a copy's agents see their own team's carriers)."""
    if isinstance(msg, Keyframe):
        return replace(
            msg,
            world_from_cam=_shift(msg.world_from_cam, off),
            descriptors=msg.descriptors if mask is None else msg.descriptors ^ mask,
            gnss_enu=None if msg.gnss_enu is None else msg.gnss_enu + off,
        )
    if isinstance(msg, MapPoints):
        return replace(
            msg, xyz=msg.xyz + off, descriptors=msg.descriptors if mask is None else msg.descriptors ^ mask
        )
    if isinstance(msg, PoseUpdates):
        return replace(msg, world_from_cam=_shift(msg.world_from_cam, off), xyz=msg.xyz + off)
    if isinstance(msg, Rendezvous):  # relative poses only: nothing to shift
        return replace(msg, observed_agent=msg.observed_agent + suffix)
    return msg


@dataclass
class Stream:
    """One replayed agent: hello and (send time from the start, encoded frame, is keyframe) in order."""

    agent_id: str
    hello: Hello
    frames: list[tuple[float, bytes, bool]]
    start_pose: list[list[float]]


def _stereo_baseline(rec: Path, meta: dict[str, Any], agent: dict[str, Any]) -> float | None:
    """The agent's stereo baseline as recorded, or, for a recording made before it was kept, from the
    recorded scenario's calibration."""
    if "stereo_baseline" in agent:
        return None if agent["stereo_baseline"] is None else float(agent["stereo_baseline"])
    scen = Path(meta.get("scenario_dir", "")) / agent["agent_id"]
    if not meta.get("scenario_dir") or not scen.is_dir():
        raise SystemExit(
            f"error: {rec / 'team.json'} has no stereo baseline for {agent['agent_id']} and its scenario "
            f"({scen}) is gone: record the team again"
        )
    # the calibration only (the whole dataset would read every IMU sample and frame list)
    from hivemap.client.bag_calib import load_calibration

    rig = load_calibration([scen]).stereo_rig()
    return None if rig is None else float(rig.baseline)


def make_streams(rec: Path, n: int, speed: float, duration_s: float | None) -> list[Stream]:
    meta = json.loads((rec / "team.json").read_text())
    base = meta["agents"]
    decoded = {a["agent_id"]: [decode(f)[1] for f in _frames(rec / f"{a['agent_id']}.sqlite")] for a in base}
    t0 = min(m.timestamp for msgs in decoded.values() for m in msgs if isinstance(m, Keyframe))
    baselines = {a["agent_id"]: _stereo_baseline(rec, meta, a) for a in base}
    streams = []
    for i in range(n):
        a, c = base[i % len(base)], i // len(base)
        off = np.array([c * KM, 0.0, 0.0])
        mask = None if c == 0 else np.random.default_rng(c).integers(0, 256, 32, dtype=np.uint8)
        suffix = "" if c == 0 else f"c{c}"
        aid = a["agent_id"] + suffix
        frames: list[tuple[float, bytes, bool]] = []
        held: list[Message] = []
        session = 0
        for msg in decoded[a["agent_id"]]:
            if isinstance(msg, Keyframe | MapPoints | PoseUpdates) and not frames and not held:
                session = msg.session
            held.append(copy_message(msg, off, mask, suffix))
            if isinstance(msg, Keyframe):
                t = (msg.timestamp - t0) / speed
                if duration_s is not None and t > duration_s:
                    held = []
                    break
                for h in held:
                    frames.append((t, encode(h, len(frames) + 1), isinstance(h, Keyframe)))
                held = []
        t_end = frames[-1][0] if frames else 0.0
        for h in held:  # what followed the last keyframe, each at a seq of its own
            frames.append((t_end, encode(h, len(frames) + 1), False))
        lever = a["cam_from_antenna"]
        lever_a = None if lever is None else np.asarray(lever, dtype=np.float64)
        hello = Hello(aid, a["kind"], a["camera"], f"team-{aid}", 0, session, lever_a, uuid.uuid4().hex,
                      stereo_baseline=baselines[a["agent_id"]])  # fmt: skip
        start = np.asarray(meta["start_poses"][a["agent_id"]], dtype=np.float64)
        streams.append(Stream(aid, hello, frames, _shift(start, off).tolist()))
    return streams


# ------------------------------------------------------------------------------------------ replay
