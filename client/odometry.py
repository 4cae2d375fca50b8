"""The odometry an agent streams: its visual tracking with the IMU fused in, and nothing from outside.

The front-end uses the IMU only to align gravity and predict rotation, so its poses drift in height and
tilt wherever the images are poor (fog, low texture); the second stage's IMU factors hold that drift.
But the agent's second stage also takes the server's corrections (co-location) and GNSS fixes, and
what the server's pose graph must hold as the agent's own measurement cannot contain the server's
earlier answers. So a second instance of the same fusion runs with the IMU alone; each keyframe is
streamed at ``stream_from_vio(node) @ vio pose`` (and its new points moved alike), so the server's map
and its odometry edges start from the IMU-aided shape (docs/decisions.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


class StreamOdometry:
    """An IMU-only :class:`~hivemap.client.second_stage.SecondStage` over the same keyframes (the same
    node ids) as the agent's own, from :meth:`start` on (an agent that streams nothing does not pay for
    it); before that, or without IMU options, it does nothing and the VIO is streamed as is."""

    def __init__(self, options: Any) -> None:
        self.options = options
        self.stage: Any = None

    def start(self) -> None:
        """Fuse from now on (the agent is about to stream; keyframes added before stay at the VIO)."""
        from hivemap.client.second_stage import SecondStage

        if self.stage is None and getattr(self.options, "imu", None) is not None:
            self.stage = SecondStage(self.options)

    def add_imu(self, samples: F64 | None) -> None:
        if self.stage is not None:
            self.stage.add_imu(samples)

    def add_keyframe(self, node: int, timestamp: float, vio_from_body: F64, **kw: Any) -> None:
        """As :meth:`SecondStage.add_keyframe` (no GNSS, no co-location ever reaches this stage); a
        keyframe whose predecessor came before :meth:`start` begins this stage's first segment."""
        if self.stage is None:
            return
        prev = kw.get("prev_id")
        if not self.stage.keyframe_ids or (prev is not None and not self.stage.has_keyframe(prev)):
            kw = {"new_segment": True}
        self.stage.add_keyframe(node, timestamp, vio_from_body, **kw)

    def update_vio_poses(self, updates: dict[int, F64]) -> None:
        if self.stage is not None:
            self.stage.update_vio_poses({k: T for k, T in updates.items() if self.stage.has_keyframe(k)})

    def local_from_stream(self, main: Any, segment: int) -> F64:
        """Where the streamed frame of ``segment`` lies in the agent's own (main) stage's local frame: the
        fit of that stage's keyframe positions to this one's (yaw and translation when gravity-aligned),
        as ``local_from_vio`` is fitted to the VIO. Both hold the IMU, so a corrected pose the server sends
        keeps its IMU-aided shape (mapped through the VIO frame, it would take the visual drift back);
        without the IMU the stream is the VIO: ``main.local_from_vio``."""
        from hivemap.client.second_stage.factors import frame_fit

        if self.stage is None:
            return np.asarray(main.local_from_vio(segment), dtype=np.float64)
        ids = [
            k for k in main.keyframe_ids if main.keyframe_segment(k) == segment and self.stage.has_keyframe(k)
        ]
        if not ids:
            return np.asarray(main.local_from_vio(segment), dtype=np.float64)
        src = np.array([self.stage.keyframe_pose(k)[:3, 3] for k in ids])
        dst = np.array([main.keyframe_pose(k)[:3, 3] for k in ids])
        last = main.keyframe_pose(ids[-1]) @ np.linalg.inv(self.stage.keyframe_pose(ids[-1]))
        return np.asarray(frame_fit(src, dst, main.options.gravity_aligned, last), dtype=np.float64)

    def stream_from_vio(self, node: int | None) -> F64:
        """The rigid transform taking the keyframe ``node``'s VIO pose to its streamed (IMU-aided) pose,
        in the VIO frame; identity without the IMU or for an unknown node."""
        if self.stage is None or node is None or not self.stage.has_keyframe(node):
            return np.eye(4)
        return stage_from_vio(self.stage, node)


def stage_from_vio(stage: Any, node: int) -> F64:
    """The rigid transform taking keyframe ``node``'s VIO pose to its pose in ``stage`` (a second stage)."""
    return np.asarray(stage.keyframe_pose(node) @ np.linalg.inv(stage.vio_pose(node)), dtype=np.float64)


