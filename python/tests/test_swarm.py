"""Real multi-process runs with a robot played from Python: scripts/run_swarm.sh starts the
sim, the other robots and the critic; the Python robot is its own process, as a user would run
it. Every process has a watchdog; nothing may be left in /dev/shm."""

import csv
import json
import math
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from formation_swarm import Observer, connect, wire
from formation_swarm.run import OBSERVATION_DIMS

from conftest import assert_clean, kill_group, launch, python_robot, remove_leftovers, wait_or_kill

WATCHDOG_S = 240


def _config_value(text, section, key):
    """A value of the complete config.toml the sim writes (plain `key = value` lines)."""
    current = None
    for line in text.splitlines():
        line = line.split("#")[0].strip()
        if line.startswith("["):
            current = line.strip("[]")
        elif current == section and re.match(rf"{key}\s*=", line):
            return line.split("=", 1)[1].strip().strip('"')
    raise KeyError(f"{section}.{key}")


def check_run_json(run_dir, external):
    """run.json agrees with the config.toml the sim wrote (the launcher computes it in bash)."""
    info = json.loads((run_dir / "run.json").read_text())
    config = (run_dir / "config.toml").read_text()
    assert info["external"] == external
    assert info["shm_prefix"] == f"fc_{info['run_id']}_"
    assert info["observation"] == _config_value(config, "env", "observation")
    assert info["observation_dim"] == OBSERVATION_DIMS[info["observation"]]
    for section, key in [("ticks", "critic_window"), ("ticks", "startup_timeout_s"), ("ticks", "sim_silence_ms"),
                         ("ticks", "command_timeout_ms"), ("env", "v_max"), ("env", "w_max"),
                         ("env", "proximity_range_m")]:
        assert float(info[key]) == float(_config_value(config, section, key)), key


def unicycle(pose, v, w, dt):
    """``formation_core::physics::integrate``: exact integration of the unicycle over ``dt`` with
    constant (v, w), a circular arc whose chord is v dt sinc(w dt / 2) at the mean heading (sinc
    by its series near 0); the heading wrapped to (-pi, pi]. Before the arena's clamp."""
    x, y, theta = pose
    half_turn = 0.5 * w * dt
    sinc = 1.0 - half_turn * half_turn / 6.0 if abs(half_turn) < 1e-6 else math.sin(half_turn) / half_turn
    chord = v * dt * sinc
    heading = math.remainder(theta + w * dt, 2 * math.pi)
    return x + chord * math.cos(theta + half_turn), y + chord * math.sin(theta + half_turn), heading


def check_unicycle_steps(world, dt, arena_m, v_max, w_max, tolerance=1e-4):
    """Every robot's pose at tick t+1 of an episode is the exact unicycle integration of its pose
    at tick t under the command the state of tick t+1 says was applied in that transition (the
    command of tick t, clamped to the limits), kept in the arena (x, y clamped to [0, side], the
    side at least ``arena_m``). Returns how many robot-steps were checked."""
    checked = 0
    for before, after in zip(world, world[1:]):
        if after.episode != before.episode or after.tick != before.tick + 1:
            continue
        for robot, (pose, (v, w), got) in enumerate(zip(before.poses, after.applied, after.poses)):
            where = f"episode {after.episode} tick {before.tick} -> {after.tick}, robot {robot}"
            assert 0.0 <= v <= v_max and -w_max <= w <= w_max, f"{where}: applied ({v}, {w}) past the limits"
            x, y, theta = unicycle(pose, v, w, dt)
            for axis, want, value in (("x", x, got[0]), ("y", y, got[1])):
                if want < 0.0:
                    assert value == 0.0, f"{where}: {axis} {value} is not clamped to 0 ({want})"
                elif want > arena_m:
                    # The arena may grow past arena_m for larger swarms: the side is in [arena_m, want].
                    assert arena_m - tolerance <= value <= want + tolerance, f"{where}: {axis} {value}, wanted {want}"
                else:
                    assert abs(value - want) <= tolerance, f"{where}: {axis} {value}, unicycle gives {want}"
            turn = math.remainder(got[2] - theta, 2 * math.pi)
            assert abs(turn) <= tolerance, f"{where}: theta {got[2]}, unicycle gives {theta}"
            checked += 1
    return checked


