"""The map's elements, ``MapPoint`` and ``Keyframe``, keyed ``(agent_id, id)`` (:mod:`.model`)."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator, Sequence
from itertools import repeat
from operator import attrgetter
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import se3_inverse

KfKey = tuple[str, int]
PointKey = tuple[str, int]
F64 = NDArray[np.float64]


def _key(k: Sequence[Any]) -> tuple[str, int]:
    return (str(k[0]), int(k[1]))


class MapPoint:
    """A 3D landmark.

    ``xyz``: f64 (3,) position in the map's frame; ``descriptor``: u8 (32,) representative ORB descriptor;
    ``observations``: keyframe key -> keypoint index (maintained by the ``Map`` once the point is in one).
    """

    __slots__ = ("agent_id", "id", "xyz", "descriptor", "observations")

    def __init__(
        self,
        agent_id: str,
        id: int,
        xyz: ArrayLike,
        descriptor: ArrayLike | None = None,
        observations: dict[KfKey, int] | None = None,
    ) -> None:
        self.agent_id = str(agent_id)
        self.id = int(id)
        self.xyz: F64 = np.array(xyz, dtype=np.float64).reshape(3)
        d = np.zeros(32, np.uint8) if descriptor is None else np.array(descriptor, dtype=np.uint8)
        if d.shape != (32,):
            raise ValueError(f"MapPoint descriptor must have shape (32,), got {d.shape}")
        self.descriptor: NDArray[np.uint8] = d
        self.observations: dict[KfKey, int] = {_key(k): int(v) for k, v in (observations or {}).items()}

    @property
    def key(self) -> PointKey:
        return (self.agent_id, self.id)

    def __repr__(self) -> str:
        n_obs = len(self.observations)
        return f"MapPoint({self.agent_id!r}, {self.id}, xyz={self.xyz.tolist()}, obs={n_obs})"


_OBSERVATIONS = attrgetter("observations")
_XYZ = attrgetter("xyz")


def positions(points: Sequence[MapPoint]) -> F64:
    """The points' ``xyz`` as one (n, 3) array. The helpers below run their loop over the points in C:
    the server moves every point of a map after each optimisation, and a Python loop per point held its
    event loop on large maps."""
    if not points:
        return np.zeros((0, 3))
    return np.concatenate(list(map(_XYZ, points))).astype(np.float64, copy=False).reshape(len(points), 3)


def set_positions(points: Sequence[MapPoint], xyz: F64) -> None:
    """Each point's ``xyz`` to its row of ``xyz`` (n, 3)."""
    deque(map(_SET_XYZ, points, xyz), maxlen=0)


def first_observers(points: Sequence[MapPoint]) -> list[KfKey | None]:
    """Each point's first observation's keyframe (the one whose corrections it follows), or None."""
    return list(map(next, map(iter, map(_OBSERVATIONS, points)), repeat(None)))


_SET_XYZ = cast(Callable[[MapPoint, F64], None], vars(MapPoint)["xyz"].__set__)  # the slot's setter