class StreamedPoses:
    """The front-end's events at their streamed poses: each keyframe and the points it created moved by
    its keyframe's ``stream_from_vio``; a pose update's keyframes by their own and its points by their
    creating keyframe's (current) one; a new session's guess of its frame in the previous session's
    between the two sessions' streamed frames. ``moved(session, kf_id)``: that transform (4x4)."""

    def __init__(self, moved: Any) -> None:
        self.moved = moved
        self._creator: dict[tuple[int, int], int] = {}  # (session, point id) -> keyframe id
        self._last: dict[int, int] = {}  # session -> its newest keyframe id
        # what :meth:`refresh` needs: each keyframe's latest VIO pose and the pose the server has for it
        self._vio: dict[tuple[int, int], F64] = {}
        self._sent: dict[tuple[int, int], F64] = {}

    def keyframe(self, ev: Any) -> tuple[F64, F64, F64 | None]:
        """(world_from_cam, new points' xyz, prev_session_from_world) of a ``KeyframeEvent``."""
        C = self.moved(ev.session, ev.kf_id)
        for p in np.asarray(ev.new_point_ids).tolist():
            self._creator[(ev.session, int(p))] = int(ev.kf_id)
        key = (int(ev.session), int(ev.kf_id))
        self._vio[key] = np.asarray(ev.world_from_cam, dtype=np.float64).copy()
        self._sent[key] = C @ self._vio[key]
        guess = ev.prev_session_from_world
        earlier = [s for s in self._last if s < ev.session]
        if guess is not None and earlier:
            s = max(earlier)
            # the guess maps this session's VIO frame into the previous one's; both are streamed moved
            guess = self.moved(s, self._last[s]) @ np.asarray(guess, dtype=np.float64) @ np.linalg.inv(C)
        self._last[ev.session] = int(ev.kf_id)
        return C @ ev.world_from_cam, _apply(C, ev.new_point_xyz), guess

    def update(self, ev: Any) -> tuple[F64, F64]:
        """(world_from_cam, xyz) of a ``PoseUpdateEvent``."""
        s = int(ev.session)
        out = []
        for k, w in zip(np.asarray(ev.kf_ids).tolist(), ev.world_from_cam, strict=True):
            self._vio[(s, int(k))] = np.asarray(w, dtype=np.float64).copy()
            self._sent[(s, int(k))] = self.moved(s, int(k)) @ self._vio[(s, int(k))]
            out.append(self._sent[(s, int(k))])
        T = np.array(out).reshape(-1, 4, 4)
        xyz = np.asarray(ev.xyz, dtype=np.float64).reshape(-1, 3).copy()
        cache: dict[int | None, F64] = {}
        for i, p in enumerate(np.asarray(ev.point_ids).tolist()):
            k = self._creator.get((s, int(p)))
            if k not in cache:
                cache[k] = self.moved(s, k)
            xyz[i] = _apply(cache[k], xyz[i : i + 1])[0]
        return T, xyz

    def sent_pose(self, session: int, kf_id: int) -> F64:
        """The keyframe's pose as the server has it (as last sent)."""
        return self._sent[(session, kf_id)]

    def refresh(self, min_m: float, min_deg: float) -> list[tuple[int, Any, F64]]:
        """The keyframes whose streamed pose moved since they were last sent, as
        ``(session, kf_ids, world_from_cam)`` per session: a pose update whose points follow their
        keyframes (``PoseUpdates.points_follow``). The odometry is a smoother: each new keyframe's IMU
        factors also move the keyframes before it, and the server, which builds its pose graph on what it
        was sent, should hold that smoothed shape rather than each keyframe's first, causal, estimate. A
        keyframe is resent once its camera moved ``min_m`` or turned ``min_deg`` from what the server has."""
        from hivemap.maps.geometry import rotation_angle_deg

        by_session: dict[int, list[tuple[int, F64]]] = {}
        for (s, k), V in self._vio.items():
            now, held = self.moved(s, k) @ V, self._sent[(s, k)]
            moved_m = float(np.linalg.norm(now[:3, 3] - held[:3, 3]))
            if moved_m >= min_m or rotation_angle_deg(now[:3, :3] @ held[:3, :3].T) >= min_deg:
                self._sent[(s, k)] = now
                by_session.setdefault(s, []).append((k, now))
        return [
            (
                s,
                np.asarray([k for k, _ in items], np.int64),
                np.array([T for _, T in items]).reshape(-1, 4, 4),
            )
            for s, items in sorted(by_session.items())
        ]


def _apply(C: F64, xyz: Any) -> F64:
    pts = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    return pts @ C[:3, :3].T + C[:3, 3]
