"""Test kit for real multi-process runs (the Python twin of the workspace's src/lib.rs):
launches scripts/run_swarm.sh with prebuilt binaries under a watchdog, in a run-unique run
directory, and checks that nothing of the run is left behind."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator, List, Optional

import pytest

REPO = Path(__file__).resolve().parents[2]


def bin_dir() -> Path:
    """FORMATION_BIN_DIR, else target/debug (scripts/test.sh builds it first)."""
    path = Path(os.environ.get("FORMATION_BIN_DIR", REPO / "target" / "debug"))
    missing = [b for b in ("formation-sim", "formation-agent", "formation-critic") if not (path / b).is_file()]
    if missing:
        pytest.fail(f"{missing} missing in {path}: build first (nice -n 10 cargo build --workspace --bins)")
    return path


def kill_group(proc: subprocess.Popen) -> None:
    """SIGKILL to the process group started for ``proc`` (only ours)."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


@dataclasses.dataclass
class Launch:
    """A launcher run in progress or finished."""

    proc: subprocess.Popen
    run_dir: Path
    log: Path
    started: float
    status: Optional[int] = None

    @property
    def output(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    @property
    def run_id(self) -> Optional[str]:
        match = re.search(r"^run (\S+?):", self.output, re.M)
        return match.group(1) if match else None

    def summary(self) -> dict:
        return json.loads((self.run_dir / "summary.json").read_text())

    def wait(self, watchdog: float) -> Optional[int]:
        """Waits for the launcher; past ``watchdog`` seconds from its start kills its whole
        process group, removes the run's shared memory and returns None."""
        try:
            self.status = self.proc.wait(timeout=max(0.0, self.started + watchdog - time.monotonic()))
        except subprocess.TimeoutExpired:
            kill_group(self.proc)
            self.status = None
            remove_leftovers(self.run_id)
        return self.status


def launch(args: List[str], run_dir: Path) -> Launch:
    """Starts scripts/run_swarm.sh ARGS --run-dir RUN_DIR with prebuilt binaries, in its own
    process group, output to RUN_DIR.log."""
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    log = run_dir.with_suffix(".log")
    env = dict(os.environ, FORMATION_BIN_DIR=str(bin_dir()))
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [str(REPO / "scripts" / "run_swarm.sh"), *args, "--run-dir", str(run_dir)],
            stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, env=env,
            start_new_session=True,
        )
    return Launch(proc, run_dir, log, time.monotonic())


def python_robot(run_dir: Path, index: int, log: Path, policy: str = "baseline") -> subprocess.Popen:
    """``python3 -m formation_swarm robot RUN_DIR INDEX`` as a real process (own group)."""
    with open(log, "wb") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "formation_swarm", "robot", str(run_dir), str(index), "--policy", policy],
            stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
        )


def wait_or_kill(proc: subprocess.Popen, timeout: float) -> Optional[int]:
    """The exit status of ``proc``, or None after killing it at ``timeout``."""
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        kill_group(proc)
        return None


def shm_leftovers(run_id: str) -> List[str]:
    return sorted(n for n in os.listdir("/dev/shm") if n.startswith(f"fc_{run_id}_"))


def root_path(run_id: str) -> Path:
    return Path(tempfile.gettempdir()) / "formation-iox2" / run_id


def remove_leftovers(run_id: Optional[str]) -> None:
    """What a killed run leaves: its /dev/shm files and its iceoryx2 root path."""
    if not run_id:
        return
    for name in shm_leftovers(run_id):
        try:
            os.remove(f"/dev/shm/{name}")
        except OSError:
            pass
    subprocess.run(["rm", "-rf", str(root_path(run_id))], check=False)


def processes_mentioning(text: str) -> List[int]:
    """Processes whose command line contains ``text`` (the run id or the run directory)."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        try:
            cmdline = Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if text in cmdline:
            found.append(int(entry))
    return found


def assert_clean(launch: Launch) -> None:
    """No process, no shared memory and no iceoryx2 root path of the run is left."""
    run_id = launch.run_id
    assert run_id, f"the launcher did not announce its run id:\n{launch.output}"
    deadline = time.monotonic() + 5.0
    while processes_mentioning(run_id) or processes_mentioning(str(launch.run_dir)):
        if time.monotonic() > deadline:
            break
        time.sleep(0.1)
    assert not shm_leftovers(run_id), f"shared memory left: {shm_leftovers(run_id)}"
    assert not processes_mentioning(run_id), f"processes left: {processes_mentioning(run_id)}"
    assert not processes_mentioning(str(launch.run_dir)), f"processes left: {processes_mentioning(str(launch.run_dir))}"
    assert not root_path(run_id).exists(), f"iceoryx2 root path left: {root_path(run_id)}"


@dataclasses.dataclass
class LiveRun:
    """A scripted run watched from Python (see :func:`realtime_scripted_run`)."""

    swarm: Launch
    run: Any  # formation_swarm.RunInfo: the connection to the run's sim
    observer: Any  # formation_swarm.Observer, closed once the run is over
    world: list  # every WorldState read so far, oldest first


@contextlib.contextmanager
def realtime_scripted_run(
    tmp_path: Path, n: int, seed: int, config: str, watchdog: float, until_tick: Optional[int] = None
) -> Iterator[LiveRun]:
    """Starts a one-episode scripted eval run of ``n`` robots paced in real time (viewer off,
    ``config`` the TOML text of its --config) in ``tmp_path/run``, connects an Observer to it
    and, given ``until_tick``, reads states until one of that tick, so the block talks to the
    sim while the episode is under way. After the block: reads the states left, closes the
    observer and asserts the launcher exited 0 within ``watchdog`` seconds. On any failure the
    launcher's process group is killed and the run's shared memory removed."""
    from formation_swarm import Observer, connect  # here: the kit's other helpers need no package

    config_path = tmp_path / "run.toml"
    config_path.write_text(config)
    swarm = launch([str(n), "--mode", "eval", "--scripted", "all", "--episodes", "1", "--seed", str(seed),
                    "--realtime", "--viewer", "off", "--config", str(config_path)], tmp_path / "run")
    try:
        run = connect(swarm.run_dir, timeout=60)
        live = LiveRun(swarm, run, Observer(run), [])
        while until_tick is not None and (not live.world or live.world[-1].tick < until_tick):
            got = live.observer.wait(30)
            assert got, f"no state within 30 s:\n{swarm.output}"
            live.world.extend(got)
        yield live
        live.world.extend(live.observer.states(timeout=60))
        live.observer.close()
        status = swarm.wait(watchdog)
    finally:
        if swarm.proc.poll() is None:
            swarm.wait(0)  # kills the launcher's group and removes the run's shared memory
    assert status == 0, swarm.output