def run_with_python_robot(tmp_path, extra_args, episodes):
    run_dir = tmp_path / "run"
    # The robot starts first and waits for run.json: both start orders must work.
    robot = python_robot(run_dir, 2, tmp_path / "robot.log")
    swarm = launch(["3", "--mode", "eval", "--scripted", "0,1", "--external", "2", "--episodes", str(episodes),
                    "--seed", "1", "--viewer", "off", *extra_args], run_dir)
    try:
        status = swarm.wait(WATCHDOG_S)
        robot_status = wait_or_kill(robot, 30)
    finally:
        if robot.poll() is None:
            wait_or_kill(robot, 0)
        if swarm.proc.poll() is None:
            swarm.wait(0)  # kills the launcher's group and removes the run's shared memory
    robot_log = (tmp_path / "robot.log").read_text(errors="replace")
    assert status == 0, f"launcher status {status}:\n{swarm.output}\nrobot:\n{robot_log}"
    assert robot_status == 0, f"python robot status {robot_status}:\n{robot_log}"
    assert "external robots 2" in swarm.output and "python3 -m formation_swarm robot" in swarm.output
    assert_clean(swarm)
    return swarm, robot_log


def test_python_baseline_plays_robot_2_of_an_eval_run(tmp_path):
    swarm, robot_log = run_with_python_robot(tmp_path, [], 20)
    summary = swarm.summary()
    print(json.dumps({k: summary[k] for k in ("episodes", "success_rate", "collision_rate", "missed_ticks",
                                              "rejected_commands", "env_steps_per_s", "wall_s")}))
    assert summary["episodes"] == 20
    assert summary["success_rate"] >= 0.9, summary
    assert summary["rejected_commands"] == 0
    assert summary["scripted_agents"] == [0, 1]
    assert summary["external_agents"] == [2], "the summary says which robots were outside"
    assert "run ended after" in robot_log
    assert "corrupt" not in robot_log.lower(), robot_log
    check_run_json(swarm.run_dir, [2])


def test_a_python_robot_holds_the_clients_lock_while_its_ports_are_open(tmp_path):
    """The launcher removes a run's files only once no client holds the run's clients lock, so a
    Python robot whose ports outlive the sim removes its services itself (iceoryx2 would warn
    of a corrupted system otherwise): the lock is held from the Robot's start to its close."""
    import fcntl

    from formation_swarm import Baseline, Robot

    run_dir = tmp_path / "run"
    swarm = launch(["3", "--mode", "eval", "--scripted", "0,1", "--external", "2", "--episodes", "2",
                    "--seed", "1", "--viewer", "off"], run_dir)
    try:
        robot = Robot(run_dir, 2, Baseline(), connect_timeout=30)
        lock = os.open(f"/dev/shm/{robot.run.shm_prefix}clients.lock", os.O_RDONLY)
        try:
            with pytest.raises(BlockingIOError):
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            assert robot.run_forever().episodes == 2
            robot.close()
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)  # free once the ports are gone
            fcntl.flock(lock, fcntl.LOCK_UN)
        finally:
            os.close(lock)
        assert swarm.wait(WATCHDOG_S) == 0, swarm.output
    finally:
        if swarm.proc.poll() is None:
            swarm.wait(0)
    assert_clean(swarm)


def test_python_baseline_on_the_papers_observation(tmp_path):
    """A --config run: run.json carries the 12-float model, the Python baseline follows it."""
    config = tmp_path / "paper-observation.toml"
    config.write_text('[env]\nobservation = "paper"  # two neighbours and the goal\n')
    swarm, _ = run_with_python_robot(tmp_path, ["--config", str(config)], 5)
    check_run_json(swarm.run_dir, [2])
    assert json.loads((swarm.run_dir / "run.json").read_text())["observation_dim"] == 12
    assert swarm.summary()["episodes"] == 5


