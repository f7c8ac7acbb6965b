"""`--record mcap` (ros2/src/record.rs): a real eval run writes RUN_DIR/run.mcap, read back with
the `mcap` + `mcap-ros2-support` readers (and rosbags): per episode each robot's odometry count
is steps + 1, the outcome is episodes.csv's, and the final edge error recomputed from the
recorded poses, targets and slot map is `final_edge_error_m`. Skipped only when those packages
are missing (.ci/run installs them)."""

import bisect
import csv
import math
import re
from collections import defaultdict

import pytest

pytest.importorskip("mcap")
pytest.importorskip("mcap_ros2")
pytest.importorskip("rosbags")

from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402

from conftest import assert_clean, launch  # noqa: E402

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
