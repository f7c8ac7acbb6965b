"""Golden CDR files for the ROS 2 side's Rust unit tests (ros2/src/wire.rs), written by
``rosbags``' ROS 2 type store, not by our code. ``python3 python/tests/ros2_golden.py`` rewrites
them into ros2/tests/golden/; test_ros2.py checks that the checked-in files are what rosbags
writes today."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Dict

import numpy as np
from rosbags.typesys import Stores, get_typestore

GOLDEN = Path(__file__).resolve().parents[2] / "ros2" / "tests" / "golden"


def messages() -> Dict[str, bytes]:
    """Each golden file's name and bytes, as wire.rs's tests build the same messages."""
    store = get_typestore(Stores.ROS2_JAZZY)
    t = store.types
    time = lambda sec, nanosec: t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)  # noqa: E731
    vec = lambda x, y, z: t["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)  # noqa: E731
    pose_cov = np.zeros(36)
    pose_cov[0], pose_cov[35] = 0.01, 0.02
    odometry = t["nav_msgs/msg/Odometry"](
        header=t["std_msgs/msg/Header"](stamp=time(12, 300_000_000), frame_id="world"),
        child_frame_id="robot_2/base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=1.5, y=-2.25, z=0.0),
                orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(0.25), w=math.cos(0.25)),
            ),
            covariance=pose_cov,
        ),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](linear=vec(0.4, 0.0, 0.0), angular=vec(0.0, 0.0, -0.7)),
            covariance=np.zeros(36),
        ),
    )
    array = t["std_msgs/msg/Float32MultiArray"](
        layout=t["std_msgs/msg/MultiArrayLayout"](
            dim=[t["std_msgs/msg/MultiArrayDimension"](label="relative", size=3, stride=3)], data_offset=0
        ),
        data=np.array([0.25, -1.0, 3.5], dtype=np.float32),
    )
    clock = t["rosgraph_msgs/msg/Clock"](clock=time(7, 100_000_000))
    twist = t["geometry_msgs/msg/Twist"](linear=vec(0.3, 0.0, 0.0), angular=vec(0.0, 0.0, 0.8))
    out = {
        "odometry.cdr": store.serialize_cdr(odometry, "nav_msgs/msg/Odometry"),
        "float32_multi_array.cdr": store.serialize_cdr(array, "std_msgs/msg/Float32MultiArray"),
        "clock.cdr": store.serialize_cdr(clock, "rosgraph_msgs/msg/Clock"),
        "twist.cdr": store.serialize_cdr(twist, "geometry_msgs/msg/Twist"),
        "twist_be.cdr": store.serialize_cdr(twist, "geometry_msgs/msg/Twist", little_endian=False),
    }
    return {name: bytes(data) for name, data in out.items()}


def main() -> int:
    GOLDEN.mkdir(parents=True, exist_ok=True)
    for name, data in messages().items():
        (GOLDEN / name).write_bytes(data)
        print(f"{GOLDEN / name}: {len(data)} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
