"""eval.trajectory.loop_errors: a loop event's measured relative pose against ground truth."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from hivemap.eval.globalmap import loop_errors
from hivemap.eval.trajectory import trajectory_from_poses
from hivemap.maps.geometry import se3


def test_loop_error_is_the_measurements_offset_from_the_true_relative_pose() -> None:
    t = np.arange(0.0, 10.0, 0.5)
    # two agents' cameras: "a" drives along x, "b" flies 3 m higher along y, both turned by some yaw
    a = np.array([se3(Rotation.from_euler("z", 0.1 * i).as_matrix(), np.array([i, 0.0, 0.0])) for i in t])
    b = np.array(
        [se3(Rotation.from_euler("zx", [0.3, -0.7]).as_matrix(), np.array([0.0, i, 3.0])) for i in t]
    )
    gt = {"a": trajectory_from_poses(t, a), "b": trajectory_from_poses(t, b)}
    true = np.linalg.inv(b[4]) @ a[6]  # cam_b(t=2.0)_from_cam_a(t=3.0)
    # measured: the query camera 0.1 m too low in the world, and turned by 0.5 deg
    world_shift = np.array([0.0, 0.0, -0.1])
    meas = true.copy()
    meas[:3, 3] += b[4][:3, :3].T @ world_shift
    meas[:3, :3] = meas[:3, :3] @ Rotation.from_euler("x", 0.5, degrees=True).as_matrix()
    first = {"query": ["a", 6], "candidate": ["b#2", 4], "query_t": 3.0, "candidate_t": 2.0}
    # the same loop turned 0.5 deg about the vertical instead (a's camera z is the world's up): no tilt
    yawed = true @ se3(Rotation.from_euler("z", 0.5, degrees=True).as_matrix(), np.zeros(3))
    late = {"query": ["a", 1], "candidate": ["b", 1], "query_t": 99.0, "candidate_t": 0.0}
    events = [
        {"kind": "loop", "data": {**first, "candidate_from_query": meas.tolist(), "n_inliers": 50}},
        {"kind": "loop", "data": {**first, "candidate_from_query": yawed.tolist()}},
        {"kind": "loop", "data": {"refused": True, "n_inliers": 9}},  # refused loops carry no measurement
        {"kind": "loop", "data": {**late, "candidate_from_query": true.tolist()}},  # no ground truth at 99 s
    ]
    e, y = loop_errors(events, gt)
    assert (e["query"], e["candidate"]) == ("a", "b")
    assert abs(e["trans_err_m"] - 0.1) < 1e-9 and abs(e["vertical_err_m"] + 0.1) < 1e-9
    assert abs(e["rot_err_deg"] - 0.5) < 1e-6 and abs(e["tilt_err_deg"] - 0.5) < 1e-6  # about a's x: all tilt
    assert abs(y["rot_err_deg"] - 0.5) < 1e-6 and y["tilt_err_deg"] < 1e-4  # acos: ~1e-6 deg near 0
    assert abs(e["distance_m"] - float(np.linalg.norm(true[:3, 3]))) < 1e-9


def test_merges_are_measured_like_loops() -> None:
    """A ``merge_detail`` event with its measured relative pose is listed too, as kind "merge"."""
    t = np.arange(0.0, 4.0, 0.5)
    a = np.array([se3(np.eye(3), np.array([i, 0.0, 0.0])) for i in t])
    b = np.array([se3(Rotation.from_euler("z", 0.4).as_matrix(), np.array([0.0, i, 3.0])) for i in t])
    gt = {"a": trajectory_from_poses(t, a), "b": trajectory_from_poses(t, b)}
    meas = np.linalg.inv(b[2]) @ a[1]
    meas[:3, 3] += [0.3, 0.0, 0.0]  # 0.3 m off in the candidate camera
    merge = {"query": ["a", 2], "candidate": ["b", 4], "query_t": 0.5, "candidate_t": 1.0}
    events = [
        {"kind": "merge_detail", "data": {**merge, "candidate_from_query": meas.tolist(), "n_inliers": 80}},
        {"kind": "merge_detail", "data": {"by": "start_pose", "query_t": None}},  # old record: no measurement
    ]
    (e,) = loop_errors(events, gt)
    assert e["kind"] == "merge" and (e["query"], e["candidate"]) == ("a", "b")
    assert abs(e["trans_err_m"] - 0.3) < 1e-9 and e["rot_err_deg"] < 1e-6 and e["n_inliers"] == 80


def test_loops_and_merges_the_server_took_back_are_left_out() -> None:
    """A loop the robust pose graph rejected after the fact (and did not readmit) and a merge that was
    undone are not accepted loops or merges; a readmitted loop is."""
    t = np.arange(0.0, 4.0, 0.5)
    a = np.array([se3(np.eye(3), np.array([i, 0.0, 0.0])) for i in t])
    gt = {"a": trajectory_from_poses(t, a)}
    rel = (np.linalg.inv(a[1]) @ a[6]).tolist()  # exact for the query at 3.0 s
    rel_back = (np.linalg.inv(a[1]) @ a[7]).tolist()  # exact for the query at 3.5 s
    gone = {"query": ["a", 6], "candidate": ["a", 1], "query_t": 3.0, "candidate_t": 0.5}
    back = {"query": ["a", 7], "candidate": ["a", 1], "query_t": 3.5, "candidate_t": 0.5}
    merge = {"query": ["a", 6], "candidate": ["a", 1], "query_t": 3.0, "candidate_t": 0.5, "merge_id": 4}
    events = [
        {"kind": "loop", "data": {**gone, "candidate_from_query": rel}},
        {"kind": "loop", "data": {**back, "candidate_from_query": rel_back}},
        {"kind": "merge_detail", "data": {**merge, "candidate_from_query": rel}},
        {"kind": "loop_rejected", "data": dict(gone)},
        {"kind": "loop_rejected", "data": dict(back)},
        {"kind": "loop_readmitted", "data": dict(back)},
        {"kind": "merge_undone", "data": {"merge_id": 4, "reason": "gnss"}},
    ]
    (e,) = loop_errors(events, gt)
    assert e["kind"] == "loop" and e["distance_m"] > 2.0 and e["trans_err_m"] < 1e-9
    # the readmitted loop is the one at 3.5 s: 3 m from its candidate
    assert abs(e["distance_m"] - 3.0) < 1e-9
