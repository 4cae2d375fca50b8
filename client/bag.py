"""ROS bags as agent datasets, without ROS: ROS 1 ``.bag`` files and ROS 2 bag folders (sqlite3 or MCAP
storage), read with the pure-Python ``rosbags`` library.

``load_bag(BagSource(path, calib, topics))`` returns the same :class:`~hivemap.client.dataset.AgentDataset`
the EuRoC folder reader gives, so the replay (offline or streaming) does not know where its frames came
from. A bag carries no calibration: it comes from ``calib``, either a EuRoC ``mav0`` folder (its
``cam0``/``cam1``/``imu0`` ``sensor.yaml``; ``gnss0/sensor.yaml`` gives the ENU origin) or Kalibr files
(a camchain yaml, optionally an IMU yaml with the noise densities).

Topics (defaults are EuRoC's bags): two ``sensor_msgs/Image`` (or ``CompressedImage``) streams, a
``sensor_msgs/Imu`` and an optional ``sensor_msgs/NavSatFix``. Times are the messages' header stamps (the
bag's receive time when a driver left them zero). Stereo frames are the stamps both cameras have.

``hivemap.client.bag_write.write_bag`` goes the other way (EuRoC folder -> bag) so that a rendered dataset
can be replayed from a bag, and tests can check both give the same trajectory.
"""

from __future__ import annotations

import logging
import weakref
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

from hivemap.client.bag_calib import Calibration, load_calibration
from hivemap.client.dataset import AgentDataset, GnssSeries
from hivemap.client.dataset_files import (
    DatasetError,
)

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
IMU_TYPE = "sensor_msgs/msg/Imu"
GNSS_TYPE = "sensor_msgs/msg/NavSatFix"


@dataclass(frozen=True)
class BagTopics:
    """Which topics hold what; ``cam1=None`` reads a monocular bag, ``gnss=None`` ignores GNSS."""

    cam0: str = "/cam0/image_raw"
    cam1: str | None = "/cam1/image_raw"
    imu: str = "/imu0"
    gnss: str | None = None


# The CLI flag that sets each topic, so that an error about a topic says how to fix it.
TOPIC_FLAGS = {"cam0": "--cam0-topic", "cam1": "--cam1-topic", "imu": "--imu-topic", "gnss": "--gnss-topic"}


@dataclass(frozen=True)
class BagSource:
    """A bag to replay: its path (ROS 1 file or ROS 2 folder), calibration path(s) and topics."""

    path: Path
    calib: tuple[Path, ...]
    topics: BagTopics = field(default_factory=BagTopics)


def is_bag(path: Path) -> bool:
    """A ROS 1 bag file, a ROS 2 bag folder (``metadata.yaml``) or a ``.db3``/``.mcap`` file inside one."""
    if path.is_file():
        return path.suffix == ".bag" or (
            path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file()
        )
    return path.is_dir() and (path / "metadata.yaml").is_file()


def _bag_root(path: Path) -> Path:
    """What ``AnyReader`` opens: the ``.bag`` file or the ROS 2 bag folder."""
    return path.parent if path.suffix in (".db3", ".mcap") else path


def dataset_source(
    dataset: Path, calib: Sequence[Path] = (), topics: BagTopics | None = None
) -> Path | BagSource:
    """What ``hivemap agent --dataset`` names: a bag (with ``calib`` and ``topics``) or a EuRoC folder."""
    if is_bag(dataset):
        return BagSource(dataset, tuple(calib), topics or BagTopics())
    if not dataset.exists():
        raise DatasetError("dataset not found (a EuRoC folder, a ROS 1 .bag or a ROS 2 bag folder)", dataset)
    if dataset.is_file():
        raise DatasetError("not a dataset: a EuRoC folder, a ROS 1 .bag or a ROS 2 bag folder", dataset)
    if calib:
        raise DatasetError("--calib is for ROS bags; a EuRoC folder has its own sensor.yaml files", dataset)
    return dataset


# ---------------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------------


