"""Real multi-process runs with a robot played from Python: scripts/run_swarm.sh starts the
sim, the other robots and the critic; the Python robot is its own process, as a user would run
it. Every process has a watchdog; nothing may be left in /dev/shm."""

import json
import os
import re
import subprocess
import sys
import time


from formation_swarm import Observer, connect
from formation_swarm.run import OBSERVATION_DIMS

from conftest import assert_clean, launch, python_robot, remove_leftovers, wait_or_kill

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
    assert "run ended after" in robot_log
    check_run_json(swarm.run_dir, [2])


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
    state, then the end of the run."""
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
        status = swarm.wait(WATCHDOG_S)
        assert status == 0, swarm.output
        assert wait_or_kill(robot, 30) == 0
    finally:
        if robot is not None and robot.poll() is None:
            wait_or_kill(robot, 0)
        if swarm.proc.poll() is None:
            swarm.wait(0)
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
        "root_path": f"{root_path(run_id)}/", "protocol_version": 2, "observation": "slot_proximity",
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