def test_observer_reads_consecutive_states(tmp_path):
    """An Observer beside a run whose robot 2 is external reads consecutive ticks of the true
    state, then the end of the run; the poses of consecutive ticks obey the unicycle model under
    the applied commands the states carry."""
    run_dir = tmp_path / "run"
    swarm = launch(["3", "--mode", "eval", "--scripted", "0,1", "--external", "2", "--episodes", "3",
                    "--seed", "2", "--viewer", "off"], run_dir)
    robot = None
    try:
        run = connect(run_dir, timeout=30)
        observer = Observer(run)
        # Attached a while after the launcher started, as a user reading its instructions would:
        # the sim waits for robot 2 meanwhile (and the launcher's watch loop runs).
        time.sleep(1.5)
        assert swarm.proc.poll() is None, swarm.output
        robot = python_robot(run_dir, 2, tmp_path / "robot.log")
        world = list(observer.states(timeout=60))
        observer.close()
        assert observer.run_ended, "the observer saw the end of the run (or the sim leave)"
        assert len(world) > 20
        for before, after in zip(world, world[1:]):
            assert after.sequence == before.sequence + 1, "no state lost"
            if after.episode == before.episode:
                assert after.tick == before.tick + 1
            else:
                assert after.tick == 0 and after.episode == before.episode + 1
        assert all(s.n_agents == 3 and len(s.poses) == 3 for s in world)
        ends = [s for s in world if s.outcome != 0]
        assert len(ends) == 3 and all(s.outcome_name == "success" for s in ends)
        # The true states follow the sim's kinematics exactly: consecutive ticks of an episode
        # are one unicycle step apart under the applied commands (dt and limits of this run).
        config = (run_dir / "config.toml").read_text()
        checked = check_unicycle_steps(world, float(_config_value(config, "env", "dt_s")),
                                       float(_config_value(config, "env", "arena_m")), run.v_max, run.w_max)
        assert checked == 3 * (len(world) - 3), "every robot-step of the three episodes was checked"
        assert any(v > 0.0 for s in world for v, _ in s.applied), "the robots moved"
        status = swarm.wait(WATCHDOG_S)
        assert status == 0, swarm.output
        assert wait_or_kill(robot, 30) == 0
    finally:
        if robot is not None and robot.poll() is None:
            wait_or_kill(robot, 0)
        if swarm.proc.poll() is None:
            swarm.wait(0)
    assert_clean(swarm)


def _rejoin_of(sim_log, agent):
    """(episode, tick) of the sim's ``agent A rejoined at episode E tick T`` lines."""
    return [(int(e), int(t)) for e, t in re.findall(rf"sim: agent {agent} rejoined at episode (\d+) tick (\d+)", sim_log)]


