"""The agent's second stage judged alone: record its inputs once, replay them under other options in seconds.

``record`` replays one agent dataset offline (as ``hivemap agent --offline``) and keeps every call the
runner made to its own second stage (keyframes with the tracking's relative poses and covariances, IMU
samples, the local BA's pose updates, GNSS fixes) with the stage's options. The front-end is
deterministic offline, so a recording stands for that agent's single run on that world.

``replay`` runs the recorded calls through a fresh :class:`~hivemap.client.second_stage.SecondStage` with
the recorded options and with each ``--set`` variant, and prints per recording the keyframes' ATE (evo,
SE(3), body frame against the dataset's ground truth) for the tracking (VIO), the stage at the end
(smoothed) and the stage as each keyframe was added (causal: what the agent streams), and what the server
holds when the agent also resends the keyframes the smoothing moved (``--resend-m``/``--resend-deg``).

    .venv/bin/python bench/second_stage.py record --dataset data/factory02/uav1 --out runs/stage/f02-uav1.pkl
    .venv/bin/python bench/second_stage.py replay runs/stage/*.pkl --set between_huber=0 \\
        --set imu.accelerometer_random_walk=0.003
"""

from __future__ import annotations

import argparse
import copy
import pickle
import sys
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

RECORDED = ("add_keyframe", "add_imu", "update_vio_poses", "add_gnss")


def cmd_record(a: argparse.Namespace) -> None:
    import hivemap.client.second_stage as second_stage
    from hivemap.client.replay_io import GnssMode
    from hivemap.client.runner import RunnerOptions, run_offline

    log: dict[str, Any] = {"dataset": str(Path(a.dataset).resolve()), "options": None, "calls": []}
    base = second_stage.SecondStage

    class Recording(base):  # type: ignore[misc, valid-type]
        """The runner's own stage (the first one built); every later instance records nothing."""

        def __init__(self, options: Any = None) -> None:
            super().__init__(options)
            self._rec = log["options"] is None
            if self._rec:
                log["options"] = self.options

    def recorder(name: str) -> Any:
        method = getattr(base, name)

        def call(self: Any, *args: Any, **kw: Any) -> Any:
            if self._rec:
                log["calls"].append((name, copy.deepcopy(args), copy.deepcopy(kw)))
            return method(self, *args, **kw)

        return call

    for name in RECORDED:
        setattr(Recording, name, recorder(name))
    second_stage.SecondStage = Recording  # the runner imports it from the package when it starts
    try:
        with tempfile.TemporaryDirectory() as tmp:
            options = RunnerOptions(gnss=GnssMode(a.gnss), progress=not a.no_progress)
            run_offline(a.dataset, a.run_out or tmp, options)
    finally:
        second_stage.SecondStage = base
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    with open(a.out, "wb") as f:
        pickle.dump(log, f)
    print(f"{len(log['calls'])} calls of {a.dataset}'s second stage -> {a.out}")


def _variant(options: Any, sets: list[str]) -> Any:
    """``options`` with ``name=value`` items applied (``imu.name`` for the IMU options; values are Python
    literals, e.g. ``0.003``, ``None``, ``(0.05, 0.01, 0.1)``)."""
    import ast

    kw: dict[str, Any] = {}
    imu: dict[str, Any] = {}
    for item in sets:
        name, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"--set {item!r}: expected name=value")
        (imu if name.startswith("imu.") else kw)[name.removeprefix("imu.")] = ast.literal_eval(value)
    if imu:
        if options.imu is None:
            raise SystemExit("imu.* given for a recording without IMU options")
        kw["imu"] = replace(options.imu, **imu)
    return replace(options, **kw)


