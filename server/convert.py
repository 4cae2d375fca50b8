"""Wire messages (hivemap.protocol) -> map objects (hivemap.maps), in the frame of the map that holds them."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from hivemap.maps import Keyframe as MapKeyframe
from hivemap.maps import MapPoint
from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import Sim3
from hivemap.protocol import Keyframe, MapPoints


def fold_agent_id(agent_id: str, session: int) -> str:
    """The map-model agent id of one agent session: ``uav1`` for session 0, ``uav1#2`` for session 2."""
    return agent_id if session == 0 else f"{agent_id}#{session}"


def split_folded(folded: str) -> tuple[str, int]:
    agent_id, _, session = folded.partition("#")
    return agent_id, int(session) if session else 0


def keyframe_from_msg(
    folded: str,
    msg: Keyframe,
    camera: PinholeCamera,
    global_from_vio: Sim3,
    stereo_baseline: float | None = None,
) -> MapKeyframe:
    """A map keyframe from a wire keyframe, its pose moved from the VIO frame by ``global_from_vio``;
    its stereo observations kept when the agent's hello gave ``stereo_baseline``."""
    T = np.array(msg.world_from_cam, dtype=np.float64)
    return MapKeyframe(
        agent_id=folded,
        id=int(msg.kf_id),
        timestamp=float(msg.timestamp),
        world_from_cam=global_from_vio.transform_pose(T),
        camera=camera,
        keypoints=np.array(msg.keypoints, dtype=np.float32),
        octaves=np.array(msg.octaves, dtype=np.uint8),
        descriptors=np.array(msg.descriptors, dtype=np.uint8),
        point_ids=np.array(msg.point_ids, dtype=np.int64),
        gnss_enu=None if msg.gnss_enu is None else np.array(msg.gnss_enu, dtype=np.float64),
        gnss_cov=None if msg.gnss_cov is None else np.array(msg.gnss_cov, dtype=np.float64),
        up_cam=None if msg.up_cam is None else np.array(msg.up_cam, dtype=np.float64),
        u_right=None if msg.u_right is None or stereo_baseline is None else msg.u_right,
        stereo_baseline=stereo_baseline,
        odom_sigma=None if msg.odom_sigma is None else np.array(msg.odom_sigma, dtype=np.float64),
        track_sigma=None if msg.track_sigma is None else np.array(msg.track_sigma, dtype=np.float64),
        vio_from_cam=np.array(msg.world_from_cam, dtype=np.float64),
    )


def points_from_msg(
    folded: str, msg: MapPoints, rows: NDArray[np.int64], global_from_vio: Sim3
) -> list[MapPoint]:
    """Map points for some rows of a wire ``map_points`` message, moved by ``global_from_vio``."""
    xyz = global_from_vio.apply(np.asarray(msg.xyz, dtype=np.float64)[rows])
    desc = np.array(msg.descriptors[rows], dtype=np.uint8)
    ids = msg.ids[rows].tolist()
    return [
        MapPoint(agent_id=folded, id=int(pid), xyz=xyz[i], descriptor=desc[i])  # MapPoint copies
        for i, pid in enumerate(ids)
    ]
