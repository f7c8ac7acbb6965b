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
    scan = t["sensor_msgs/msg/LaserScan"](
        header=t["std_msgs/msg/Header"](stamp=time(3, 250_000_000), frame_id="robot_1/base_link"),
        angle_min=0.0, angle_max=math.tau * 15 / 16, angle_increment=math.tau / 16, time_increment=0.0,
        scan_time=0.1, range_min=0.0, range_max=2.0,
        ranges=np.array([0.5, 2.0, 1.25], dtype=np.float32), intensities=np.array([], dtype=np.float32),
    )
    out = {
        "odometry.cdr": store.serialize_cdr(odometry, "nav_msgs/msg/Odometry"),
        "float32_multi_array.cdr": store.serialize_cdr(array, "std_msgs/msg/Float32MultiArray"),
        "clock.cdr": store.serialize_cdr(clock, "rosgraph_msgs/msg/Clock"),
        "twist.cdr": store.serialize_cdr(twist, "geometry_msgs/msg/Twist"),
        "twist_be.cdr": store.serialize_cdr(twist, "geometry_msgs/msg/Twist", little_endian=False),
        "laser_scan.cdr": store.serialize_cdr(scan, "sensor_msgs/msg/LaserScan"),
        "marker_array.cdr": store.serialize_cdr(marker_array(t, time), "visualization_msgs/msg/MarkerArray"),
    }
    return {name: bytes(data) for name, data in out.items()}


def marker_array(t, time):
    """Two markers: a DELETEALL, then a box whose every sequence and string is set (the
    alignment of each field after a bool or a string)."""
    header = t["std_msgs/msg/Header"](stamp=time(3, 0), frame_id="world")
    vec = lambda x, y, z: t["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)  # noqa: E731
    point = lambda x, y, z: t["geometry_msgs/msg/Point"](x=x, y=y, z=z)  # noqa: E731
    color = lambda r, g, b, a: t["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=a)  # noqa: E731

    def marker(ns, id_, type_, action, pose, scale, rgba, **extra):
        fields = dict(
            header=header, ns=ns, id=id_, type=type_, action=action, pose=pose, scale=scale, color=rgba,
            lifetime=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0), frame_locked=False, points=[],
            colors=[], texture_resource="",
            texture=t["sensor_msgs/msg/CompressedImage"](
                header=t["std_msgs/msg/Header"](stamp=time(0, 0), frame_id=""), format="",
                data=np.array([], dtype=np.uint8)),
            uv_coordinates=[], text="", mesh_resource="",
            mesh_file=t["visualization_msgs/msg/MeshFile"](filename="", data=np.array([], dtype=np.uint8)),
            mesh_use_embedded_materials=False)
        fields.update(extra)
        return t["visualization_msgs/msg/Marker"](**fields)

    origin = t["geometry_msgs/msg/Pose"](position=point(0.0, 0.0, 0.0),
                                         orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=0.0))
    wall = t["geometry_msgs/msg/Pose"](position=point(2.0, 3.5, 0.15),
                                       orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(0.5),
                                                                                     w=math.cos(0.5)))
    delete_all = marker("obstacles", 0, 0, 3, origin, vec(0.0, 0.0, 0.0), color(0.0, 0.0, 0.0, 0.0))
    box = marker("obstacles", 7, 1, 0, wall, vec(3.0, 0.1, 0.3), color(0.5, 0.25, 0.125, 1.0),
                 frame_locked=True, points=[point(1.0, 2.0, 3.0)], colors=[color(1.0, 0.0, 0.0, 1.0)],
                 texture_resource="t",
                 texture=t["sensor_msgs/msg/CompressedImage"](
                     header=t["std_msgs/msg/Header"](stamp=time(1, 2), frame_id="cam"), format="png",
                     data=np.array([1, 2, 3], dtype=np.uint8)),
                 uv_coordinates=[t["visualization_msgs/msg/UVCoordinate"](u=0.25, v=0.75)], text="wall",
                 mesh_resource="m",
                 mesh_file=t["visualization_msgs/msg/MeshFile"](filename="f", data=np.array([9], dtype=np.uint8)),
                 mesh_use_embedded_materials=True)
    return t["visualization_msgs/msg/MarkerArray"](markers=[delete_all, box])


def main() -> int:
    GOLDEN.mkdir(parents=True, exist_ok=True)
    for name, data in messages().items():
        (GOLDEN / name).write_bytes(data)
        print(f"{GOLDEN / name}: {len(data)} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