def server_priors(st: Any, server: Any, body_from_cam: Any, stride: int) -> dict[int, Any]:
    """The server's keyframe poses (``server``: evo trajectory of cam0 poses in its global frame) as the
    stage's local body poses for every ``stride``-th keyframe, as a correction carries them: placed by
    the rigid fit of the server's keyframes onto the stage's (the runner uses the server's
    ``global_from_local``; the co-location offset takes up what either leaves)."""
    from hivemap.client.second_stage.factors import rigid_alignment

    ids = list(st.keyframe_ids)
    ts, own = st.keyframe_poses()
    st_, T_gc = np.asarray(server.timestamps), np.asarray(server.poses_se3)
    j = np.clip(np.searchsorted(st_, ts), 1, len(st_) - 1)
    j = np.where(np.abs(st_[j - 1] - ts) < np.abs(st_[j] - ts), j - 1, j)
    ok = np.abs(st_[j] - ts) < 0.02
    glob = {ids[i]: T_gc[j[i]] @ np.linalg.inv(body_from_cam) for i in np.flatnonzero(ok)}
    if len(glob) < 3:
        raise SystemExit("the server estimate shares fewer than 3 keyframe times with the recording")
    row = {k: i for i, k in enumerate(ids)}
    keys = sorted(glob, key=row.__getitem__)
    A = rigid_alignment(
        np.array([glob[k][:3, 3] for k in keys]), np.array([own[row[k]][:3, 3] for k in keys])
    )
    return {k: A @ glob[k] for k in keys[::stride]}