def test_a_killed_python_robot_is_replaced_and_the_run_goes_on(tmp_path):
    """Robot 2 played from Python is SIGKILLed in the middle of an episode a few episodes into an
    eval run; a new ``python3 -m formation_swarm robot RUN_DIR 2`` takes its slot, and the run
    finishes every episode with the launcher's status 0.

    A run of scripted robots plays thousands of ticks a second (a whole 100-episode run took
    0.34 s), faster than a test can catch a given tick by looking. So the robot is first stopped
    (SIGSTOP): the sim then waits at the tick whose command it owes, and the test reads where
    that is. Mid-episode, the robot is killed there; at an episode's first tick it is let go on
    and stopped again a little later.

    The sim holds a dead robot's last command and waits ``ticks.command_timeout_ms`` per tick
    for it, then after 3 missed ticks stops waiting and races through the episodes with it
    standing still (about 200 episodes/s). With the default 200 ms that leaves 0.6 s for a fresh
    Python process to greet, which a busy machine does not always manage: this run waits 1.5 s
    per tick (4.5 s in all) so that the replacement reliably finds the run where the old robot
    left it."""
    episodes = 300
    config = tmp_path / "patient.toml"
    config.write_text("[ticks]\ncommand_timeout_ms = 1500  # a replacement robot has 4.5 s to greet\n")
    run_dir = tmp_path / "run"
    swarm = launch(["3", "--mode", "eval", "--scripted", "0,1", "--external", "2", "--episodes", str(episodes),
                    "--seed", "3", "--viewer", "off", "--config", str(config)], run_dir)
    first = replacement = None
    try:
        run = connect(run_dir, timeout=30)
        observer = Observer(run, poll_s=0.002)
        first = python_robot(run_dir, 2, tmp_path / "robot-1.log")
        world, killed_at = [], None
        deadline = time.monotonic() + 60
        while killed_at is None:
            assert time.monotonic() < deadline, f"no robot stopped mid-episode within 60 s:\n{swarm.output}"
            assert swarm.proc.poll() is None and first.poll() is None, swarm.output
            world.extend(observer.wait(0.05))
            if not world or world[-1].episode < 3:
                continue
            os.killpg(first.pid, signal.SIGSTOP)
            # The sim waits up to command_timeout_ms (1.5 s) for the stopped robot's command:
            # in 0.2 s every state it published has arrived, the newest the tick it waits at.
            time.sleep(0.2)
            world.extend(observer.receive())
            newest = world[-1]
            if newest.tick >= 1 and newest.outcome == 0:
                kill_group(first)
                killed_at = newest
            else:
                os.killpg(first.pid, signal.SIGCONT)
        replacement = python_robot(run_dir, 2, tmp_path / "robot-2.log")
        world.extend(observer.states(timeout=60))
        observer.close()
        assert observer.run_ended, "the observer saw the end of the run (or the sim leave)"
        status = swarm.wait(WATCHDOG_S)
        replacement_status = wait_or_kill(replacement, 30)
    finally:
        for robot in (first, replacement):
            if robot is not None and robot.poll() is None:
                wait_or_kill(robot, 0)
        if swarm.proc.poll() is None:
            swarm.wait(0)  # kills the launcher's group and removes the run's shared memory
    logs = "\n".join(f"{f.name}:\n{f.read_text(errors='replace')}" for f in sorted(tmp_path.glob("robot-*.log")))
    sim_log = (run_dir / "logs" / "sim.log").read_text(errors="replace")
    assert status == 0, f"launcher status {status}:\n{swarm.output}\n{logs}\n{sim_log}"
    assert first.returncode == -9, "the first robot died of the SIGKILL"
    assert replacement_status == 0, f"replacement robot status {replacement_status}:\n{logs}"
    assert "run ended after" in (tmp_path / "robot-2.log").read_text(errors="replace")

    summary = swarm.summary()
    print(json.dumps({k: summary[k] for k in ("episodes", "success_rate", "missed_ticks", "rejoined_agents",
                                              "rejected_commands", "wall_s")}))
    assert summary["episodes"] == episodes
    assert summary["rejoined_agents"] == 1, summary
    assert summary["rejected_commands"] == 0, summary
    rejoins = _rejoin_of(sim_log, 2)
    assert len(rejoins) == 1, sim_log
    rejoined = rejoins[0]

    # The robot died mid-episode: the first tick whose command was missing (the state after it
    # counts it) comes after the ticks it had answered in that episode.
    missing = [s for s in world if s.missed > 0]
    assert missing, "the states counted the dead robot's missing commands"
    first_miss = (missing[0].episode, missing[0].tick - 1)
    assert first_miss > (killed_at.episode, killed_at.tick - 1) and first_miss[1] >= 1, (killed_at, first_miss)
    assert rejoined >= first_miss, (first_miss, rejoined)

    rows = list(csv.DictReader((run_dir / "episodes.csv").open()))
    assert [int(r["episode"]) for r in rows] == list(range(episodes))
    missed = {int(r["episode"]): int(r["missed_ticks"]) for r in rows if int(r["missed_ticks"]) > 0}
    # Every missed tick is robot 2's while it was dead: between its death and the replacement's
    # greeting (robots 0 and 1 answered every tick).
    assert missed and all(first_miss[0] <= e <= rejoined[0] for e in missed), (first_miss, rejoined, missed)
    assert sum(missed.values()) == summary["missed_ticks"] >= 1
    # The episodes that started after the replacement greeted are played as well as ever.
    after = [r for r in rows if int(r["episode"]) > rejoined[0]]
    assert len(after) >= 10, f"only {len(after)} episodes after the rejoin at {rejoined}"
    success = sum(r["outcome"] == "success" for r in after) / len(after)
    assert success >= 0.9, [(r["episode"], r["outcome"]) for r in after]
    assert all(int(r["missed_ticks"]) == 0 for r in after)
    assert_clean(swarm)


def test_external_flag_is_validated(tmp_path):
    for args, message in [(["--external", "3"], "robot 3 does not exist (robots are 0..2)"),
                          (["--external", "x"], "--external takes 'all' or indices"),
                          (["--scripted", "0,2", "--external", "2"], "cannot be both --scripted and --external")]:
        done = subprocess.run(["scripts/run_swarm.sh", "3", *args, "--run-dir", str(tmp_path / "r")],
                              cwd=str(__import__("conftest").REPO), capture_output=True, text=True, timeout=30)
        assert done.returncode == 2 and message in done.stderr, (args, done.stderr)
        assert not (tmp_path / "r").exists()


