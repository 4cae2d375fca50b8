"""Reader for EuRoC/ASL-format agent datasets (hivemap renders and real EuRoC recordings).

Layout (one agent)::

    <agent_dir>/mav0/cam0/data.csv   "#timestamp [ns],filename"      + data/<t_ns>.png + sensor.yaml
    <agent_dir>/mav0/cam1/...        (optional: a monocular sequence has no cam1)
    <agent_dir>/mav0/imu0/data.csv   "#timestamp [ns],w_RS_S_x [rad s^-1],...,a_RS_S_z [m s^-2]" + sensor.yaml
    <agent_dir>/mav0/state_groundtruth_estimate0/data.csv  (optional) EuRoC ground truth, 17 columns
    <agent_dir>/mav0/gnss0/data.csv  (optional, hivemap) "#timestamp [ns],east,north,up,sigma_h,sigma_v"
    <agent_dir>/agent.yaml           (optional, hivemap) agent_id, kind

Scenario: ``<dir>/manifest.yaml`` lists the agents (``load_scenario``).

Timestamps: ``*_t_ns`` are int64 nanoseconds as on disk; ``timestamps`` / ``imu[:, 0]`` are float64 seconds
(same epoch). Poses are world_from_body 4x4 (body = IMU frame); quaternions on disk are (w, x, y, z).
Every problem with the input raises ``DatasetError`` naming the file (and line).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TypeAlias

import numpy as np
from numpy.typing import NDArray

from hivemap.client.dataset_files import DatasetError as DatasetError  # raised here, caught by callers
from hivemap.client.dataset_files import (
    camera_from_sensor_yaml,
    gnss_from_sensor_yaml,
    imu_from_sensor_yaml,
    read_csv_numeric,
    read_image_list,
    read_yaml,
)
from hivemap.maps.camera import PinholeCamera, StereoRig

if TYPE_CHECKING:
    from hivemap.client.bag import BagSource

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
# What the replay accepts as its input: a EuRoC/ASL folder, or a ROS bag with calibration and topics.
DatasetSource: TypeAlias = "str | Path | BagSource"


# ---------------------------------------------------------------------------------------------
# Data classes
# ---------------------------------------------------------------------------------------------


class FrameSource(Protocol):
    """What the replay needs of a dataset's frames: ns timestamps and images by index (read in order).
    Implemented by :class:`FrameList` (image files) and ``hivemap.client.bag.BagFrames`` (a ROS bag)."""

    @property
    def t_ns(self) -> I64: ...

    @property
    def timestamps(self) -> F64: ...

    def __len__(self) -> int: ...

    def load(self, i: int) -> tuple[NDArray[np.uint8], NDArray[np.uint8] | None]: ...


@dataclass(frozen=True)
class FrameList:
    """Synchronised stereo (or mono) frames; images load lazily as uint8 grayscale."""

    t_ns: I64
    cam0_paths: list[Path]
    cam1_paths: list[Path] | None = None

    @property
    def timestamps(self) -> F64:
        return self.t_ns.astype(np.float64) * 1e-9

    def __len__(self) -> int:
        return len(self.t_ns)

    def load(self, i: int) -> tuple[NDArray[np.uint8], NDArray[np.uint8] | None]:
        """(gray cam0, gray cam1 or None) of frame i."""
        g0 = _load_gray(self.cam0_paths[i])
        g1 = None if self.cam1_paths is None else _load_gray(self.cam1_paths[i])
        return g0, g1

    def __iter__(self) -> Iterator[tuple[float, NDArray[np.uint8], NDArray[np.uint8] | None]]:
        """Yields (t_seconds, gray0, gray1)."""
        ts = self.timestamps
        for i in range(len(self)):
            g0, g1 = self.load(i)
            yield float(ts[i]), g0, g1


def _load_gray(path: Path) -> NDArray[np.uint8]:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError("cannot read image (missing or corrupt)", path)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint16:
        img = img // 256
    return np.asarray(img, dtype=np.uint8)


@dataclass(frozen=True)
class GroundTruth:
    """World-from-body poses (body = IMU frame), velocities and the true IMU biases."""

    t_ns: I64
    world_from_body: F64  # (N, 4, 4)
    velocity: F64  # (N, 3) world frame
    bias_gyro: F64  # (N, 3)
    bias_accel: F64  # (N, 3)

    @property
    def timestamps(self) -> F64:
        return self.t_ns.astype(np.float64) * 1e-9

    def __len__(self) -> int:
        return len(self.t_ns)

    def at(self, t_ns: I64 | int) -> F64:
        """Poses (M, 4, 4) at the given ns timestamps: exact rows when present, else interpolated
        (linear position, slerp rotation); outside the range -> DatasetError."""
        from scipy.spatial.transform import Rotation, Slerp

        q = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        if len(self) == 0 or q.min() < self.t_ns[0] or q.max() > self.t_ns[-1]:
            raise DatasetError("requested time outside the ground truth range")
        rel = (self.t_ns - self.t_ns[0]).astype(np.float64)
        qr = (q - self.t_ns[0]).astype(np.float64)
        slerp = Slerp(rel, Rotation.from_matrix(self.world_from_body[:, :3, :3]))
        out = np.tile(np.eye(4), (len(q), 1, 1))
        out[:, :3, :3] = slerp(qr).as_matrix()
        for d in range(3):
            out[:, d, 3] = np.interp(qr, rel, self.world_from_body[:, d, 3])
        idx = np.searchsorted(self.t_ns, q)
        exact = (idx < len(self.t_ns)) & (self.t_ns[np.minimum(idx, len(self.t_ns) - 1)] == q)
        out[exact] = self.world_from_body[idx[exact]]
        return out


@dataclass(frozen=True)
class GnssSeries:
    """GNSS fixes in ENU metres around ``origin`` (lat, lon, ellipsoidal height) when known."""

    t_ns: I64
    enu: F64  # (N, 3)
    sigma: F64  # (N, 2): sigma_h, sigma_v
    origin: tuple[float, float, float] | None = None
    nmea_path: Path | None = None

    @property
    def timestamps(self) -> F64:
        return self.t_ns.astype(np.float64) * 1e-9

    def __len__(self) -> int:
        return len(self.t_ns)


@dataclass
class AgentDataset:
    """One agent's sequence (see module docstring). ``imu``: (N, 7) [t_s, w_x, w_y, w_z, a_x, a_y, a_z]."""

    agent_id: str
    kind: str
    root: Path
    cameras: dict[str, PinholeCamera]
    T_BS: dict[str, F64]  # sensor -> body_from_sensor 4x4 ("cam0", "cam1", "imu0", "gnss0")
    rates: dict[str, float]
    frames: FrameSource
    rig: StereoRig | None
    imu: F64
    imu_t_ns: I64
    imu_noise: dict[str, float]
    groundtruth: GroundTruth | None
    gnss: GnssSeries | None
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def camera(self) -> PinholeCamera:
        return self.cameras["cam0"]

    def groundtruth_at_frames(self) -> F64:
        """world_from_body (N, 4, 4) at the frame timestamps (DatasetError without ground truth)."""
        if self.groundtruth is None:
            raise DatasetError("no ground truth", self.root)
        return self.groundtruth.at(self.frames.t_ns)