def _open_reader(path: Path) -> AnyReader:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    # ROS 2 bags written without message definitions need a default type store; Humble's has the
    # sensor_msgs types this module reads.
    return AnyReader([_bag_root(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def _stamp_ns(msg: Any, bag_t_ns: int) -> int:
    st = msg.header.stamp
    t = int(st.sec) * 1_000_000_000 + int(st.nanosec)
    return t if t > 0 else int(bag_t_ns)


def decode_image(msg: Any, msgtype: str, topic: str) -> U8:
    """``sensor_msgs/Image`` (mono8/16, rgb8, bgr8, rgba8, bgra8) or ``CompressedImage`` -> gray uint8."""
    import cv2

    if msgtype.endswith("CompressedImage"):
        img = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise DatasetError(f"{topic}: cannot decode a compressed image ({msg.format!r})")
        return np.asarray(img, dtype=np.uint8)
    h, w, step, enc = int(msg.height), int(msg.width), int(msg.step), str(msg.encoding).lower()
    data = np.asarray(msg.data, dtype=np.uint8)
    channels = {"mono8": 1, "8uc1": 1, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}
    if enc in ("mono16", "16uc1"):
        rows = data[: h * step].reshape(h, step)[:, : 2 * w]
        dt = np.dtype(">u2" if msg.is_bigendian else "<u2")
        return np.asarray(rows.copy().view(dt) // 256, dtype=np.uint8)
    if enc not in channels:
        raise DatasetError(
            f"{topic}: image encoding {enc!r} unsupported (mono8/16, rgb8, bgr8, rgba8, bgra8)"
        )
    n = channels[enc]
    if data.size < h * step or step < w * n:
        raise DatasetError(f"{topic}: image data ({data.size} bytes) shorter than {h} rows of {step}")
    img = data[: h * step].reshape(h, step)[:, : w * n].reshape(h, w, n)
    if n == 1:
        return np.ascontiguousarray(img[:, :, 0])
    code = {
        "rgb8": cv2.COLOR_RGB2GRAY,
        "bgr8": cv2.COLOR_BGR2GRAY,
        "rgba8": cv2.COLOR_RGBA2GRAY,
        "bgra8": cv2.COLOR_BGRA2GRAY,
    }[enc]
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(img), code), dtype=np.uint8)


class BagFrames:
    """Stereo (or mono) frames of a bag, decoded on demand. The replay reads them in order, so one
    pass over the image topics serves it without holding the images in memory; going back restarts."""

    def __init__(self, path: Path, cam0: str, cam1: str | None, t_ns: I64) -> None:
        self.path = path
        self.cam0, self.cam1 = cam0, cam1
        self._t_ns = t_ns
        self._wanted = {int(t) for t in t_ns}
        self._cursor: Iterator[tuple[int, U8, U8 | None]] | None = None
        self._next = 0
        self._ahead: dict[int, tuple[U8, U8 | None]] = {}
        # The open pass holds the bag open; close it before interpreter shutdown, when closing the
        # reader from the garbage collector fails (a replay stopped by --max-frames leaves it open).
        self._open: list[Any] = []
        weakref.finalize(self, _close_all, self._open)

    def close(self) -> None:
        """Close the bag if a pass over it is open (the next ``load`` opens it again)."""
        _close_all(self._open)
        self._cursor = None

    @property
    def t_ns(self) -> I64:
        return self._t_ns

    @property
    def timestamps(self) -> F64:
        return self._t_ns.astype(np.float64) * 1e-9

    def __len__(self) -> int:
        return len(self._t_ns)

    def __iter__(self) -> Iterator[tuple[float, U8, U8 | None]]:
        for i, t in enumerate(self.timestamps):
            g0, g1 = self.load(i)
            yield float(t), g0, g1

    def load(self, i: int) -> tuple[U8, U8 | None]:
        """(gray cam0, gray cam1 or None) of frame i."""
        if self._cursor is None or i < self._next:
            self.close()
            self._cursor, self._ahead = self._pairs(), {}
            self._open.append(self._cursor)
        self._next = i + 1
        want = int(self._t_ns[i])
        while want not in self._ahead:
            try:
                t, g0, g1 = next(self._cursor)
            except StopIteration:
                self._cursor = None
                raise DatasetError(f"frame at {want} ns not found on a second pass", self.path) from None
            if t >= want:  # frames before the one asked for are skipped, later ones kept
                self._ahead[t] = (g0, g1)
        images = self._ahead.pop(want)
        if i == len(self) - 1:
            self.close()
        return images

    def _pairs(self) -> Iterator[tuple[int, U8, U8 | None]]:
        with _open_reader(self.path) as reader:
            topics = {self.cam0} | ({self.cam1} if self.cam1 else set())
            conns = [c for c in reader.connections if c.topic in topics]
            pending: dict[str, dict[int, U8]] = {t: {} for t in topics}
            for conn, bag_t, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                t = _stamp_ns(msg, bag_t)
                if t not in self._wanted:
                    continue
                pending[conn.topic][t] = decode_image(msg, conn.msgtype, conn.topic)
                if self.cam1 is None:
                    yield t, pending[self.cam0].pop(t), None
                elif t in pending[self.cam0] and t in pending[self.cam1]:
                    yield t, pending[self.cam0].pop(t), pending[self.cam1].pop(t)


def _close_all(generators: list[Any]) -> None:
    while generators:
        generators.pop().close()


def _sorted_unique(t: list[int], rows: list[list[float]], topic: str) -> tuple[I64, F64]:
    """Sort by stamp and drop repeated stamps (bags are ordered by receive time, not by stamp)."""
    ts = np.asarray(t, dtype=np.int64)
    vals = np.asarray(rows, dtype=np.float64).reshape(len(t), -1)
    order = np.argsort(ts, kind="stable")
    ts, vals = ts[order], vals[order]
    keep = np.concatenate([[True], np.diff(ts) > 0]) if len(ts) else np.zeros(0, bool)
    if not keep.all():
        log.warning("%s: %d messages with a repeated stamp dropped", topic, int((~keep).sum()))
    return ts[keep], vals[keep]


def load_bag(source: BagSource) -> AgentDataset:
    """Read a bag's IMU and GNSS, index its frames and attach the calibration (see the module doc)."""
    from rosbags.highlevel import AnyReaderError

    path = Path(source.path)
    if not path.exists():
        raise DatasetError("bag not found", path)
    calib = load_calibration(source.calib)
    topics = source.topics
    if topics.cam1 is not None and "cam1" not in calib.cameras:
        raise DatasetError("the calibration has no cam1 (give --cam1-topic '' for a monocular bag)")
    try:
        with _open_reader(path) as reader:
            conns = {c.topic: c for c in reader.connections}
            wanted = {"cam0": topics.cam0, "cam1": topics.cam1, "imu": topics.imu, "gnss": topics.gnss}
            expected = {"cam0": IMAGE_TYPES, "cam1": IMAGE_TYPES, "imu": (IMU_TYPE,), "gnss": (GNSS_TYPE,)}
            for role, topic in wanted.items():
                if topic is None:
                    continue
                if topic not in conns:
                    have = ", ".join(sorted(conns)) or "none"
                    raise DatasetError(
                        f"topic {topic!r} not in the bag (it has: {have}); "
                        f"choose another with {TOPIC_FLAGS[role]}",
                        path,
                    )
                if conns[topic].msgtype not in expected[role]:
                    raise DatasetError(
                        f"topic {topic!r} is {conns[topic].msgtype}, expected {' or '.join(expected[role])}",
                        path,
                    )
            stamps: dict[str, list[int]] = {topics.cam0: []}
            if topics.cam1:
                stamps[topics.cam1] = []
            imu_t: list[int] = []
            imu_rows: list[list[float]] = []
            gnss_t: list[int] = []
            gnss_rows: list[list[float]] = []
            use = [conns[t] for t in wanted.values() if t is not None]
            for conn, bag_t, raw in reader.messages(connections=use):
                msg: Any = reader.deserialize(raw, conn.msgtype)
                t = _stamp_ns(msg, bag_t)
                if conn.topic in stamps:
                    stamps[conn.topic].append(t)
                elif conn.topic == topics.imu:
                    w, a = msg.angular_velocity, msg.linear_acceleration
                    imu_t.append(t)
                    imu_rows.append([w.x, w.y, w.z, a.x, a.y, a.z])
                elif conn.topic == topics.gnss:
                    if int(msg.status.status) < 0:  # STATUS_NO_FIX
                        continue
                    cov = np.asarray(msg.position_covariance, dtype=np.float64).reshape(3, 3)
                    gnss_t.append(t)
                    gnss_rows.append(
                        [msg.latitude, msg.longitude, msg.altitude, cov[0, 0], cov[1, 1], cov[2, 2]]
                    )
    except AnyReaderError as e:
        raise DatasetError(f"cannot read the bag: {e}", path) from e

    t0 = np.unique(np.asarray(stamps[topics.cam0], dtype=np.int64))
    if len(t0) == 0:
        raise DatasetError(f"topic {topics.cam0!r} has no messages", path)
    rig = None
    cameras = {"cam0": calib.cameras["cam0"]}
    if topics.cam1:
        t1 = np.unique(np.asarray(stamps[topics.cam1], dtype=np.int64))
        common = np.intersect1d(t0, t1, assume_unique=True)
        if len(common) == 0:
            raise DatasetError(f"{topics.cam0!r} and {topics.cam1!r} share no stamps", path)
        if len(common) < len(t0):
            log.warning("%s: %d cam0 frames without a cam1 partner dropped", path, len(t0) - len(common))
        t0 = common
        cameras["cam1"] = calib.cameras["cam1"]
        rig = calib.stereo_rig()
    imu_ns, imu_v = _sorted_unique(imu_t, imu_rows, topics.imu)
    if len(imu_ns) == 0:
        raise DatasetError(f"topic {topics.imu!r} has no messages", path)
    imu = np.concatenate([imu_ns[:, None].astype(np.float64) * 1e-9, imu_v], axis=1)
    gnss = _gnss_series(gnss_t, gnss_rows, calib, path, topics) if topics.gnss else None

    kind = calib.kind if calib.kind in ("uav", "ugv") else "uav"
    T_BS = {k: v for k, v in calib.T_BS.items() if k != "cam1" or topics.cam1}
    return AgentDataset(
        agent_id=calib.agent_id or (path.stem if path.is_file() else path.name),
        kind=kind,
        root=path,
        cameras=cameras,
        T_BS=T_BS,
        rates=dict(calib.rates),
        frames=BagFrames(path, topics.cam0, topics.cam1, t0),
        rig=rig,
        imu=imu,
        imu_t_ns=imu_ns,
        imu_noise=dict(calib.imu_noise),
        groundtruth=None,
        gnss=gnss,
        meta={"bag": str(path), "topics": topics.__dict__},
    )


def _gnss_series(
    t: list[int], rows: list[list[float]], calib: Calibration, path: Path, topics: BagTopics
) -> GnssSeries:
    """NavSatFix (lat, lon, alt, covariance) -> ENU around the calibration's origin (else the first fix)."""
    import pymap3d

    ts, v = _sorted_unique(t, rows, str(topics.gnss))
    if len(ts) == 0:
        log.warning("%s: no GNSS fixes on %s", path, topics.gnss)
        return GnssSeries(ts, np.zeros((0, 3)), np.zeros((0, 2)), calib.gnss_origin)
    origin = calib.gnss_origin or (float(v[0, 0]), float(v[0, 1]), float(v[0, 2]))
    e, n, u = pymap3d.geodetic2enu(v[:, 0], v[:, 1], v[:, 2], *origin)
    enu = np.stack([np.asarray(e), np.asarray(n), np.asarray(u)], axis=1)
    # sigma_h from the larger horizontal variance; unknown covariance (zeros) -> NaN -> fix unused
    var_h = np.maximum(v[:, 3], v[:, 4])
    sigma = np.stack([np.sqrt(var_h), np.sqrt(v[:, 5])], axis=1)
    sigma[sigma <= 0] = np.nan
    return GnssSeries(ts, enu, sigma, origin)


# ---------------------------------------------------------------------------------------------
# Writing (EuRoC folder -> bag)
# ---------------------------------------------------------------------------------------------

BagFormat = Literal["ros1", "sqlite3", "mcap"]
