"""The ROS 2 side (ros2/, `--ros2`) checked against sources that are not ours: the RIHS01 type
hashes and the CDR bytes against rosbags, and a real run whose robot 2 is a ROS 2 node made of
eclipse-zenoh and rosbags (`python3 -m formation_swarm ros2-node 2`), beside a stranger that
sends malformed Twists. Skipped only when those packages are missing (.ci/run installs them)."""

import re
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("rosbags")

from rosbags.typesys import Stores, get_typestore  # noqa: E402

import ros2_golden  # noqa: E402
from conftest import REPO, assert_clean, kill_group, launch, wait_or_kill  # noqa: E402
from formation_swarm.ros2 import attachment, dds_name  # noqa: E402

WATCHDOG_S = 300
EPISODES = 20


def rust_types():
    """(ROS name, DDS name, hash) of every RosType constant in ros2/src/wire.rs."""
    text = (REPO / "ros2" / "src" / "wire.rs").read_text()
    return re.findall(r'RosType \{\s*name: "([^"]+)",\s*dds: "([^"]+)",\s*hash: "([^"]+)",', text)


def test_the_rust_sides_type_hashes_are_rosbags_rihs01():
    store = get_typestore(Stores.ROS2_JAZZY)
    kilted = get_typestore(Stores.ROS2_KILTED)
    types = rust_types()
    names = {name for name, _, _ in types}
    assert {"nav_msgs/msg/Odometry", "std_msgs/msg/Float32MultiArray", "rosgraph_msgs/msg/Clock",
            "geometry_msgs/msg/Twist", "std_msgs/msg/String", "sensor_msgs/msg/LaserScan",
            "visualization_msgs/msg/MarkerArray"} <= names, names
    for name, dds, hash_ in types:
        assert hash_ == store.hash_rihs01(name), name
        assert hash_ == kilted.hash_rihs01(name), f"{name} differs in Kilted"
        assert dds == dds_name(name)


def test_the_golden_cdr_files_are_what_rosbags_writes():
    for name, data in ros2_golden.messages().items():
        assert (ros2_golden.GOLDEN / name).read_bytes() == data, f"{name}: rerun python3 python/tests/ros2_golden.py"


def free_port():
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def stranger(endpoint, ready_timeout):
    """A Zenoh peer that waits for the ROS 2 side's cmd_vel subscription on the graph, then puts
    four bad Twists: one for robot 0 (not carried), and for robot 2 one whose bytes are not a
    Twist, one without an attachment, one with a NaN. Returns what it did."""
    store = get_typestore(Stores.ROS2_JAZZY)
    twist_type = "geometry_msgs/msg/Twist"
    key = lambda robot: (f"0/formation/robot_{robot}/cmd_vel/{dds_name(twist_type)}/"  # noqa: E731
                         f"{store.hash_rihs01(twist_type)}")
    vector = store.types["geometry_msgs/msg/Vector3"]
    twist = lambda w: bytes(store.serialize_cdr(store.types[twist_type](  # noqa: E731
        linear=vector(x=0.1, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=w)), twist_type))
    config = zenoh.Config()
    for k, v in [("mode", '"peer"'), ("connect/endpoints", f'["{endpoint}"]'), ("listen/endpoints", "[]"),
                 ("scouting/multicast/enabled", "false")]:
        config.insert_json5(k, v)
    seen = threading.Event()

    def on_token(sample):
        text = str(sample.key_expr)
        if "/MS/" in text and "formation_swarm" in text and "%robot_2%cmd_vel" in text:
            seen.set()

    session = zenoh.open(config)
    try:
        watch = session.liveliness().declare_subscriber("@ros2_lv/0/**", on_token, history=True)
        if not seen.wait(ready_timeout):
            return "the ROS 2 side's cmd_vel subscription never appeared"
        gid = bytes(range(16))
        session.put(key(0), twist(0.2), attachment=attachment(1, gid))
        session.put(key(2), b"\x00\x01\x00\x00garbage", attachment=attachment(2, gid))
        session.put(key(2), twist(0.2))
        session.put(key(2), twist(float("nan")), attachment=attachment(3, gid))
        time.sleep(0.5)
        watch.undeclare()
        return "sent"
    finally:
        session.close()


def test_a_ros2_node_made_of_zenoh_and_rosbags_drives_robot_2(tmp_path):
    """The sim waits for robot 2's node: the stranger's Twists come first (while the run cannot
    end), then the node starts and drives."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    run_dir = tmp_path / "run"
    node_log = tmp_path / "node.log"
    swarm = launch(["3", "--mode", "eval", "--scripted", "0,1", "--ros2", "2", "--episodes", str(EPISODES),
                    "--seed", "1000", "--viewer", "off", "--ros2-endpoint", endpoint], run_dir)
    node = None
    try:
        stranger_did = stranger(endpoint, 120)
        with open(node_log, "wb") as out:
            node = subprocess.Popen(
                [sys.executable, "-m", "formation_swarm", "ros2-node", "2", "--endpoint", endpoint],
                stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        status = swarm.wait(WATCHDOG_S)
        node.send_signal(signal.SIGTERM)
        node_status = wait_or_kill(node, 30)
    finally:
        if node is not None and node.poll() is None:
            kill_group(node)
        if swarm.proc.poll() is None:
            swarm.wait(0)
    log = node_log.read_text(errors="replace")
    ros2_log = (run_dir / "logs" / "ros2.log").read_text(errors="replace") if (run_dir / "logs").exists() else ""
    assert status == 0, f"launcher status {status}:\n{swarm.output}\nnode:\n{log}\nros2:\n{ros2_log}"
    assert node_status == 0, log
    assert stranger_did == "sent", stranger_did
    summary = swarm.summary()
    assert summary["episodes"] == EPISODES
    assert summary["success_rate"] >= 0.9, summary
    assert summary["collision_rate"] == 0, summary
    assert summary["ros2_agents"] == [2]
    assert summary["rejected_commands"] == 0, "nothing malformed reached the sim"
    assert summary["ros2_twists_rejected"] == 4, (summary, ros2_log)
    for reason in ["for a robot this side does not carry", "wrong length", "no rmw_zenoh attachment",
                   "non-finite value"]:
        assert reason in ros2_log, ros2_log
    assert summary["ros2_twists"] >= summary["env_steps"] - summary["missed_ticks"], summary
    sent = int(re.search(r"sent (\d+) twists, received (\d+) odometry", log).group(1))
    odometry = int(re.search(r"sent (\d+) twists, received (\d+) odometry", log).group(2))
    assert sent == summary["ros2_twists"] + summary["ros2_twists_dropped"] + summary["ros2_twists_superseded"], (
        summary, log)
    assert odometry == summary["env_steps"] + EPISODES, "one odometry per state, each tick 0 included"
    assert "ROS 2 robots 2" in swarm.output and "python3 -m formation_swarm ros2-node 2" in swarm.output
    assert_clean(swarm)