# ---------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------


def _mav0(agent_dir: Path) -> Path:
    if (agent_dir / "mav0").is_dir():
        return agent_dir / "mav0"
    if agent_dir.name == "mav0" and agent_dir.is_dir():
        return agent_dir
    if not agent_dir.exists():
        raise DatasetError("dataset directory not found", agent_dir)
    raise DatasetError("no 'mav0' folder (expected EuRoC/ASL layout <agent>/mav0/cam0, imu0, ...)", agent_dir)


def _load_camera(mav0: Path, name: str) -> tuple[PinholeCamera, F64, float, I64, list[Path]]:
    cam, T_BS, rate = camera_from_sensor_yaml(mav0 / name / "sensor.yaml")
    t, names = read_image_list(mav0 / name / "data.csv")
    paths = [mav0 / name / "data" / n for n in names]
    # Real recordings are sometimes copied partially: a listed frame missing on disk is skipped (its
    # stereo partner goes too), not fatal, as long as some frames remain.
    present = np.asarray([p.is_file() for p in paths], dtype=bool)
    if len(paths) and not present.any():
        raise DatasetError(f"none of the {len(paths)} listed images exist", mav0 / name / "data")
    if not present.all():
        first = int(np.flatnonzero(~present)[0])
        log.warning(
            "%s: %d of %d listed frames missing on disk, skipped (first: %s, row %d)",
            mav0 / name / "data.csv", int((~present).sum()), len(paths), paths[first].name, first + 1,
        )  # fmt: skip
        t = t[present]
        paths = [p for p, ok in zip(paths, present, strict=True) if ok]
    return cam, T_BS, rate, t, paths


