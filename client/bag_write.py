"""EuRoC folder -> ROS bag (``write_bag``): a rendered dataset replayed from a bag, and the tests that check
the bag reader (:mod:`hivemap.client.bag`) gives the folder's trajectory."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from hivemap.client.bag import BagFormat, BagTopics
from hivemap.client.dataset import AgentDataset

log = logging.getLogger(__name__)


def write_bag(
    ds: AgentDataset,
    out: Path,
    fmt: BagFormat = "mcap",
    topics: BagTopics | None = None,
    max_frames: int | None = None,
) -> Path:
    """Write a dataset's images (mono8), IMU and, when ``topics.gnss`` is set and the dataset has an ENU
    origin, GNSS (NavSatFix) as a ROS 1 bag (``out`` is the file) or a ROS 2 bag (``out`` the folder)."""
    import pymap3d
    from rosbags.typesys import Stores, get_typestore

    topics = topics or BagTopics()
    ros1 = fmt == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = store.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Image, Imu, Vec3 = T["sensor_msgs/msg/Image"], T["sensor_msgs/msg/Imu"], T["geometry_msgs/msg/Vector3"]
    Quat, NavSatFix, NavSatStatus = (
        T["geometry_msgs/msg/Quaternion"],
        T["sensor_msgs/msg/NavSatFix"],
        T["sensor_msgs/msg/NavSatStatus"],
    )

    def header(t_ns: int, frame: str) -> Any:
        stamp = Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
        return Header(seq=0, stamp=stamp, frame_id=frame) if ros1 else Header(stamp=stamp, frame_id=frame)

    def serialize(msg: Any, msgtype: str) -> bytes:
        return bytes(store.serialize_ros1(msg, msgtype) if ros1 else store.serialize_cdr(msg, msgtype))

    n = len(ds.frames) if max_frames is None else min(max_frames, len(ds.frames))
    frame_t = [int(t) for t in ds.frames.t_ns[:n]]
    t_end = frame_t[-1] if frame_t else 0
    events: list[tuple[int, int, int]] = [(t, 0, i) for i, t in enumerate(frame_t)]
    events += [(int(t), 1, i) for i, t in enumerate(ds.imu_t_ns) if t <= t_end]
    gnss = ds.gnss if topics.gnss else None
    if gnss is not None and gnss.origin is None:
        log.warning("%s: GNSS without an ENU origin, not written", ds.root)
        gnss = None
    if gnss is not None:
        lat, lon, alt = pymap3d.enu2geodetic(gnss.enu[:, 0], gnss.enu[:, 1], gnss.enu[:, 2], *gnss.origin)
        geo = np.stack([np.asarray(lat), np.asarray(lon), np.asarray(alt)], axis=1)
        events += [(int(t), 2, i) for i, t in enumerate(gnss.t_ns) if t <= t_end]
    events.sort()

    if ros1:
        from rosbags.rosbag1 import Writer as Ros1Writer

        writer: Any = Ros1Writer(out)
    else:
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Ros2Writer

        plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
        writer = Ros2Writer(out, version=9, storage_plugin=plugin)
    with writer:
        cam_topics = [topics.cam0] + ([topics.cam1] if topics.cam1 else [])
        c_img = [writer.add_connection(t, Image.__msgtype__, typestore=store) for t in cam_topics]
        c_imu = writer.add_connection(topics.imu, Imu.__msgtype__, typestore=store)
        c_gnss = writer.add_connection(topics.gnss, NavSatFix.__msgtype__, typestore=store) if gnss else None
        for t, kind, i in events:
            if kind == 0:
                left, right = ds.frames.load(i)
                for conn, img, frame in zip(c_img, (left, right), ("cam0", "cam1"), strict=False):
                    if img is None:
                        continue
                    h, w = img.shape
                    msg = Image(
                        header=header(t, frame), height=h, width=w, encoding="mono8", is_bigendian=0, step=w,
                        data=np.ascontiguousarray(img, dtype=np.uint8).reshape(-1),
                    )  # fmt: skip
                    writer.write(conn, t, serialize(msg, Image.__msgtype__))
            elif kind == 1:
                row = ds.imu[i]
                msg = Imu(
                    header=header(t, "imu0"),
                    orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.array([-1.0] + [0.0] * 8),  # -1: no orientation
                    angular_velocity=Vec3(x=row[1], y=row[2], z=row[3]),
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=Vec3(x=row[4], y=row[5], z=row[6]),
                    linear_acceleration_covariance=np.zeros(9),
                )
                writer.write(c_imu, t, serialize(msg, Imu.__msgtype__))
            else:
                assert gnss is not None and c_gnss is not None
                sh, sv = (float(s) for s in gnss.sigma[i])
                ok = np.isfinite(sh) and np.isfinite(sv)
                cov = np.diag([sh**2, sh**2, sv**2]).reshape(-1) if ok else np.zeros(9)
                msg = NavSatFix(
                    header=header(t, "gnss0"),
                    status=NavSatStatus(status=0 if ok else -1, service=1),
                    latitude=geo[i, 0], longitude=geo[i, 1], altitude=geo[i, 2],
                    position_covariance=cov, position_covariance_type=2 if ok else 0,
                )  # fmt: skip
                writer.write(c_gnss, t, serialize(msg, NavSatFix.__msgtype__))
    return out