def test_robot_refuses_a_run_of_another_protocol(tmp_path):
    run_dir = tmp_path / "fake"
    run_dir.mkdir()
    (run_dir / "run.json").write_text(json.dumps({"protocol_version": 999, "run_id": "x", "launcher_pid": 0}))
    done = subprocess.run([sys.executable, "-m", "formation_swarm", "robot", str(run_dir), "0",
                           "--connect-timeout", "1"], capture_output=True, text=True, timeout=30)
    assert done.returncode == 1 and "speaks protocol 999" in done.stderr, done.stderr


def test_services_python_creates_first_open_in_rust(tmp_path):
    """Python sizes every service exactly as protocol/src/services.rs does: services a Python
    robot and an Observer create before any Rust process exists are opened by the sim and the
    Rust agents (binaries started directly, with a run.json written by hand)."""
    from conftest import bin_dir, processes_mentioning, root_path, shm_leftovers

    from formation_swarm import Baseline, Robot

    run_id = f"pyfirst{os.getpid()}"
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "run.json").write_text(json.dumps({
        "run_id": run_id, "n_agents": 3, "shm_prefix": f"fc_{run_id}_",
        "root_path": f"{root_path(run_id)}/", "protocol_version": wire.PROTOCOL_VERSION, "observation": "slot_proximity",
        "observation_dim": 16, "critic_window": 64, "startup_timeout_s": 60, "sim_silence_ms": 2000,
        "command_timeout_ms": 200, "v_max": 0.5, "w_max": 1.0, "proximity_range_m": 1.0, "mode": "eval",
        "external": [2], "launcher_pid": 0}))
    common = ["--agents", "3", "--mode", "eval", "--run-id", run_id, "--run-dir", str(run_dir), "--seed", "3",
              "--placement", "off"]
    procs = []
    try:
        observer = Observer(run_dir, connect_timeout=5)
        seen = []
        baseline = Baseline()

        def policy(obs):
            # Read the states as they come: a state not yet received when the sim exits goes
            # with the sim's publisher.
            seen.extend(observer.receive())
            return baseline(obs)

        robot = Robot(run_dir, 2, policy, connect_timeout=5)
        for i in (0, 1):
            procs.append(subprocess.Popen([str(bin_dir() / "formation-agent"), *common, "--agent", str(i),
                                           "--policy", "scripted"], stdout=subprocess.DEVNULL,
                                          stderr=open(tmp_path / f"agent-{i}.log", "wb"), start_new_session=True))
        procs.append(subprocess.Popen([str(bin_dir() / "formation-sim"), *common, "--episodes", "2", "--no-critic",
                                       "--scripted", "0,1"], stdout=subprocess.DEVNULL,
                                      stderr=open(tmp_path / "sim.log", "wb"), start_new_session=True))
        stats = robot.run_forever()
        robot.close()
        seen.extend(observer.receive())
        observer.close()
        statuses = [wait_or_kill(p, 30) for p in procs]
        logs = "\n".join(f.read_text(errors="replace") for f in tmp_path.glob("*.log"))
        assert statuses == [0, 0, 0], logs
        assert stats.episodes == 2 and stats.commands > 0
        world = [state for state in seen if not state.run_end]
        assert len(world) > 50 and {state.episode for state in world} == {0, 1}
        assert all(b.sequence == a.sequence + 1 for a, b in zip(world, world[1:])), "no state lost"
    finally:
        for p in procs:
            if p.poll() is None:
                wait_or_kill(p, 0)
        # iceoryx2 keeps one persistent segment per prefix (the node counter, `*.global_mgmt`)
        # for the launcher's clean-up; everything else goes when the processes end.
        leftovers = [name for name in shm_leftovers(run_id) if not name.endswith(".global_mgmt")]
        remove_leftovers(run_id)
    assert not leftovers, f"shared memory left: {leftovers}"
    assert not shm_leftovers(run_id)
    assert not processes_mentioning(run_id)
    assert not root_path(run_id).exists()