def open_dataset(source: DatasetSource) -> AgentDataset:
    """A EuRoC/ASL folder (``load_dataset``) or a ROS bag with its calibration (``BagSource``)."""
    if isinstance(source, str | Path):
        return load_dataset(source)
    from hivemap.client.bag import load_bag

    return load_bag(source)


def load_dataset(agent_dir: str | Path) -> AgentDataset:
    """Load one agent directory (EuRoC/ASL layout). Raises ``DatasetError`` naming the bad file."""
    root = Path(agent_dir)
    mav0 = _mav0(root)
    if root.name == "mav0":
        root = root.parent
    meta: dict[str, Any] = {}
    agent_id, kind = root.name, ""
    if (root / "agent.yaml").is_file():
        meta = read_yaml(root / "agent.yaml")
        agent_id = str(meta.get("agent_id", agent_id))
        kind = str(meta.get("kind", ""))
    elif (root.parent / "manifest.yaml").is_file():
        try:
            man = load_scenario(root.parent)
            for a in man.agents:
                if a.path.resolve() == root.resolve():
                    agent_id, kind = a.id, a.kind
        except DatasetError as e:
            log.warning("ignoring unreadable manifest next to %s: %s", root, e)
    if kind not in ("uav", "ugv"):
        log.info("%s: agent kind unknown, assuming 'uav' (EuRoC is a MAV)", root)
        kind = "uav"

    cameras: dict[str, PinholeCamera] = {}
    T_BS: dict[str, F64] = {}
    rates: dict[str, float] = {}
    cam0, T0, r0, t0, p0 = _load_camera(mav0, "cam0")
    if len(t0) == 0:
        raise DatasetError("no frames", mav0 / "cam0" / "data.csv")
    cameras["cam0"], T_BS["cam0"], rates["cam0"] = cam0, T0, r0
    p1: list[Path] | None = None
    rig = None
    if (mav0 / "cam1").is_dir():
        cam1, T1, r1, t1, p1_all = _load_camera(mav0, "cam1")
        cameras["cam1"], T_BS["cam1"], rates["cam1"] = cam1, T1, r1
        # keep frames present in both cameras (EuRoC: identical timestamps)
        common, i0, i1 = np.intersect1d(t0, t1, assume_unique=True, return_indices=True)
        if len(common) < len(t0):
            log.warning("%s: %d cam0 frames without a cam1 partner dropped", root, len(t0) - len(common))
        if len(common) == 0:
            raise DatasetError("cam0 and cam1 share no timestamps", mav0 / "cam1" / "data.csv")
        t0 = common
        p0 = [p0[i] for i in i0]
        p1 = [p1_all[i] for i in i1]
        rig = StereoRig(cam0, cam1, T0, T1)
    frames = FrameList(t0, p0, p1)

    T_BS["imu0"], rates["imu0"], imu_noise = imu_from_sensor_yaml(mav0 / "imu0" / "sensor.yaml")
    imu_t, imu_v = read_csv_numeric(mav0 / "imu0" / "data.csv", 7)
    if len(imu_t) == 0:
        raise DatasetError("no IMU samples", mav0 / "imu0" / "data.csv")
    imu = np.concatenate([imu_t[:, None].astype(np.float64) * 1e-9, imu_v], axis=1)

    gt = None
    gt_csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
    if gt_csv.is_file():
        gt_t, gt_v = read_csv_numeric(gt_csv, (8, 11, 17))
        n = len(gt_t)
        poses = np.tile(np.eye(4), (n, 1, 1))
        if n:
            from scipy.spatial.transform import Rotation

            q = gt_v[:, 3:7]
            norm = np.linalg.norm(q, axis=1)
            bad = np.flatnonzero(np.abs(norm - 1.0) > 1e-3)
            if len(bad):
                raise DatasetError(
                    f"quaternion not unit (norm {norm[bad[0]]:.4f}) in data row {bad[0] + 1}", gt_csv
                )
            poses[:, :3, :3] = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
            poses[:, :3, 3] = gt_v[:, 0:3]

        def cols(a: int) -> F64:
            return gt_v[:, a : a + 3] if gt_v.shape[1] >= a + 3 else np.zeros((n, 3))

        gt = GroundTruth(gt_t, poses, cols(7), cols(10), cols(13))

    gnss = None
    gdir = mav0 / "gnss0"
    if (gdir / "data.csv").is_file():
        g_t, g_v = read_csv_numeric(gdir / "data.csv", (4, 6))
        sigma = g_v[:, 3:5] if g_v.shape[1] >= 5 else np.full((len(g_t), 2), np.nan)
        origin = None
        if (gdir / "sensor.yaml").is_file():
            T_BS["gnss0"], rates["gnss0"], origin = gnss_from_sensor_yaml(gdir / "sensor.yaml")
        nmea = gdir / "nmea.txt"
        gnss = GnssSeries(g_t, g_v[:, 0:3], sigma, origin, nmea if nmea.is_file() else None)

    return AgentDataset(
        agent_id=agent_id,
        kind=kind,
        root=root,
        cameras=cameras,
        T_BS=T_BS,
        rates=rates,
        frames=frames,
        rig=rig,
        imu=imu,
        imu_t_ns=imu_t,
        imu_noise=imu_noise,
        groundtruth=gt,
        gnss=gnss,
        meta=meta,
    )


