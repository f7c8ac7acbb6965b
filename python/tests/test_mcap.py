"""`--record mcap` (ros2/src/record.rs): a real eval run writes RUN_DIR/run.mcap, read back with
the `mcap` + `mcap-ros2-support` readers (and rosbags): per episode each robot's odometry count
is steps + 1, the outcome is episodes.csv's, and the final edge error recomputed from the
recorded poses, targets and slot map is `final_edge_error_m`. A `--ros2` run through obstacles
records each robot's LaserScan and the obstacles' MarkerArray. Skipped only when those packages
are missing (.ci/run installs them; the --ros2 run also needs eclipse-zenoh)."""

import bisect
import csv
import math
import os
import re
import signal
import threading
import time
from collections import defaultdict
from pathlib import Path

import pytest

pytest.importorskip("mcap")
pytest.importorskip("mcap_ros2")
pytest.importorskip("rosbags")

from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402

from conftest import assert_clean, launch, processes_mentioning  # noqa: E402

WATCHDOG_S = 300
N = 4
EPISODES = 5


def read_mcap(path):
    """{topic: [(log_time, decoded message)]} in log-time order, and each topic's schema name."""
    topics, schemas = defaultdict(list), {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, message, msg in reader.iter_decoded_messages(log_time_order=True):
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            topics[channel.topic].append((message.log_time, msg))
            schemas[channel.topic] = schema.name
    return topics, schemas


def in_force(messages, t):
    """The newest of ``messages`` (log-time ordered) at or before ``t``."""
    times = [time for time, _ in messages]
    return messages[bisect.bisect_right(times, t) - 1][1]


def edge_error(poses, targets, slot_of):
    """The sim's mean edge error (core/src/task.rs): each robot's two observed edges, to the
    robots in the next two slots, against the slot offsets' distances."""
    n = len(poses)
    robot_in = {slot: robot for robot, slot in enumerate(slot_of)}
    total = 0.0
    for i in range(n):
        for k in (1, 2):
            j = robot_in[(slot_of[i] + k) % n]
            desired = math.dist(targets[i], targets[j])
            total += abs(math.dist(poses[i], poses[j]) - desired)
    return total / (2 * n)


def test_an_eval_run_recorded_as_mcap_matches_its_episodes(tmp_path):
    config = tmp_path / "changes.toml"
    # Two shape changes an episode: the target formation and the slot map change mid-episode.
    config.write_text("[env]\nshape_changes = 2\n")
    run_dir = tmp_path / "run"
    swarm = launch([str(N), "--mode", "eval", "--scripted", "all", "--episodes", str(EPISODES), "--seed", "7",
                    "--viewer", "off", "--config", str(config), "--record", "mcap"], run_dir)
    status = swarm.wait(WATCHDOG_S)
    assert status == 0, f"launcher status {status}:\n{swarm.output}"
    assert_clean(swarm)
    mcap_log = (run_dir / "logs" / "mcap.log").read_text()
    assert "lost" not in mcap_log, mcap_log

    topics, schemas = read_mcap(run_dir / "run.mcap")
    for robot in range(N):
        assert schemas[f"/formation/robot_{robot}/odom"] == "nav_msgs/msg/Odometry"
        assert schemas[f"/formation/robot_{robot}/cmd_applied"] == "geometry_msgs/msg/TwistStamped"
    assert schemas["/formation/target"] == schemas["/formation/goal"] == "geometry_msgs/msg/PoseArray"
    assert schemas["/formation/reward"] == "std_msgs/msg/Float32"
    assert schemas["/formation/outcome"] == "std_msgs/msg/String"

    dt_s = float(re.search(r"^dt_s = (\S+)$", (run_dir / "config.toml").read_text(), re.M).group(1))
    rows = list(csv.DictReader(open(run_dir / "episodes.csv")))
    assert len(rows) == EPISODES
    starts = [(t, msg.data) for t, msg in topics["/formation/episode"]]
    ends = [t for t, _ in topics["/formation/outcome"]]
    assert [episode for _, episode in starts] == list(range(EPISODES))
    assert len(ends) == EPISODES
    for robot in range(N):
        odometry = topics[f"/formation/robot_{robot}/odom"]
        times = [t for t, _ in odometry]
        assert all(a < b for a, b in zip(times, times[1:])), "odometry stamps rise across episodes"
        for (t, msg) in odometry:
            stamp = msg.header.stamp
            assert stamp.sec * 10**9 + stamp.nanosec == t
    changed_mid_episode = 0
    for k, row in enumerate(rows):
        start, end = starts[k][0], ends[k]
        steps = int(row["steps"])
        assert abs(end - start - round(steps * dt_s * 1e9)) <= 1, "stamps are sim time, tick x dt"
        assert topics["/formation/outcome"][k][1].data == row["outcome"], (k, row)
        final_poses = []
        for robot in range(N):
            odometry = [(t, msg) for t, msg in topics[f"/formation/robot_{robot}/odom"] if start <= t <= end]
            assert len(odometry) == steps + 1, (k, robot, len(odometry), steps)
            assert odometry[-1][0] == end
            position = odometry[-1][1].pose.pose.position
            final_poses.append((position.x, position.y))
            commands = [t for t, _ in topics[f"/formation/robot_{robot}/cmd_applied"] if start <= t < end]
            assert len(commands) == steps, (k, robot, len(commands))
        rewards = [msg.data for t, msg in topics["/formation/reward"] if start < t <= end]
        assert len(rewards) == steps
        assert math.isclose(sum(rewards), float(row["episode_return"]), abs_tol=1e-3), (k, sum(rewards), row)
        targets = [(p.position.x, p.position.y) for p in in_force(topics["/formation/target"], end).poses]
        slot_of = list(in_force(topics["/formation/slot"], end).data)
        recomputed = edge_error(final_poses, targets, slot_of)
        assert abs(recomputed - float(row["final_edge_error_m"])) <= 1e-4, (k, recomputed, row)
        changed_mid_episode += sum(1 for t, _ in topics["/formation/target"] if start < t <= end)
    assert changed_mid_episode > 0, "the shape changes were recorded when they happened"

    # rosbags reads the same file through its own type system (from the schemas in the file).
    with AnyReader([run_dir / "run.mcap"]) as reader:
        decoded = sum(1 for c, _, raw in reader.messages() if reader.deserialize(raw, c.msgtype) is not None)
    assert decoded == sum(len(messages) for messages in topics.values())


def test_a_recorder_that_stalls_loses_no_state_the_sim_waits_for_it(tmp_path):
    """The recorder is stopped (SIGSTOP) for a second mid-run, several times the state stream's
    buffer at the sim's pace: the sim holds within a window of it instead of running on, so
    afterwards every state of every episode is in the file and nothing was lost."""
    config = tmp_path / "slow_recorder.toml"
    # The sim gives a silent reader up after a quarter of sim_silence_ms: well past the pause.
    config.write_text("[ticks]\nsim_silence_ms = 20000\n")
    run_dir = tmp_path / "run"
    episodes = 12
    swarm = launch([str(N), "--mode", "eval", "--scripted", "all", "--episodes", str(episodes), "--seed", "11",
                    "--viewer", "off", "--config", str(config), "--record", "mcap"], run_dir)
    try:
        deadline = time.monotonic() + 60
        recorder = []
        while time.monotonic() < deadline and not (recorder and (run_dir / "episodes.csv").exists()):
            recorder = [pid for pid in processes_mentioning(str(run_dir))
                        if b"formation-mcap" in Path(f"/proc/{pid}/cmdline").read_bytes()]
            time.sleep(0.05)
        assert recorder, f"no recorder process:\n{swarm.output}"
        os.kill(recorder[0], signal.SIGSTOP)
        try:
            before = len(list(csv.DictReader(open(run_dir / "episodes.csv"))))
            time.sleep(1.0)
            during = len(list(csv.DictReader(open(run_dir / "episodes.csv"))))
        finally:
            os.kill(recorder[0], signal.SIGCONT)
        status = swarm.wait(WATCHDOG_S)
    finally:
        if swarm.proc.poll() is None:
            swarm.wait(0)
    assert status == 0, f"launcher status {status}:\n{swarm.output}"
    assert_clean(swarm)
    # At most a window of ticks while the recorder slept: one episode may have ended in it.
    assert during - before <= 1, (before, during)
    mcap_log = (run_dir / "logs" / "mcap.log").read_text()
    assert "lost" not in mcap_log and f"of {episodes} episodes" in mcap_log, mcap_log
    topics, _ = read_mcap(run_dir / "run.mcap")
    rows = list(csv.DictReader(open(run_dir / "episodes.csv")))
    states = sum(int(row["steps"]) + 1 for row in rows)
    assert len(topics["/formation/robot_0/odom"]) == states, (len(topics["/formation/robot_0/odom"]), states)


def surface_distance(point, markers, others, arena_m, robot_radius):
    """How far ``point`` is from the nearest surface the range sensor sees: an obstacle marker
    (a cylinder's side, a box's outline), another robot's disc or the arena's walls."""
    px, py = point
    nearest = min(px, py, arena_m - px, arena_m - py)
    for marker in markers:
        c = marker.pose.position
        if marker.type == CYLINDER:
            nearest = min(nearest, abs(math.dist((px, py), (c.x, c.y)) - marker.scale.x / 2))
        else:
            q = marker.pose.orientation
            yaw = 2 * math.atan2(q.z, q.w)
            dx, dy = px - c.x, py - c.y
            along = abs(math.cos(yaw) * dx + math.sin(yaw) * dy) - marker.scale.x / 2
            across = abs(-math.sin(yaw) * dx + math.cos(yaw) * dy) - marker.scale.y / 2
            outside = math.hypot(max(along, 0.0), max(across, 0.0))
            nearest = min(nearest, outside if outside > 0 else -max(along, across))
    for other in others:
        nearest = min(nearest, abs(math.dist((px, py), other) - robot_radius))
    return nearest


CUBE, CYLINDER, DELETEALL = 1, 3, 3
ROS2_N, ROS2_EPISODES, ROS2_ROBOT = 3, 3, 2


def test_a_ros2_run_among_obstacles_records_its_scans_and_obstacles(tmp_path):
    """A --ros2 run through a passage (robot 2 a ROS 2 node in this process): the MCAP holds
    each robot's LaserScan at every state (16 rays, range_max 2 m, its body frame, stamped as
    its odometry) and one MarkerArray of the obstacles per episode, decoded by the mcap ROS 2
    reader; every ray shorter than range_max ends on a surface: an obstacle marker, another
    robot or the arena's wall. The node received the scans on /formation/robot_2/scan."""
    zenoh = pytest.importorskip("zenoh")  # noqa: F841 - the node's transport
    from formation_swarm.ros2 import Ros2Node
    from test_ros2 import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    run_dir = tmp_path / "run"
    swarm = launch([str(ROS2_N), "--mode", "eval", "--scripted", "0,1", "--ros2", str(ROS2_ROBOT),
                    "--obstacles", "passage", "--episodes", str(ROS2_EPISODES), "--seed", "2000",
                    "--viewer", "off", "--ros2-endpoint", endpoint, "--record", "mcap"], run_dir)
    node = None
    try:
        # A Zenoh peer dials again until the side listens.
        node = Ros2Node(ROS2_ROBOT, endpoint)
        spinning = threading.Thread(target=node.spin, kwargs={"idle_exit": 5.0}, daemon=True)
        spinning.start()
        status = swarm.wait(WATCHDOG_S)
        spinning.join(30)
    finally:
        if node is not None:
            node.close()
        if swarm.proc.poll() is None:
            swarm.wait(0)
    ros2_log = (run_dir / "logs" / "ros2.log").read_text(errors="replace")
    assert status == 0, f"launcher status {status}:\n{swarm.output}\nros2:\n{ros2_log}"
    assert_clean(swarm)
    assert node.scans > 0 and len(node.latest_scan.ranges) == 16, node.scans
    assert node.latest_scan.header.frame_id == f"robot_{ROS2_ROBOT}/base_link"
    assert f"{ROS2_EPISODES} obstacle marker arrays" in ros2_log, ros2_log

    config = (run_dir / "config.toml").read_text()
    number = lambda key: float(re.search(rf"^{key} = (\S+)$", config, re.M).group(1))  # noqa: E731
    assert re.search(r'^observation = "slot_proximity_scan"$', config, re.M), config
    arena_m, robot_radius = number("arena_m"), number("eps_coll_m") / 2
    topics, schemas = read_mcap(run_dir / "run.mcap")
    assert schemas["/formation/obstacles"] == "visualization_msgs/msg/MarkerArray"
    starts = [t for t, _ in topics["/formation/episode"]]
    arrays = topics["/formation/obstacles"]
    assert [t for t, _ in arrays] == starts, "one marker array at each episode's first state"
    for _, array in arrays:
        assert array.markers[0].action == DELETEALL
        assert len(array.markers) >= 2 and {m.type for m in array.markers[1:]} <= {CUBE, CYLINDER}
        assert all(m.header.frame_id == "world" and m.ns == "obstacles" for m in array.markers)

    poses = {}
    for robot in range(ROS2_N):
        for t, odometry in topics[f"/formation/robot_{robot}/odom"]:
            q = odometry.pose.pose.orientation
            poses[robot, t] = (odometry.pose.pose.position.x, odometry.pose.pose.position.y,
                               2 * math.atan2(q.z, q.w))
    assert schemas["/tf"] == "tf2_msgs/msg/TFMessage"
    for t, tf in topics["/tf"]:
        for transform in tf.transforms:
            robot = int(re.fullmatch(r"robot_(\d+)/base_link", transform.child_frame_id).group(1))
            x, y, _ = poses[robot, t]
            assert transform.header.frame_id == "world"
            assert (transform.transform.translation.x, transform.transform.translation.y) == (x, y)
    assert len(topics["/tf"]) == len(topics["/formation/robot_0/odom"]), "one transform message per state"
    hits, on_obstacles = 0, 0
    for robot in range(ROS2_N):
        assert schemas[f"/formation/robot_{robot}/scan"] == "sensor_msgs/msg/LaserScan"
        scans = topics[f"/formation/robot_{robot}/scan"]
        assert [t for t, _ in scans] == [t for t, _ in topics[f"/formation/robot_{robot}/odom"]]
        for t, scan in scans:
            assert scan.header.frame_id == f"robot_{robot}/base_link"
            assert scan.header.stamp.sec * 10**9 + scan.header.stamp.nanosec == t
            assert len(scan.ranges) == 16 and scan.range_max == 2.0 and scan.angle_min == 0.0
            markers = in_force(arrays, t).markers[1:]
            x, y, theta = poses[robot, t]
            others = [poses[k, t][:2] for k in range(ROS2_N) if k != robot]
            for k, r in enumerate(scan.ranges):
                if r >= scan.range_max - 1e-4:
                    continue
                angle = theta + scan.angle_min + k * scan.angle_increment
                end = (x + r * math.cos(angle), y + r * math.sin(angle))
                assert surface_distance(end, markers, others, arena_m, robot_radius) < 1e-3, (robot, t, k, r)
                hits += 1
                on_obstacles += surface_distance(end, markers, [], math.inf, 0.0) < 1e-3
    assert hits > 0 and on_obstacles > 0, (hits, on_obstacles)
