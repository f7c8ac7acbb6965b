"""FormationEnv, the PettingZoo ParallelEnv over a real swarm: every test starts
scripts/run_swarm.sh N --external all (the sim and the critic as processes) with the prebuilt
binaries, plays all robots from this process, and checks that close() leaves no process,
shared memory or iceoryx2 root path of the run. Each test runs under a watchdog."""

import contextlib
import csv
import os
import json
import math
import signal
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pettingzoo")
pytest.importorskip("gymnasium")

from pettingzoo.test import parallel_api_test  # noqa: E402

import formation_swarm as fs  # noqa: E402
from formation_swarm.env import swarm_config  # noqa: E402

from conftest import REPO, bin_dir, processes_mentioning, remove_leftovers, root_path, shm_leftovers  # noqa: E402

WATCHDOG_S = 180


class Watchdog(Exception):
    """A test ran past WATCHDOG_S."""


@pytest.fixture
def watchdog():
    """SIGALRM after WATCHDOG_S raises in the test, whose finally closes the env."""

    def expire(signum, frame):
        raise Watchdog(f"test ran past {WATCHDOG_S} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(WATCHDOG_S)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.fixture
def make_env(tmp_path, watchdog):
    """FormationEnv(...) in a run-unique directory under tmp_path with the tests' binaries;
    closed at teardown (and, should close fail, its launcher's group killed), then checked for
    leftovers of every run it started."""
    envs = []

    def make(**kwargs):
        kwargs.setdefault("run_dir", tmp_path / f"env{len(envs)}")
        kwargs.setdefault("bin_dir", bin_dir())
        env = fs.FormationEnv(**kwargs)
        envs.append(env)
        return env

    yield make
    for env in envs:
        proc = env._proc
        try:
            env.close()
        finally:
            if proc is not None and proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    for env in envs:
        assert not processes_mentioning(str(env.base_dir)), "no launcher or watcher left"
        for run_id in run_ids(env):
            assert_clean(run_id)


def run_ids(env):
    """The run id of every swarm the env launched (from each swarm-<k>/run.json)."""
    ids = []
    for path in sorted(env.base_dir.glob("swarm-*/run.json")):
        ids.append(json.loads(path.read_text())["run_id"])
    return ids


def assert_clean(run_id):
    leftovers = shm_leftovers(run_id)
    remove_leftovers(run_id)
    assert not leftovers, f"shared memory left by run {run_id}: {leftovers}"
    assert not processes_mentioning(run_id), f"processes of run {run_id} left: {processes_mentioning(run_id)}"
    assert not root_path(run_id).exists(), f"iceoryx2 root path of run {run_id} left"


def play_episode(env, choose):
    """One episode from reset; returns (summed team reward, final infos of robot_0, steps)."""
    obs, infos = env.reset()
    assert infos["robot_0"]["tick"] == 0 and infos["robot_0"]["outcome"] == "running"
    total, steps = 0.0, 0
    while env.agents:
        obs, rewards, terminations, truncations, infos = env.step({a: choose(obs[a]) for a in env.agents})
        steps += 1
        assert len(set(rewards.values())) == 1, "one shared team reward"
        total += rewards["robot_0"]
        done = terminations["robot_0"] or truncations["robot_0"]
        assert all((terminations[a] or truncations[a]) == done for a in rewards)
    return total, infos["robot_0"], steps


def test_parallel_api_test_passes(make_env):
    env = make_env(n=3, seed=0)  # parallel_api_test resets with seed 0: no restart
    assert env.possible_agents == ["robot_0", "robot_1", "robot_2"]
    assert env.observation_space("robot_1").shape == (env.run.observation_dim,) == (16,)
    space = env.action_space("robot_2")
    assert space.shape == (2,) and np.all(space.low == -1.0) and np.all(space.high == 1.0)
    parallel_api_test(env, num_cycles=150)
    env.reset()
    state = env.state()
    assert state.shape == env.state_space.shape == (8 * 3 + 2,) and state.dtype == np.float32
    world = env.world()
    assert world.tick == 0 and world.n_agents == 3
    # Positions relative to the centroid sum to zero; headings are unit vectors.
    team = state[:12].reshape(3, 4)
    assert np.allclose(team[:, :2].sum(axis=0), 0.0, atol=1e-5)
    assert np.allclose(np.hypot(team[:, 2], team[:, 3]), 1.0, atol=1e-5)
    assert np.allclose(state[14:20], np.asarray(world.desired).reshape(-1), atol=1e-6)
    run_id = env.run.run_id
    env.close()
    assert_clean(run_id)
    with pytest.raises(fs.FormationError):
        env.reset()


def test_baseline_reaches_success_and_beats_random(make_env):
    env = make_env(n=3, seed=1)
    baseline = fs.Baseline.for_run(env.run)
    base = [play_episode(env, lambda obs: env.action_from_command(*baseline(obs))) for _ in range(8)]
    rng = np.random.default_rng(0)
    rand = [play_episode(env, lambda obs: rng.uniform(-1.0, 1.0, 2)) for _ in range(4)]
    outcomes = [info["outcome"] for _, info, _ in base]
    print("baseline", [(round(r, 2), info["outcome"], steps) for r, info, steps in base])
    print("random", [(round(r, 2), info["outcome"], steps) for r, info, steps in rand])
    assert outcomes.count("success") >= 6, outcomes
    assert all(info["outcome"] in ("success", "collision", "timeout") for _, info, _ in base + rand)
    assert np.mean([r for r, _, _ in rand]) < np.mean([r for r, _, _ in base])
    run_dir = env.run_dir
    env.close()
    # The sim's own record of the same episodes: the env's summed rewards are its returns.
    with open(run_dir / "episodes.csv") as f:
        rows = list(csv.DictReader(f))
    played = base + rand
    assert len(rows) >= len(played)
    for (total, info, steps), row in zip(played, rows):
        assert row["outcome"] == info["outcome"] and int(row["steps"]) == steps
        assert abs(float(row["episode_return"]) - total) < 1e-3 * max(1.0, abs(total)), (row, total)


def test_max_cycles_truncates_and_reset_plays_the_episode_out(make_env):
    env = make_env(n=3, seed=2, max_cycles=5)
    obs, infos = env.reset()
    first = infos["robot_0"]["episode"]
    for step in range(5):
        obs, rewards, terminations, truncations, infos = env.step({a: np.zeros(2) for a in env.agents})
    assert all(truncations.values()) and not any(terminations.values())
    assert infos["robot_1"]["outcome"] == "max_cycles" and infos["robot_1"]["tick"] == 5
    assert env.agents == []
    assert env.step({}) == ({}, {}, {}, {}, {})
    obs, infos = env.reset()
    assert infos["robot_2"]["episode"] == first + 1 and infos["robot_2"]["tick"] == 0
    assert set(obs) == set(env.agents) == set(env.possible_agents)
    # reset() in the middle of an episode plays it out too.
    env.step({a: env.action_space(a).sample() for a in env.agents})
    _, infos = env.reset()
    assert infos["robot_0"]["episode"] == first + 2


def test_reset_with_another_seed_restarts_the_swarm(make_env):
    env = make_env(n=3, seed=3)
    obs, _ = env.reset()
    old = env.run.run_id
    obs_same, infos = env.reset(seed=3)  # the same seed: the run goes on, next episode
    assert env.run.run_id == old and infos["robot_0"]["episode"] == 1
    obs4, infos = env.reset(seed=4)
    assert env.run.run_id != old and env.swarm_seed == 4 and infos["robot_0"]["episode"] == 0
    assert_clean(old)  # the old swarm is gone, with its shared memory
    again, _ = env.reset(seed=4, options={"restart": True})
    for agent in env.possible_agents:
        np.testing.assert_array_equal(obs4[agent], again[agent])  # a seed's episodes repeat
    assert any(not np.array_equal(obs[a], obs4[a]) for a in env.possible_agents)
    assert len(run_ids(env)) == 3


def test_paper_observation_config_and_slow_caller(make_env, tmp_path):
    """A --config run (12-float paper observation): the spaces follow run.json; the env's
    deadline lets a caller pause between steps without the sim holding its commands."""
    config = tmp_path / "paper.toml"
    config.write_text('[env]\nobservation = "paper"\n\n[ticks]\nsim_silence_ms = 3000\n')
    env = make_env(n=4, seed=5, config=config, shape="ring", step_timeout_s=30)
    assert env.run.observation == "paper" and env.observation_space("robot_3").shape == (12,)
    assert env.run.command_timeout_ms == 30_000 and env.run.startup_timeout_s >= 90
    assert env.run.sim_silence_ms == 3000
    obs, _ = env.reset()
    assert obs["robot_0"].shape == (12,) and obs["robot_0"].dtype == np.float32
    baseline = fs.Baseline.for_run(env.run)
    for _ in range(3):
        time.sleep(0.5)  # past the 200 ms default deadline
        obs, _, _, _, infos = env.step({a: env.action_from_command(*baseline(obs[a])) for a in env.agents})
        assert infos["robot_0"]["missed"] == 0 and infos["robot_0"]["skipped_ticks"] == 0


#: ``env.scan_range_m``'s default (the obstacle test's config leaves it): a ray's range over it
#: is what the observation's scan block holds.
SCAN_RANGE_M = 2.0


def distance_to_wall(point, wall):
    """How far ``point`` is from a wall's rectangle (a.x, a.y, b.x, b.y, thickness; flat ends):
    0 on or inside it."""
    ax, ay, bx, by, thickness = wall
    length = math.hypot(bx - ax, by - ay)
    ux, uy = (bx - ax) / length, (by - ay) / length
    px, py = point[0] - ax, point[1] - ay
    along, across = px * ux + py * uy, abs(py * ux - px * uy)
    return math.hypot(max(-along, 0.0, along - length), max(across - thickness / 2, 0.0))


def test_obstacles_reach_the_observations_and_the_scan_sees_the_walls(make_env):
    """obstacles="passage": the robots observe slot_proximity_scan (32 floats), the env reads
    the episode's two walls from formation/obstacles, every ray of the scan block is in
    [0, 1], and rays that read short of the range end on one of those walls at some tick."""
    env = make_env(n=3, seed=2000, obstacles="passage")
    layout = fs.wire.OBSERVATION_MODELS["slot_proximity_scan"]
    assert env.run.observation == layout.name and env.observation_space("robot_1").shape == (32,)
    scan = layout.span("scan")
    rays = scan.stop - scan.start
    baseline = fs.Baseline.for_run(env.run)
    obs, infos = env.reset()
    obstacles = env.obstacles()
    assert obstacles.episode == infos["robot_0"]["episode"] and obstacles.kind == "passage", obstacles
    assert len(obstacles.walls) == 2 and not obstacles.discs and obstacles.time_limit > 0, obstacles
    short, on_wall, ticks = 0, 0, 0
    while True:
        world = env.world()
        for i, agent in enumerate(env.possible_agents):
            assert obs[agent].shape == (32,)
            reading = obs[agent][scan]
            assert np.all((reading >= 0.0) & (reading <= 1.0)), (world.tick, agent, reading)
            x, y, theta = world.poses[i]
            for k in np.flatnonzero(reading < 1.0):
                short += 1
                angle, r = theta + 2 * math.pi * k / rays, float(reading[k]) * SCAN_RANGE_M
                hit = (x + r * math.cos(angle), y + r * math.sin(angle))
                on_wall += min(distance_to_wall(hit, wall) for wall in obstacles.walls) < 1e-3
        ticks += 1
        if not env.agents:
            break
        obs, _, _, _, infos = env.step({a: env.action_from_command(*baseline(obs[a])) for a in env.agents})
    print(f"{ticks} ticks, {infos['robot_0']['outcome']}: {short} short rays, {on_wall} on a wall")
    assert on_wall > 0, (short, ticks, obstacles)


def test_obstacles_must_name_a_kind(tmp_path):
    with pytest.raises(fs.FormationError, match="obstacles must be"):
        fs.FormationEnv(n=3, obstacles="wall", run_dir=tmp_path, bin_dir=bin_dir())


def test_swarm_config_keeps_the_users_settings(tmp_path):
    config = tmp_path / "user.toml"
    config.write_text('# mine\n[env]\nobservation = "slot"\nmax_steps = 80\n\n[learn]\nactor_hidden = [64, 64]\n'
                      '\n[ticks]\nstartup_timeout_s = 2000\n')
    merged = tomllib.loads(swarm_config(config, 12.5))
    assert merged["env"] == {"observation": "slot", "max_steps": 80}
    assert merged["learn"]["actor_hidden"] == [64, 64]
    assert merged["ticks"] == {"startup_timeout_s": 2000, "command_timeout_ms": 12500}
    assert tomllib.loads(swarm_config(None, 600))["ticks"] == {"command_timeout_ms": 600_000, "startup_timeout_s": 660}
    assert swarm_config(config, None) == config.read_text()


def test_swarm_config_takes_reality_from_a_file_or_a_dict_over_the_configs(tmp_path):
    config = tmp_path / "user.toml"
    config.write_text('[env]\nmax_steps = 80\n\n[reality]\ncommand_loss = 0.2\n')
    preset = tmp_path / "preset.toml"
    preset.write_text('# mine\n[reality]\nposition_noise_m = [0.05, 0.1]\ndead_robot = "stop"\n\n[env]\nmax_steps = 5\n')
    from_file = tomllib.loads(swarm_config(config, None, preset))
    assert from_file["reality"] == {"position_noise_m": [0.05, 0.1], "dead_robot": "stop"}, "replaces the config's"
    assert from_file["env"] == {"max_steps": 80}, "only the file's [reality] is read"
    from_dict = tomllib.loads(swarm_config(None, 30, {"actuation_delay_ticks": [2, 2]}))
    assert from_dict["reality"] == {"actuation_delay_ticks": [2, 2]}
    assert from_dict["ticks"]["command_timeout_ms"] == 30_000
    parsed_preset = {"reality": {"observation_loss": 0.05}}
    assert tomllib.loads(swarm_config(None, None, parsed_preset))["reality"] == {"observation_loss": 0.05}
    no_section = tmp_path / "none.toml"
    no_section.write_text("[env]\nmax_steps = 5\n")
    with pytest.raises(fs.FormationError, match="has no \\[reality\\] section"):
        swarm_config(None, None, no_section)
    with pytest.raises(fs.FormationError, match="does not exist"):
        swarm_config(None, None, tmp_path / "missing.toml")


def test_reality_reaches_the_swarms_config_and_bad_values_are_refused_by_name(make_env, tmp_path):
    """reality= (a preset file) is the run's [reality], as the sim and the critic read it
    (config.toml in the run directory); an out-of-range value is refused naming the field."""
    preset = REPO / "configs" / "reality-field.toml"
    config = tmp_path / "user.toml"
    config.write_text("[env]\nmax_steps = 80\n")
    env = make_env(n=3, seed=7, config=config, reality=preset)
    written = tomllib.loads((env.base_dir / "swarm-1" / "config.toml").read_text())
    field = tomllib.loads(preset.read_text())["reality"]
    # The run's config lists every [reality] key: the preset's as it sets them, others defaulted.
    assert {key: written["reality"][key] for key in field} == field
    assert written["reality"]["actuation_delay_ticks"] == [1, 3]
    assert written["env"]["max_steps"] == 80
    env.reset()
    env.step({a: [0.0, 0.0] for a in env.agents})
    with pytest.raises(fs.FormationError, match="reality.command_loss"):
        make_env(n=3, seed=7, reality={"command_loss": 1.5})


def test_lost_observations_are_not_waited_for(make_env):
    """Under observation_loss the env steps on (it waits only for the observations the sim
    sent): a robot whose observation was lost is told so in its infos and keeps its last
    observation, and the sim's summary counts the lost observations."""
    env = make_env(n=3, seed=3, reality={"observation_loss": 0.3})
    obs, infos = env.reset()
    lost, steps = 0, 0
    last = dict(obs)
    while steps < 40:
        if not env.agents:
            obs, infos = env.reset()
            last = dict(obs)
        assert all(isinstance(infos[a]["observation_lost"], bool) for a in env.agents)
        obs, rewards, terminations, truncations, infos = env.step({a: [0.2, 0.1] for a in env.agents})
        steps += 1
        for agent in obs:
            if infos[agent]["observation_lost"]:
                lost += 1
                assert np.array_equal(obs[agent], last[agent]), "a lost observation: the last one again"
        last = dict(obs)
    assert lost > 0, "some observations were lost"
    run_dir = env.run_dir
    env.close()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["lost_observations"] > 0, summary


def test_action_units(make_env):
    env = make_env(n=3, seed=6)
    assert env.command_from_action([-1, 0]) == (0.0, 0.0)
    assert env.command_from_action(np.array([1.0, -1.0], dtype=np.float32)) == (env.run.v_max, -env.run.w_max)
    assert env.command_from_action([5.0, 0.5]) == (env.run.v_max, 0.5 * env.run.w_max)  # clipped
    np.testing.assert_allclose(env.action_from_command(0.25 * env.run.v_max, 0.2), [-0.5, 0.2 / env.run.w_max])
    env.reset()
    _, _, _, _, infos = env.step({a: [1.0, 0.0] for a in env.agents})
    assert np.allclose(env.world().applied, [(env.run.v_max, 0.0)] * 3)
    with pytest.raises(fs.FormationError, match="missing"):
        env.step({"robot_0": [0.0, 0.0]})


def test_render_mode_rerun_records_to_the_run_dir(make_env):
    env = make_env(n=3, seed=7, render_mode="rerun", max_cycles=20)
    assert env.viewer == "save" and env.recording == env.run_dir / "recording.rrd"
    obs, _ = env.reset()
    while env.agents:
        obs, *_ = env.step({a: [0.5, 0.0] for a in env.agents})
    assert env.render() is None
    recording = env.recording
    env.close()
    assert recording.is_file() and recording.stat().st_size > 0


def test_a_killed_process_leaves_nothing(tmp_path, watchdog):
    """SIGKILL to the process that holds the env: its watcher stops the swarm and removes the
    run's shared memory within seconds."""
    import subprocess
    import sys

    script = (
        "import os, signal, sys\n"
        "import formation_swarm as fs\n"
        f"env = fs.FormationEnv(n=3, seed=8, run_dir={str(tmp_path / 'env')!r}, bin_dir={str(bin_dir())!r})\n"
        "env.reset()\n"
        "env.step({a: [0.0, 0.0] for a in env.agents})\n"
        "print(env.run.run_id, flush=True)\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    assert done.returncode == -signal.SIGKILL, done.stderr
    run_id = done.stdout.split()[0]
    base = str(tmp_path / "env")
    deadline = time.monotonic() + 30
    while (shm_leftovers(run_id) or processes_mentioning(run_id) or processes_mentioning(base)) \
            and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not processes_mentioning(base), "the launcher and the watcher have ended"
    assert_clean(run_id)


def test_close_prints_nothing(tmp_path, watchdog):
    """A normal open/step/close leaves the Python process's own stderr empty: the client's ports
    go before the swarm removes its services (iceoryx2 warns of "a corrupted system" once per
    service otherwise). In a process of its own, as a user runs it (pytest's own process does
    not show the race)."""
    import subprocess
    import sys

    script = (
        "import formation_swarm as fs\n"
        f"env = fs.FormationEnv(n=3, seed=9, run_dir={str(tmp_path / 'env')!r}, bin_dir={str(bin_dir())!r})\n"
        "for seed in (9, 20, 21, 22):  # each new seed stops the running swarm and starts another\n"
        "    obs, _ = env.reset(seed=seed)\n"
        "    for _ in range(5):\n"
        "        obs, *_ = env.step({a: [0.5, 0.0] for a in env.agents})\n"
        "env.close()\n"
        "print(' '.join(p.parent.name + '=' + __import__('json').loads(p.read_text())['run_id']\n"
        "               for p in sorted(env.base_dir.glob('swarm-*/run.json'))))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=150,
                          env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    assert done.returncode == 0, done.stderr
    assert done.stderr == "", done.stderr
    ids = [item.split("=")[1] for item in done.stdout.split()]
    assert len(ids) == 4
    for run_id in ids:
        assert_clean(run_id)


FRESH_PROCESSES = 10


@contextlib.contextmanager
def short_temp_dir():
    """A temporary directory of the test's own, with a short path as the system's: a run's
    iceoryx2 root path goes under it, and the sockets there allow 107 bytes of path."""
    import shutil

    temp = Path(tempfile.mkdtemp(prefix="fs-test-"))
    try:
        yield temp
    finally:
        shutil.rmtree(temp, ignore_errors=True)


def test_fresh_processes_print_nothing_and_leave_nothing():
    """The first reset() in a fresh process, then a restart at tick 0 (reset with another seed)
    and a close: in each of FRESH_PROCESSES processes the Python process's stderr stays empty and
    nothing of the env is left in its temporary directory (no formation-env-* directory, no
    iceoryx2 root path) nor in /dev/shm. Stopping a swarm at tick 0 is where a sim ends without
    announcing the run's end (asked to stop before it catches the signal); the env must then
    drop its ports at once, before the launcher removes the run's files (iceoryx2 prints "The
    static storage was already removed" for each otherwise)."""
    with short_temp_dir() as temp:
        fresh_processes_print_nothing_and_leave_nothing(temp)


def fresh_processes_print_nothing_and_leave_nothing(temp):
    import subprocess
    import sys

    script = (
        "import sys\n"
        "import formation_swarm as fs\n"
        f"env = fs.FormationEnv(n=3, seed=int(sys.argv[1]), bin_dir={str(bin_dir())!r})\n"
        "obs, _ = env.reset()\n"
        "first = env.run.run_id\n"
        "obs, _ = env.reset(seed=int(sys.argv[1]) + 1)\n"
        "env.step({a: [0.5, 0.0] for a in env.agents})\n"
        "env.close()\n"
        "print(env.base_dir, first, env.run.run_id)\n"
    )
    environ = dict(os.environ, TMPDIR=str(temp), PYTHONPATH=os.pathsep.join(sys.path))
    for k in range(FRESH_PROCESSES):
        done = subprocess.run([sys.executable, "-c", script, str(40 + 2 * k)], capture_output=True, text=True,
                              timeout=150, env=environ)
        assert done.returncode == 0, done.stderr
        assert done.stderr == "", f"process {k}: {done.stderr}"
        base, *run_ids = done.stdout.split()
        assert Path(base).parent == temp and not Path(base).exists(), f"process {k}: {base} left"
        for run_id in run_ids:
            assert not shm_leftovers(run_id), f"process {k}: shared memory of run {run_id} left"
            assert not processes_mentioning(run_id), f"process {k}: processes of run {run_id} left"
        left = [p.name for p in temp.iterdir() if p.name != "formation-iox2"]
        left += [f"formation-iox2/{p.name}" for p in (temp / "formation-iox2").iterdir()]
        assert not left, f"process {k} left {left} in its temporary directory"


def test_a_closed_env_leaves_its_runs_only_when_asked(monkeypatch, watchdog):
    """Without run_dir a closed env leaves nothing in the temporary directory, and neither does
    a copy (pickle) that was never used, nor one that ran and was closed; render_mode="rerun"
    keeps its directory, with the recording in it."""
    with short_temp_dir() as temp:
        closed_envs_leave_their_runs_only_when_asked(temp, monkeypatch)


def closed_envs_leave_their_runs_only_when_asked(temp, monkeypatch):
    import gc
    import pickle

    monkeypatch.setenv("TMPDIR", str(temp))
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    envs = []
    try:
        env = fs.FormationEnv(n=3, seed=50, bin_dir=bin_dir(), max_cycles=3)
        envs.append(env)
        unused = pickle.loads(pickle.dumps(env))
        used = pickle.loads(pickle.dumps(env))
        envs.append(used)
        recorded = fs.FormationEnv(n=3, seed=51, bin_dir=bin_dir(), render_mode="rerun", max_cycles=3)
        envs.append(recorded)
        for e in (env, used, recorded):
            e.reset()
            while e.agents:
                e.step({a: [0.5, 0.0] for a in e.agents})
        del unused
        gc.collect()
    finally:
        for e in envs:
            e.close()
    ids = [e.run.run_id for e in envs]
    left = sorted(p.name for p in temp.iterdir() if p.name != "formation-iox2")
    assert left == [recorded.base_dir.name], left
    assert recorded.recording.is_file() and recorded.recording.stat().st_size > 0
    assert not list((temp / "formation-iox2").iterdir())
    for run_id in ids:
        assert not shm_leftovers(run_id) and not processes_mentioning(run_id)


def test_close_waits_for_the_swarm_even_when_it_fails(monkeypatch, watchdog):
    """An error while close() plays the run out still releases the ports and waits for the
    launcher before the env's directory is removed: when close() has raised, no process of the
    env is left to write into that directory, and the directory and the run's files are gone."""
    with short_temp_dir() as temp:
        monkeypatch.setenv("TMPDIR", str(temp))
        monkeypatch.setattr(tempfile, "tempdir", str(temp))
        play_out = fs.FormationEnv._play_out

        def play_out_then_fail(self, proc, deadline):
            play_out(self, proc, deadline)
            raise RuntimeError("injected after the play-out")

        monkeypatch.setattr(fs.FormationEnv, "_play_out", play_out_then_fail)
        env = fs.FormationEnv(n=3, seed=52, bin_dir=bin_dir())
        env.reset()
        env.step({a: [0.5, 0.0] for a in env.agents})
        base, run_id = env.base_dir, env.run.run_id
        with pytest.raises(RuntimeError, match="injected"):
            env.close()
        assert not processes_mentioning(str(base)), "the launcher or its watcher outlived close()"
        assert not base.exists()
        assert not shm_leftovers(run_id) and not processes_mentioning(run_id)
        assert not list((temp / "formation-iox2").iterdir())


def test_a_held_launcher_lock_keeps_its_run_from_the_sweep(make_env, tmp_path):
    """A run whose launcher lock is held (here by a process of this test; its run id names a pid
    that does not exist, as a launcher's in another PID namespace would) is not swept by a
    real launcher, and ``launcher_alive`` says it lives; released, the next launcher sweeps it."""
    import subprocess
    import sys

    child = subprocess.Popen(["true"])
    child.wait()
    run_id = f"r000001p{child.pid}x9"
    lock = f"/dev/shm/fc_{run_id}_launcher.lock"
    data = f"/dev/shm/fc_{run_id}_state.data"
    for path in (lock, data):
        open(path, "wb").close()
    holder = subprocess.Popen(
        [sys.executable, "-c", "import fcntl, sys\nf = open(sys.argv[1])\nfcntl.flock(f, fcntl.LOCK_EX)\n"
                               "print('held', flush=True)\nsys.stdin.read()\n", lock],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "held\n"
        info = fs.RunInfo.from_dict(tmp_path, {
            "run_id": run_id, "n_agents": 3, "shm_prefix": f"fc_{run_id}_", "root_path": str(root_path(run_id)),
            "protocol_version": fs.PROTOCOL_VERSION, "observation": "slot_proximity", "observation_dim": 16,
            "critic_window": 64, "startup_timeout_s": 60, "sim_silence_ms": 2000, "command_timeout_ms": 200,
            "v_max": 0.5, "w_max": 1.0, "proximity_range_m": 1.0, "mode": "eval", "launcher_pid": child.pid})
        assert info.launcher_alive()
        env = make_env(n=3, seed=10)  # a real launcher: its sweep leaves the held run alone
        assert os.path.exists(lock) and os.path.exists(data)
        assert env.run.launcher_alive() and "whose launcher is gone" not in env._log_tail(50)
        holder.stdin.close()
        assert holder.wait(timeout=30) == 0
        assert not info.launcher_alive()
        env.reset(seed=11)  # the next launcher (this one, or any on the machine) sweeps it
        assert not os.path.exists(lock) and not os.path.exists(data)
        assert not info.launcher_alive()
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait()
        remove_leftovers(run_id)


def test_supersuit_vector_env_recipe(make_env):
    """PettingZoo's recipe for Stable-Baselines3: SuperSuit's pettingzoo_env_to_vec_env_v1, then
    concat_vec_envs_v1, which copies the env with cloudpickle; each copy starts its own swarm
    on first use, and both copies step."""
    ss = pytest.importorskip("supersuit")
    import pickle

    env = make_env(n=3, seed=12, max_cycles=40)
    copy = pickle.loads(pickle.dumps(env))
    assert copy.run is None and copy.observation_space("robot_0") == env.observation_space("robot_0")
    copy.close()  # never started: nothing to stop
    vec = ss.concat_vec_envs_v1(ss.pettingzoo_env_to_vec_env_v1(env), 2, num_cpus=0, base_class="gymnasium")
    try:
        obs, infos = vec.reset(seed=13)
        assert obs.shape == (2 * 3, env.run.observation_dim)
        copies = [sub.par_env for sub in vec.vec_envs]
        assert all(c is not env and c.run is not None for c in copies)
        assert len({c.run.run_id for c in copies + [env]}) == 3, "every copy runs its own swarm"
        for _ in range(45):  # past max_cycles: the vector env resets the copies itself
            obs, rewards, terminations, truncations, infos = vec.step(
                np.tile(np.array([[0.5, 0.0]], dtype=np.float32), (6, 1)))
            assert obs.shape == (6, env.run.observation_dim) and rewards.shape == (6,)
            assert np.all(np.isfinite(obs)) and np.all(np.isfinite(rewards))
        assert all(c.run.launcher_alive() for c in copies)
        copy_ids = [c.run.run_id for c in copies]
        ticks = [c.world().tick for c in copies]
        assert all(t > 0 for t in ticks), ticks
    finally:
        vec.close()
    for run_id in copy_ids:
        assert_clean(run_id)