@dataclass(frozen=True)
class ManifestAgent:
    id: str
    kind: str
    path: Path
    complete: bool = True
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ScenarioManifest:
    """``manifest.yaml`` of a rendered scenario."""

    root: Path
    name: str
    seed: int | None
    agents: list[ManifestAgent]
    origin: tuple[float, float, float] | None
    raw: dict[str, Any]

    def agent(self, agent_id: str) -> ManifestAgent:
        for a in self.agents:
            if a.id == agent_id:
                return a
        raise DatasetError(f"no agent {agent_id!r} in the manifest", self.root / "manifest.yaml")

    def load_agent(self, agent_id: str) -> AgentDataset:
        return load_dataset(self.agent(agent_id).path)


def load_scenario(scenario_dir: str | Path) -> ScenarioManifest:
    """Read ``<dir>/manifest.yaml`` (scenario name, seed, agents [{id, kind, path}], origin)."""
    root = Path(scenario_dir)
    path = root / "manifest.yaml"
    d = read_yaml(path)
    try:
        agents = []
        for a in d["agents"]:
            extra = {k: v for k, v in a.items() if k not in ("id", "kind", "path", "complete")}
            agents.append(
                ManifestAgent(
                    str(a["id"]), str(a["kind"]), root / str(a["path"]), bool(a.get("complete", True)), extra
                )
            )
        o = d.get("origin")
        origin = None if not o else (float(o["lat"]), float(o["lon"]), float(o["alt"]))
        name = str(d.get("scenario", d.get("name", root.name)))
        seed = None if d.get("seed") is None else int(d["seed"])
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"bad manifest: missing or invalid {e}", path) from e
    return ScenarioManifest(root, name, seed, agents, origin, d)
