"""ROS bags written here with ``rosbags``' writer (ROS 1 ``.bag``, ROS 2 ``.db3`` and ``.mcap``),
from the simulator's lines, for the tests of ``calstation import``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

CUSTOM = "my_msgs/msg/ScanWithAngle"


CUSTOM_DEF = "sensor_msgs/LaserScan scan\nfloat64 angle_deg\n"


# --- writing bags -----------------------------------------------------------------------------
@dataclass
class Bag:
    """A bag being written with rosbags: ROS 1 or ROS 2 (sqlite3 or mcap storage)."""

    path: Path
    flavour: str  # "ros1", "db3", "mcap"

    def __post_init__(self) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        ros1 = self.flavour == "ros1"
        self.store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        self.store.register(get_types_from_msg(CUSTOM_DEF, CUSTOM))
        if ros1:
            from rosbags.rosbag1 import Writer as W1

            self.writer: Any = W1(self.path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer as W2

            plugin = StoragePlugin.MCAP if self.flavour == "mcap" else StoragePlugin.SQLITE3
            self.writer = W2(self.path, version=9, storage_plugin=plugin)
        self.connections: dict[str, Any] = {}

    def __enter__(self) -> Bag:
        self.writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.writer.close()

    def t(self, name: str) -> Any:
        return self.store.types[name]

    def header(self, t_ns: int, frame: str = "laser") -> Any:
        sec, nsec = divmod(int(t_ns), 1_000_000_000)
        stamp = self.t("builtin_interfaces/msg/Time")(sec=sec, nanosec=nsec)
        extra = {"seq": 0} if self.flavour == "ros1" else {}
        return self.t("std_msgs/msg/Header")(**extra, stamp=stamp, frame_id=frame)

    def write(self, topic: str, msgtype: str, t_ns: int, msg: Any) -> None:
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype,
                                                                 typestore=self.store)
        c = self.connections[topic]
        data = (self.store.serialize_ros1(msg, msgtype) if self.flavour == "ros1"
                else self.store.serialize_cdr(msg, msgtype))
        self.writer.write(c, int(t_ns), data)

    def laser_scan(self, line: Any, range_min: float, range_max: float,
                   intensities: np.ndarray | None = None) -> Any:
        """A calstation line as a LaserScan in lidar_link: θ = −α; invalid returns as inf,
        nan or 0 in turn (REP-117 and common driver habits)."""
        az = np.asarray(line.azimuth_rad, np.float64)
        r = np.asarray(line.range_m, np.float64).copy()
        bad = np.flatnonzero(~np.asarray(line.valid))
        r[bad] = np.array([np.inf, np.nan, 0.0])[np.arange(len(bad)) % 3]
        return self.t("sensor_msgs/msg/LaserScan")(
            header=self.header(line.timestamp_ns),
            angle_min=np.float32(-az[0]), angle_max=np.float32(-az[-1]),
            angle_increment=np.float32(-(az[1] - az[0])),
            time_increment=np.float32(line.point_period_ns * 1e-9),
            scan_time=np.float32(0.005), range_min=np.float32(range_min),
            range_max=np.float32(range_max), ranges=r.astype(np.float32),
            intensities=(np.zeros(0, np.float32) if intensities is None
                         else intensities.astype(np.float32)),
        )