def replay(
    rec: dict[str, Any],
    options: Any,
    resend: tuple[float, float] | None = None,
    priors: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """(timestamps, poses) of the VIO, the stage at the end and the stage as each keyframe was added;
    with ``resend`` (``RunnerOptions.stream_resend``), also what a server that is sent each keyframe and
    then its resends (:meth:`StreamedPoses.refresh`) ends up holding, and ``resent``: how many resends."""
    from types import SimpleNamespace

    from hivemap.client.odometry import StreamedPoses, stage_from_vio
    from hivemap.client.second_stage import SecondStage

    st = SecondStage(options)
    streamed = StreamedPoses(lambda _s, k: stage_from_vio(st, k))
    none = np.zeros(0, np.int64)
    causal_t, causal_T = [], []
    resent = 0
    for name, args, kw in rec["calls"]:
        getattr(st, name)(*args, **kw)
        if name == "add_keyframe":
            causal_t.append(float(args[1]))
            causal_T.append(st.keyframe_pose(args[0]))
            if resend is not None:
                ev = SimpleNamespace(session=0, kf_id=args[0], world_from_cam=st.vio_pose(args[0]),
                                     new_point_ids=none, new_point_xyz=np.zeros((0, 3)),
                                     prev_session_from_world=None)  # fmt: skip
                streamed.keyframe(ev)
                resent += sum(len(kf_ids) for _, kf_ids, _ in streamed.refresh(*resend))
    ts, poses = st.keyframe_poses()
    vio = np.array([st.vio_pose(k) for k in st.keyframe_ids])
    out: dict[str, Any] = {
        "vio": (ts, vio),
        "final": (ts, poses),
        "causal": (np.array(causal_t), np.array(causal_T)),
    }
    if resend is not None:
        held = np.array([streamed.sent_pose(0, k) for k in st.keyframe_ids])
        out["resent"] = (ts, held)
        out["n_resent"] = resent
    if priors is not None:
        # the server's final estimate as one correction, at each of the given sigmas (rad, m)
        local = server_priors(st, priors["server"], priors["body_from_cam"], priors["stride"])
        for rot, trans in priors["sigmas"]:
            cov = np.diag([rot**2] * 3 + [trans**2] * 3)
            st.set_colocations({k: (T, cov) for k, T in local.items()})
            out[f"prior {rot:g}/{trans:g}"] = st.keyframe_poses()
        ts_s = np.asarray(priors["server"].timestamps)
        out["server"] = (
            ts_s,
            np.asarray(priors["server"].poses_se3) @ np.linalg.inv(priors["body_from_cam"]),
        )
    return out


def cmd_replay(a: argparse.Namespace) -> None:
    from hivemap.eval.trajectory import ate, groundtruth_trajectory, read_tum, trajectory_from_poses

    variants = [("recorded", [])] + [(s, s.split(",")) for s in a.set]
    if a.server and len(a.server) != len(a.recordings):
        raise SystemExit("--server: one server estimate per recording, in the same order")
    sigmas = [tuple(float(x) for x in s.split(",")) for s in a.sigma]
    resend = (a.resend_m, a.resend_deg) if a.resend_m > 0 else None
    extra = f" {'resent':>6s} {'n':>5s} {'kfs':>5s}" if resend else ""
    head = f"{'recording':28s} {'variant':36s} {'vio':>6s} {'final':>6s} {'causal':>6s}{extra}"
    print(f"{head}  (keyframe ATE, m)")
    for path in a.recordings:
        with open(path, "rb") as f:
            rec = pickle.load(f)
        gt = groundtruth_trajectory(rec["dataset"])
        priors = None
        if a.server:
            from hivemap.client.dataset import load_dataset

            srv = a.server[a.recordings.index(path)]
            priors = {"server": read_tum(srv), "stride": a.stride, "sigmas": sigmas,
                      "body_from_cam": load_dataset(rec["dataset"]).T_BS["cam0"]}  # fmt: skip
        for label, sets in variants:
            out = replay(rec, _variant(rec["options"], sets), resend, priors)
            n_resent = out.pop("n_resent", None)
            err = {k: ate(trajectory_from_poses(t, T), gt, "se3", max_diff=0.02).stats.rmse
                   for k, (t, T) in out.items()}  # fmt: skip
            row = f"{err['vio']:6.3f} {err['final']:6.3f} {err['causal']:6.3f}"
            if resend is not None:
                row += f" {err['resent']:6.3f} {n_resent:5d} {len(out['final'][0]):5d}"
            row += "".join(f"  {k} {v:.3f}" for k, v in err.items() if k.startswith(("prior", "server")))
            print(f"{Path(path).stem:28s} {label:36s} {row}", flush=True)


def main() -> None:
    from hivemap.client.runner_options import RunnerOptions

    resend = RunnerOptions().stream_resend or (0.0, 0.0)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record", help="run an agent offline and keep its second stage's inputs")
    r.add_argument("--dataset", required=True, help="an agent's dataset folder (EuRoC layout)")
    r.add_argument("--out", required=True, help="the recording (.pkl)")
    r.add_argument("--gnss", default="denied", help="GNSS mode, as `hivemap agent --gnss` (default: denied)")
    r.add_argument("--run-out", help="keep the run's outputs here (default: discarded)")
    r.add_argument("--no-progress", action="store_true")
    p = sub.add_parser("replay", help="replay recordings with the recorded options and variants")
    p.add_argument("recordings", nargs="+")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE[,NAME=VALUE]",
                   help="a variant of the stage's options (repeat for more variants)")  # fmt: skip
    p.add_argument("--resend-m", type=float, default=resend[0],
                   help="also replay the agent's resends (RunnerOptions.stream_resend; 0: off): 'resent' "
                        "is the ATE of what the server then holds, 'n' the resends, "
                        "'kfs' the keyframes")  # fmt: skip
    p.add_argument("--resend-deg", type=float, default=resend[1])
    p.add_argument("--server", action="append", default=[], metavar="TUM",
                   help="a server's final estimate of the recorded agent (cam0 poses, as "
                        "`server_global.tum`), one per recording: fused as one correction's co-location "
                        "priors")  # fmt: skip
    p.add_argument("--stride", type=int, default=12, help="priors on every stride-th keyframe (default 12)")
    p.add_argument(
        "--sigma",
        action="append",
        default=[],
        metavar="RAD,M",
        help="co-location prior sigmas to try (repeat; default: RunnerOptions.colocation_sigma)",
    )
    if not sys.argv[1:]:  # `make bench` runs every bench bare
        print("bench/second_stage.py: on request only (`record`, then `replay`; see --help)")
        return
    a = ap.parse_args()
    if a.cmd == "replay" and not a.sigma:
        a.sigma = [",".join(str(x) for x in RunnerOptions().colocation_sigma)]
    cmd_record(a) if a.cmd == "record" else cmd_replay(a)


if __name__ == "__main__":
    main()