class Keyframe:
    """A keyframe: pose, camera, ORB features and the map point referenced by each keypoint.

    Arrays: ``world_from_cam`` f64 (4, 4); ``keypoints`` f32 (N, 2) distorted pixels; ``octaves`` u8 (N,);
    ``descriptors`` u8 (N, 32); ``point_ids`` i64 (N,) (-1 = no point); ``gnss_enu`` f64 (3,) or None;
    ``gnss_cov`` f64 (3, 3) or None; ``up_cam`` f64 (3,) or None (the agent's IMU up direction in the
    camera frame); ``u_right`` f32 (N,) or None with ``stereo_baseline`` (m): per keypoint its stereo
    match's u in the virtual rectified right camera (the camera's undistorted pinhole intrinsics, the
    baseline along x), NaN where none (``hivemap.protocol.Keyframe``); None for a monocular keyframe.
    camera frame); ``odom_sigma`` f64 (2,) [m, deg] or None (the error weak or lost tracking added to the
    pose relative to the agent's previous keyframe, ``protocol.Keyframe.odom_sigma``); ``track_sigma`` f64
    (2,) [m, deg] or None (that pose's per-axis sigma as the agent's tracking measured it,
    ``protocol.Keyframe.track_sigma``); ``vio_from_cam`` f64 (4, 4) or None (the pose in the agent's own
    odometry frame as the agent last sent it: its keyframe message or a later pose update; the pose graph's
    odometry edges hold it).

    Point references: keypoint ``i`` references point ``(agent, point_ids[i])`` where ``agent`` is
    ``point_agents.get(i, agent_id)`` (``point_agents`` only lists keypoints that reference another agent's
    point, which happens after fusions). Either pass ``point_ids`` (points of this agent) or ``point_keys``
    (a per-keypoint list of ``(agent, id)`` or None). Inside a ``Map`` change references only through the
    map (``add_observation``, ``remove_observation``, ``fuse_points``) so its indices stay consistent.

    ``parent`` is the spanning-tree parent, maintained by the ``Map`` (None for a root).
    """

    __slots__ = (
        "agent_id",
        "id",
        "timestamp",
        "world_from_cam",
        "camera",
        "keypoints",
        "octaves",
        "descriptors",
        "point_ids",
        "point_agents",
        "gnss_enu",
        "gnss_cov",
        "up_cam",
        "u_right",
        "stereo_baseline",
        "odom_sigma",
        "track_sigma",
        "vio_from_cam",
        "parent",
    )

    def __init__(
        self,
        agent_id: str,
        id: int,
        timestamp: float,
        world_from_cam: ArrayLike,
        camera: PinholeCamera,
        keypoints: ArrayLike,
        octaves: ArrayLike | None = None,
        descriptors: ArrayLike | None = None,
        point_ids: ArrayLike | None = None,
        gnss_enu: ArrayLike | None = None,
        gnss_cov: ArrayLike | None = None,
        *,
        point_keys: Sequence[PointKey | None] | None = None,
        up_cam: ArrayLike | None = None,
        u_right: ArrayLike | None = None,
        stereo_baseline: float | None = None,
        odom_sigma: ArrayLike | None = None,
        track_sigma: ArrayLike | None = None,
        vio_from_cam: ArrayLike | None = None,
    ) -> None:
        self.agent_id = str(agent_id)
        self.id = int(id)
        self.timestamp = float(timestamp)
        self.world_from_cam: F64 = np.array(world_from_cam, dtype=np.float64).reshape(4, 4)
        self.camera = camera
        kp = np.ascontiguousarray(keypoints, dtype=np.float32)
        if kp.size == 0:
            kp = kp.reshape(0, 2)
        if kp.ndim != 2 or kp.shape[1] != 2:
            raise ValueError(f"keypoints must have shape (N, 2), got {kp.shape}")
        n = len(kp)
        self.keypoints: NDArray[np.float32] = kp
        self.octaves: NDArray[np.uint8] = (
            np.zeros(n, np.uint8) if octaves is None else np.ascontiguousarray(octaves, dtype=np.uint8)
        )
        self.descriptors: NDArray[np.uint8] = (
            np.zeros((n, 32), np.uint8)
            if descriptors is None
            else np.ascontiguousarray(descriptors, dtype=np.uint8).reshape(-1, 32)
        )
        if self.octaves.shape != (n,) or self.descriptors.shape != (n, 32):
            raise ValueError(
                f"octaves {self.octaves.shape} / descriptors {self.descriptors.shape} "
                f"do not match {n} keypoints"
            )
        self.point_agents: dict[int, str] = {}
        if point_keys is not None:
            if point_ids is not None:
                raise ValueError("pass point_ids or point_keys, not both")
            if len(point_keys) != n:
                raise ValueError(f"point_keys has {len(point_keys)} entries for {n} keypoints")
            self.point_ids: NDArray[np.int64] = np.full(n, -1, np.int64)
            for i, pk in enumerate(point_keys):
                if pk is not None:
                    self.set_point_key(i, _key(pk))
        elif point_ids is None:
            self.point_ids = np.full(n, -1, np.int64)
        else:
            # always a private, writable copy (protocol arrays are read-only)
            self.point_ids = np.array(point_ids, dtype=np.int64).reshape(-1)
            if self.point_ids.shape != (n,):
                raise ValueError(f"point_ids {self.point_ids.shape} does not match {n} keypoints")
        self.gnss_enu: F64 | None = None if gnss_enu is None else np.array(gnss_enu, np.float64).reshape(3)
        self.gnss_cov: F64 | None = None if gnss_cov is None else np.array(gnss_cov, np.float64).reshape(3, 3)
        # up direction (unit, against gravity) in the camera frame as the agent's IMU measured it
        self.up_cam: F64 | None = None if up_cam is None else np.array(up_cam, np.float64).reshape(3)
        self.u_right: NDArray[np.float32] | None = None
        self.stereo_baseline: float | None = None
        if u_right is not None and stereo_baseline is not None:
            self.u_right = np.array(u_right, dtype=np.float32).reshape(-1)
            if self.u_right.shape != (n,):
                raise ValueError(f"u_right {self.u_right.shape} does not match {n} keypoints")
            if not stereo_baseline > 0:
                raise ValueError(f"stereo_baseline must be positive, got {stereo_baseline}")
            self.stereo_baseline = float(stereo_baseline)
        self.odom_sigma: F64 | None = (
            None if odom_sigma is None else np.array(odom_sigma, np.float64).reshape(2)
        )
        self.track_sigma: F64 | None = (
            None if track_sigma is None else np.array(track_sigma, np.float64).reshape(2)
        )
        self.vio_from_cam: F64 | None = (
            None if vio_from_cam is None else np.array(vio_from_cam, np.float64).reshape(4, 4)
        )
        self.parent: KfKey | None = None

    @property
    def key(self) -> KfKey:
        return (self.agent_id, self.id)

    @property
    def n_keypoints(self) -> int:
        return len(self.keypoints)

    @property
    def cam_from_world(self) -> F64:
        return se3_inverse(self.world_from_cam)

    @property
    def center(self) -> F64:
        """Camera centre in the world frame (3,)."""
        return self.world_from_cam[:3, 3].copy()

    def point_key(self, i: int) -> PointKey | None:
        pid = int(self.point_ids[i])
        if pid < 0:
            return None
        return (self.point_agents.get(i, self.agent_id), pid)

    def set_point_key(self, i: int, key: PointKey | None) -> None:
        """Low-level: set keypoint ``i``'s reference. Inside a Map use the Map's methods instead."""
        if key is None:
            self.point_ids[i] = -1
            self.point_agents.pop(i, None)
            return
        agent, pid = key
        if pid < 0:
            raise ValueError(f"point id must be >= 0, got {pid}")
        self.point_ids[i] = pid
        if agent == self.agent_id:
            self.point_agents.pop(i, None)
        else:
            self.point_agents[i] = agent

    @property
    def point_keys(self) -> list[PointKey | None]:
        """Per keypoint: the referenced point key or None (a fresh list; editing it changes nothing)."""
        return [self.point_key(i) for i in range(self.n_keypoints)]

    def referenced_points(self) -> Iterator[tuple[int, PointKey]]:
        """(keypoint index, point key) for every keypoint that references a point."""
        for i in np.flatnonzero(self.point_ids >= 0).tolist():
            yield i, (self.point_agents.get(i, self.agent_id), int(self.point_ids[i]))

    def __repr__(self) -> str:
        n_ref = int((self.point_ids >= 0).sum())
        return (
            f"Keyframe({self.agent_id!r}, {self.id}, t={self.timestamp}, kps={self.n_keypoints}"
            f", refs={n_ref})"
        )
