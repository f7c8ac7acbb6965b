"""A PettingZoo ``ParallelEnv`` over a real multi-process swarm.

``FormationEnv`` starts the launcher, ``formation N --external all --mode eval`` (the sim and
the critic as their own processes, no robot process) and plays all N robot slots from this Python
process over iceoryx2 shared memory, one ``Robot`` per slot, exactly as ``formation-agent``
would: every ``step`` answers the sim's current tick for every robot and waits for the next.

    import formation_swarm as fs
    env = fs.FormationEnv(n=3, seed=1)
    obs, infos = env.reset()
    while env.agents:
        obs, rewards, terminations, truncations, infos = env.step(
            {agent: env.action_space(agent).sample() for agent in env.agents})
    env.close()

Needs the ``pettingzoo`` extra (``pip install './python[pettingzoo]'``) and the binaries:
``cargo install``-ed on PATH, in ``FORMATION_BIN_DIR``, or a checkout's ``scripts/run_swarm.sh``
(:func:`find_launcher` gives the order).
"""

from __future__ import annotations

import atexit
import collections
import dataclasses
import gc
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import tomllib
import weakref
from pathlib import Path
from typing import Any, Deque, Dict, List, Optional, Tuple, Union

import gymnasium
import iceoryx2 as iox2
import numpy as np
from pettingzoo import ParallelEnv

from . import wire
from .observer import EpisodeObstacles, Observer, WorldState
from .robot import Robot, Tick
from .run import FormationError, RunInfo, SimGone, connect

#: Agent names: ``robot_0`` .. ``robot_{N-1}`` (robot i of the swarm).
AGENT_PREFIX = "robot_"
#: The episode budget the env gives the sim: it never ends a run by itself.
RUN_EPISODES = 1_000_000_000
#: One wait for the sim, between two looks at its health.
WAIT_SLICE_S = 0.1
#: Outcome name in ``infos`` when the env's ``max_cycles`` cut the episode (not a sim outcome).
OUTCOME_MAX_CYCLES = "max_cycles"
#: Outcome name in ``infos`` when the end of the episode went unseen (stream overflow).
OUTCOME_LOST = "lost"
#: What ``FormationEnv(obstacles=...)`` takes (run_swarm.sh ``--obstacles``): ``mixed`` draws one
#: of the other three kinds per episode.
OBSTACLE_KINDS = ("none", "forest", "passage", "trap", "mixed")
#: How long the watcher gives an orphaned launcher to end the run before killing its group
#: (the sim cannot finish an episode whose robots are gone: it waits for their commands).
ORPHAN_GRACE_S = 5.0

_TERMINAL = (wire.OUTCOME_SUCCESS, wire.OUTCOME_COLLISION)

# Watches the env's process from outside: started with a pipe on its stdin, it reads until EOF.
# "done" first: close() finished the run itself. Anything else (the env's process was killed,
# or exited without close() and its atexit hook did not run): SIGTERM to the launcher (it asks
# the sim to end the run), a grace period, then SIGKILL to the launcher's process group and the
# run's shared memory and root path removed.
_REAPER = r"""
import os, json, shutil, signal, sys, time
pid, run_dir, grace = int(sys.argv[1]), sys.argv[2], float(sys.argv[3])
signal.signal(signal.SIGINT, signal.SIG_IGN)
if sys.stdin.read().startswith("done"):
    sys.exit(0)
def alive():
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
try:
    os.kill(pid, signal.SIGTERM)
except ProcessLookupError:
    pass
deadline = time.monotonic() + grace
while alive() and time.monotonic() < deadline:
    time.sleep(0.2)
if alive():
    try:
        os.killpg(pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
try:
    info = json.load(open(os.path.join(run_dir, "run.json")))
except (OSError, ValueError):
    sys.exit(0)
prefix = "fc_%s_" % info["run_id"]
for name in os.listdir("/dev/shm"):
    if name.startswith(prefix):
        try:
            os.remove(os.path.join("/dev/shm", name))
        except OSError:
            pass
shutil.rmtree(info["root_path"], ignore_errors=True)
"""


#: The binaries a run needs: the launcher and the members it starts (``cargo install`` puts
#: them side by side).
BINARIES = ("formation", "formation-sim", "formation-agent", "formation-critic")


@dataclasses.dataclass(frozen=True)
class Launcher:
    """How the env starts a swarm: ``command`` (``run_swarm.sh`` of a checkout, or the
    ``formation`` binary) and the prebuilt binaries it uses (``FORMATION_BIN_DIR``; None: the
    checkout's script builds a release first), found as :func:`find_launcher` says."""

    command: Path
    bin_dir: Optional[Path]
    found: str


def _script(checkout: Path) -> Path:
    return checkout / "scripts" / "run_swarm.sh"


def _is_checkout(directory: Path) -> bool:
    """A formation-swarm checkout: its ``scripts/run_swarm.sh`` beside the ``python/`` package."""
    return _script(directory).is_file() and (directory / "python" / "formation_swarm").is_dir()


def checkout_around(start: Union[str, Path]) -> Optional[Path]:
    """The formation-swarm checkout holding ``start`` (it, or the nearest directory above it
    that is one), else None."""
    start = Path(start).resolve()
    for directory in (start, *start.parents):
        if _is_checkout(directory):
            return directory
    return None


def _missing(directory: Path) -> List[str]:
    return [b for b in BINARIES if not os.access(directory / b, os.X_OK) or not (directory / b).is_file()]


def find_launcher(repo: Union[str, Path, None] = None, bin_dir: Union[str, Path, None] = None) -> Launcher:
    """Where the env's swarms come from, in this order (the first that applies wins):

    1. ``repo`` (``FormationEnv(repo=...)``): that checkout's ``scripts/run_swarm.sh``;
    2. ``$FORMATION_REPO``: the same;
    3. ``bin_dir`` (``FormationEnv(bin_dir=...)``), else ``$FORMATION_BIN_DIR``: the
       ``formation`` launcher in that directory, with its member binaries beside it;
    4. the checkout this package sits in (``pip install -e ./python``, or ``PYTHONPATH``): its
       ``scripts/run_swarm.sh``;
    5. ``formation`` on ``PATH`` with ``formation-sim``, ``formation-agent`` and
       ``formation-critic`` beside it (as ``cargo install`` puts them, python/README.md);
    6. the checkout holding the current directory (it or the nearest directory above it with
       ``scripts/run_swarm.sh`` and ``python/formation_swarm``): its ``scripts/run_swarm.sh``
       (a package installed with ``pip install ./python``, used from inside the checkout).

    A checkout's script uses the binaries of 3 when given, else builds a release first. Raises
    ``FormationError`` naming each place tried."""
    env_bin = os.environ.get("FORMATION_BIN_DIR") or None
    chosen_bin = bin_dir if bin_dir is not None else env_bin
    bins = None if chosen_bin is None else Path(chosen_bin).expanduser().resolve()
    for given, how in ((repo, "repo="), (os.environ.get("FORMATION_REPO") or None, "FORMATION_REPO")):
        if given is not None:
            checkout = Path(given).expanduser().resolve()
            if not _script(checkout).is_file():
                raise FormationError(f"{how} {checkout} has no scripts/run_swarm.sh")
            return Launcher(_script(checkout), bins, f"{how} {checkout}")
    tried = ["repo= (not given)", "FORMATION_REPO (not set)"]
    if bins is not None:
        how = "bin_dir=" if bin_dir is not None else "FORMATION_BIN_DIR"
        missing = _missing(bins)
        if missing:
            raise FormationError(f"{how} {bins} lacks {', '.join(missing)}")
        return Launcher(bins / "formation", bins, f"{how} {bins}")
    tried.append("bin_dir= / FORMATION_BIN_DIR (not set)")
    package_checkout = Path(__file__).resolve().parents[2]
    if _script(package_checkout).is_file():
        return Launcher(_script(package_checkout), None, f"the checkout of the package, {package_checkout}")
    tried.append(f"the checkout the package sits in ({package_checkout} has no scripts/run_swarm.sh)")
    on_path = shutil.which("formation")
    if on_path is not None:
        directory = Path(on_path).parent
        missing = _missing(directory)
        if not missing:
            return Launcher(directory / "formation", directory, f"PATH, {directory}")
        tried.append(f"PATH (formation in {directory}, but not {', '.join(missing)} beside it)")
    else:
        tried.append("PATH (no formation)")
    here = Path.cwd()
    around = checkout_around(here)
    if around is not None:
        return Launcher(_script(around), None, f"the checkout holding the current directory, {around}")
    tried.append(f"the checkout holding the current directory (neither {here} nor a directory above it "
                 "has scripts/run_swarm.sh and python/formation_swarm)")
    raise FormationError(
        "cannot find the formation-swarm binaries; tried, in order: " + "; ".join(tried) + ". Install them "
        "(python/README.md: cargo install ...), or pass FormationEnv(repo=...) / set FORMATION_REPO to a "
        "checkout, or set FORMATION_BIN_DIR to a directory of built binaries, or run from inside a checkout"
    )


# --- the run's configuration: the user's --config plus the env's tick deadline --------------


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise FormationError(f"cannot write {value!r} into a TOML configuration")


def _toml_dumps(data: Dict[str, Any], prefix: str = "") -> str:
    """Tables of plain values, as config.toml has them (the launcher's run.json reader reads
    ``key = value`` lines under ``[section]`` headers)."""
    lines = [f"{key} = {_toml_value(value)}" for key, value in data.items() if not isinstance(value, dict)]
    out = "".join(line + "\n" for line in lines)
    for key, value in data.items():
        if isinstance(value, dict):
            out += f"\n[{prefix}{key}]\n" + _toml_dumps(value, f"{prefix}{key}.")
    return out


Reality = Union[str, Path, Dict[str, Any], None]


def reality_section(reality: Union[str, Path, Dict[str, Any]]) -> Dict[str, Any]:
    """The ``[reality]`` keys ``reality`` stands for: a TOML file's ``[reality]`` table (its
    other tables are not read, as run_swarm.sh ``--reality``), or a dict of the keys themselves
    (``{"actuation_delay_ticks": [1, 3], ...}``; a dict holding a ``"reality"`` table, a parsed
    preset, gives that table). The values are checked by the launcher, which names the field."""
    if isinstance(reality, dict):
        section = reality.get("reality", reality) if isinstance(reality.get("reality"), dict) else reality
        return dict(section)
    path = Path(reality)
    if not path.is_file():
        raise FormationError(f"reality file {path} does not exist")
    try:
        section = tomllib.loads(path.read_text()).get("reality")
    except tomllib.TOMLDecodeError as err:
        raise FormationError(f"reality file {path} is not valid TOML: {err}") from err
    if not isinstance(section, dict):
        raise FormationError(f"reality file {path} has no [reality] section")
    return section


def swarm_config(config: Union[str, Path, None], step_timeout_s: Optional[float], reality: Reality = None) -> str:
    """The TOML the env runs the swarm with: ``config`` (a file, or None for the defaults) with
    ``ticks.command_timeout_ms`` set to ``step_timeout_s`` and ``ticks.startup_timeout_s``
    raised past it (the critic waits that long for a sim that waits for the env), and with
    ``reality`` (see :func:`reality_section`) as its ``[reality]`` section, replacing any of
    ``config``'s."""
    text = Path(config).read_text() if config is not None else ""
    if step_timeout_s is None and reality is None:
        return text
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise FormationError(f"{config} is not valid TOML: {err}") from err
    if step_timeout_s is not None:
        command_timeout_ms = max(1, int(round(step_timeout_s * 1000)))
        startup_floor = int(math.ceil(step_timeout_s)) + 60
        ticks = data.setdefault("ticks", {})
        ticks["command_timeout_ms"] = command_timeout_ms
        ticks["startup_timeout_s"] = max(int(ticks.get("startup_timeout_s", 60)), startup_floor)
    if reality is not None:
        data["reality"] = reality_section(reality)
    return _toml_dumps(data)


def _closer(ref: "weakref.ref[FormationEnv]") -> Any:
    def close_at_exit() -> None:
        env = ref()
        if env is not None:
            env.close()

    return close_at_exit


class FormationEnv(ParallelEnv):
    """N robots of a real formation-swarm run as a PettingZoo ``ParallelEnv``.

    Agents are ``robot_0`` .. ``robot_{N-1}``. Spaces (gymnasium ``Box``, float32):

    * observation: ``(observation_dim,)`` from run.json (16 for the default ``slot_proximity``
      model, 12 ``paper``, 14 ``slot``, 32 ``slot_proximity_scan``: the default among
      obstacles), the robot's own observation, unbounded; laid out as docs/PROTOCOL.md says
      (``wire.OBSERVATION_MODELS[env.run.observation]`` names each block's floats);
    * action: ``[-1, 1]^2``, **normalised** as the learned actor's tanh output:
      ``v = (a0 + 1) / 2 * v_max`` (0 .. v_max, forward only), ``w = a1 * w_max``; values
      outside are clipped. :meth:`action_from_command` maps a physical (v, w) back;
    * state (:meth:`state`, :attr:`state_space`): ``8 N + 2`` floats of the true world, see
      :meth:`state`.

    ``reset()`` returns the observations at tick 0 of the next episode the sim starts (an
    unfinished episode is played out first with every robot holding still). ``reset(seed=S)``
    with S other than the running swarm's seed (or ``options={"restart": True}``) restarts the
    whole swarm with seed S: a new launcher, sim and critic, about 1-3 s on a loaded 2-CPU
    machine with prebuilt binaries; the same seed continues the run's sequence of episodes.

    ``step(actions)`` answers the current tick for every robot and returns the next tick:
    ``rewards`` the team's shared reward of that transition (the sim's ``State.reward``, the
    same for every robot), ``terminations`` True on a ``success`` or ``collision`` outcome,
    ``truncations`` True on the sim's time limit (``timeout``, ``env.max_steps`` ticks; among
    obstacles the episode's own, :meth:`obstacles` ``.time_limit``),
    ``aborted`` or after ``max_cycles`` steps; ``infos[agent]["outcome"]`` names it
    (``running`` while it goes on, ``max_cycles`` for the env's own cut). An episode that ends
    empties :attr:`agents`.

    Lost observations (``[reality]``'s ``observation_loss``): the sim does not publish a lost
    observation and does not wait for that robot's command at that tick (the robot keeps the
    command it had). The env follows the sim's state of the tick (``State.observation_lost``):
    it waits only for the observations that were sent, and for a robot whose observation was
    lost it returns, with ``infos[agent]["observation_lost"] = True`` (False otherwise, also in
    ``reset``), the last observation that robot received in this episode (zeros when tick 0's
    was lost) and sends nothing of its action for that tick (the sim does not ask for it).
    Rewards, terminations and truncations stay the team's. An episode's last tick is never
    lost. A tick at which every observation was lost may be passed over (``skipped_ticks``).

    Lockstep: the sim waits for every robot's command, so by default the env sets the run's
    ``ticks.command_timeout_ms`` to ``step_timeout_s`` (600 s): the swarm pauses while the caller
    thinks between steps. ``step_timeout_s=None`` keeps the configuration's deadline (200 ms by
    default); a caller slower than that then has its robots' last commands held, and after 3
    missed ticks in a row the sim stops waiting for them.

    Keyword arguments: ``n`` robots (3 to 64); ``seed``; ``shape`` (``random``, ``ring``,
    ``line``, ``wedge``, ``grid``, ``mixed``: run_swarm.sh ``--shape``); ``obstacles`` (between
    the start and the goal of every episode: ``forest``, ``passage``, ``trap``, ``mixed`` or
    ``none``, run_swarm.sh ``--obstacles``, over the config's ``[obstacles] kind``; None keeps
    the config's, none by default; among obstacles the robots observe ``slot_proximity_scan``,
    32 floats with the range sensor's 16 rays in its ``scan`` block, each range over
    ``env.scan_range_m``, unless ``config`` names another model; :meth:`obstacles` gives each
    episode's); ``config`` (a TOML file of
    overrides, run_swarm.sh ``--config``); ``reality`` (the robots' real world: sensor noise,
    actuation delay, motor lag, lost messages, as run_swarm.sh ``--reality``: a TOML file whose
    ``[reality]`` table is read, e.g. ``configs/reality-field.toml``, or a dict of its keys;
    written into the swarm's config over any ``[reality]`` of ``config``);
    ``max_cycles`` (steps per episode, None: the sim's
    ``env.max_steps``); ``render_mode`` None or ``"rerun"`` (the sim records every tick to
    ``<run_dir>/recording.rrd``, ``--viewer save``); ``viewer`` (``spawn``, ``save``,
    ``connect=URL`` or ``off``: run_swarm.sh ``--viewer``, overrides the one render_mode picks);
    ``run_dir`` (where the runs go: ``swarm-<k>`` per launch; default a temporary directory,
    removed by :meth:`close` unless render_mode is ``"rerun"``); ``repo`` (a checkout whose
    ``scripts/run_swarm.sh`` to run) and ``bin_dir`` (prebuilt binaries, ``FORMATION_BIN_DIR``):
    where the launcher and its binaries come from, see :func:`find_launcher`; ``placement`` (run_swarm.sh ``--placement``); ``step_timeout_s``;
    ``launch_timeout_s`` (how long to wait for run.json); ``close_timeout_s``.

    Use :meth:`close` (or ``with FormationEnv(...) as env``): it stops the swarm and leaves
    nothing in /dev/shm. An env still open at interpreter exit is closed by an ``atexit`` hook;
    for a process that is killed, a small watcher process (started with the swarm) stops the
    swarm within seconds and removes its shared memory.

    The env pickles as its constructor's arguments (SuperSuit's ``concat_vec_envs_v1`` copies
    it so): a copy starts its own swarm when first used, in its own directory.
    """

    metadata = {"name": "formation_swarm_v0", "render_modes": ["rerun"], "is_parallelizable": True}

    def __init__(
        self,
        n: int = 3,
        seed: int = 1,
        shape: Optional[str] = None,
        config: Union[str, Path, None] = None,
        max_cycles: Optional[int] = None,
        render_mode: Optional[str] = None,
        *,
        reality: Reality = None,
        obstacles: Optional[str] = None,
        viewer: Optional[str] = None,
        run_dir: Union[str, Path, None] = None,
        repo: Union[str, Path, None] = None,
        bin_dir: Union[str, Path, None] = None,
        placement: str = "auto",
        step_timeout_s: Optional[float] = 600.0,
        launch_timeout_s: float = 900.0,
        close_timeout_s: float = 60.0,
    ) -> None:
        def resolved(path: Union[str, Path, None]) -> Optional[str]:
            return None if path is None else str(Path(path).expanduser().resolve())

        self._configure(
            dict(
                n=n, seed=seed, shape=shape, obstacles=obstacles, config=resolved(config), max_cycles=max_cycles,
                reality=dict(reality) if isinstance(reality, dict) else resolved(reality),
                render_mode=render_mode, viewer=viewer, run_dir=resolved(run_dir), repo=resolved(repo),
                bin_dir=resolved(bin_dir), placement=placement, step_timeout_s=step_timeout_s,
                launch_timeout_s=launch_timeout_s, close_timeout_s=close_timeout_s,
            ),
            copy=False,
        )
        try:
            self._launch(self._seed)
        except BaseException:
            self.close()
            raise
        self._make_spaces(self.run.observation_dim)

    def _configure(self, args: Dict[str, Any], copy: bool) -> None:
        """Checks the constructor's arguments (``args``, paths resolved) and sets the env up
        without starting a swarm; a ``copy`` (unpickled) puts its runs in a directory of its
        own under a given ``run_dir``."""
        render_mode, n, seed, config = args["render_mode"], args["n"], args["seed"], args["config"]
        if render_mode not in (None, "rerun"):
            raise FormationError(f"render_mode must be None or 'rerun', got {render_mode!r}")
        if not (wire.MIN_AGENTS <= int(n) <= wire.MAX_AGENTS):
            raise FormationError(f"n must be {wire.MIN_AGENTS} to {wire.MAX_AGENTS}, got {n}")
        if int(seed) < 0:
            raise FormationError(f"seed must be a whole number >= 0, got {seed}")
        self._args = args
        self.n = int(n)
        self._seed = int(seed)
        self.render_mode = render_mode
        self.max_cycles = args["max_cycles"]
        self.shape = args["shape"]
        if args["obstacles"] is not None and args["obstacles"] not in OBSTACLE_KINDS:
            raise FormationError(f"obstacles must be None or one of {', '.join(OBSTACLE_KINDS)}, got {args['obstacles']!r}")
        #: The obstacles kind given to every swarm (None: the config's ``[obstacles] kind``).
        self.obstacle_kind: Optional[str] = args["obstacles"]
        self.config = None if config is None else Path(config)
        if self.config is not None and not self.config.is_file():
            raise FormationError(f"config file {self.config} does not exist")
        reality = args.get("reality")
        #: The ``[reality]`` section written into every swarm's config (None: the config's own).
        self.reality: Optional[Dict[str, Any]] = None if reality is None else reality_section(reality)
        self.viewer = args["viewer"] or ("save" if render_mode == "rerun" else "off")
        self.placement = args["placement"]
        self.step_timeout_s = args["step_timeout_s"]
        self.launch_timeout_s = args["launch_timeout_s"]
        self.close_timeout_s = args["close_timeout_s"]
        #: How this env starts its swarms (:func:`find_launcher`).
        self.launcher = find_launcher(args["repo"], args["bin_dir"])
        self._own_base = args["run_dir"] is None
        self._copy = copy
        #: Where this env's runs go: ``run_dir``, else a temporary directory (a copy's: one of
        #: its own, under ``run_dir`` when given). Made when the first swarm starts (None until
        #: then), so a copy never used leaves nothing behind.
        self.base_dir: Optional[Path] = None
        self.keep_runs = not self._own_base or render_mode == "rerun"

        self.possible_agents: List[str] = [f"{AGENT_PREFIX}{i}" for i in range(self.n)]
        self.agents: List[str] = []
        self._index = {agent: i for i, agent in enumerate(self.possible_agents)}
        self._launches = 0
        self._proc: Optional[subprocess.Popen] = None
        self._reaper: Optional[subprocess.Popen] = None
        self._robots: List[Robot] = []
        self._observer: Optional[Observer] = None
        self._waitset = None
        self._guards: List[Any] = []
        self._clients_lock: Optional[int] = None
        self._last_state: Optional[wire.State] = None
        self._episode_obstacles: Optional[EpisodeObstacles] = None
        self._owed = False
        self._closed = False
        # An env left open at interpreter exit is closed then (a weak reference: the hook does
        # not keep the env alive).
        self._atexit = _closer(weakref.ref(self))
        atexit.register(self._atexit)
        #: The RunInfo (run.json) of the running swarm (None until a copy first starts one).
        self.run: Optional[RunInfo] = None
        #: The run directory of the running swarm (``<base>/swarm-<k>``).
        self.run_dir: Optional[Path] = None

    def _make_spaces(self, observation_dim: int) -> None:
        obs_space = gymnasium.spaces.Box(-np.inf, np.inf, shape=(observation_dim,), dtype=np.float32)
        self.observation_spaces = {agent: obs_space for agent in self.possible_agents}
        act_space = gymnasium.spaces.Box(-1.0, 1.0, shape=(wire.ACTION_DIM,), dtype=np.float32)
        self.action_spaces = {agent: act_space for agent in self.possible_agents}
        #: ``Box`` of :meth:`state`.
        self.state_space = gymnasium.spaces.Box(-np.inf, np.inf, shape=(8 * self.n + 2,), dtype=np.float32)

    # --- pickling: a copy is its constructor's arguments and starts its own swarm ------------

    def __getstate__(self) -> Dict[str, Any]:
        """What a copy (pickle, cloudpickle, ``copy.deepcopy``) keeps: the constructor's
        arguments and the observation size; no process, port or lock of this env."""
        return {"args": dict(self._args), "observation_dim": int(self.observation_spaces[self.possible_agents[0]].shape[0])}

    def __setstate__(self, state: Dict[str, Any]) -> None:
        """An unpickled copy: the same arguments and spaces, its own swarm started when first
        used (:meth:`reset`), its runs in its own directory."""
        self._configure(dict(state["args"]), copy=True)
        self._make_spaces(int(state["observation_dim"]))

    def _ensure_swarm(self, seed: Optional[int] = None) -> None:
        """Starts the swarm of an unpickled copy on its first use (``seed``, else the env's)."""
        self._check_open()
        if self.run is None:
            self._launch(self._seed if seed is None else int(seed))

    # --- PettingZoo --------------------------------------------------------------------------

    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.action_spaces[agent]

    @property
    def swarm_seed(self) -> int:
        """The running swarm's seed (``reset(seed=...)`` with another one restarts the swarm)."""
        return self._seed

    @property
    def recording(self) -> Optional[Path]:
        """``<run_dir>/recording.rrd`` when the sim records (``--viewer save``), else None."""
        return self.run_dir / "recording.rrd" if self.viewer == "save" and self.run_dir else None

    def reset(
        self, seed: Optional[int] = None, options: Optional[Dict[str, Any]] = None
    ) -> Tuple[Dict[str, np.ndarray], Dict[str, Dict[str, Any]]]:
        """Observations and infos at tick 0 of the next episode the sim starts.

        ``seed`` other than the running swarm's, or ``options={"restart": True}``: the swarm is
        restarted with that seed first (a new run: about 1-3 s)."""
        self._check_open()
        options = options or {}
        if seed is not None and int(seed) < 0:
            raise FormationError(f"seed must be a whole number >= 0, got {seed}")
        self._ensure_swarm(seed)
        if (seed is not None and int(seed) != self._seed) or options.get("restart"):
            self._shutdown()
            self._launch(self._seed if seed is None else int(seed))
        if self._owed:
            # The episode is still running (max_cycles, or reset before its end): play it out
            # with every robot holding still; the sim ends it (at the latest on its time limit).
            for robot, tick in zip(self._robots, self._current):
                if tick is not None:
                    robot.answer(tick, 0.0, 0.0)
            self._owed = False
        self.agents = []
        heads = self._next_episode()
        episode = self._last_state.header.episode
        self._episode_obstacles = self._obstacles_of(episode)
        self._current = heads
        self._owed = True
        self._key = (episode, 0)
        self._observations = [np.zeros(self.run.observation_dim, dtype=np.float32) for _ in range(self.n)]
        lost = self._observe(heads)
        self._last_episode = episode
        self._cycles = 0
        self._return = 0.0
        self.agents = list(self.possible_agents)
        info = {"episode": episode, "tick": 0, "outcome": "running", "seed": self._seed, "run_id": self.run.run_id}
        observations = {agent: self._observations[i].copy() for i, agent in enumerate(self.possible_agents)}
        infos = {agent: dict(info, observation_lost=lost[i]) for i, agent in enumerate(self.possible_agents)}
        return observations, infos

    def _observe(self, heads: List[Optional[Tick]]) -> List[bool]:
        """Keeps each robot's observation of ``heads``; whose was lost (None: kept as it was)."""
        for i, head in enumerate(heads):
            if head is not None:
                self._observations[i] = np.array(head.obs, dtype=np.float32)
        return [head is None for head in heads]

    def step(self, actions: Dict[str, Any]):
        """Answers the current tick with ``actions`` (normalised, see the class) for every
        robot, waits for the sim's next tick and returns (observations, rewards, terminations,
        truncations, infos). After the episode's end (``agents`` empty): empty dicts."""
        self._check_open()
        if not self.agents:
            return {}, {}, {}, {}, {}
        missing = [agent for agent in self.agents if agent not in actions]
        if missing:
            raise FormationError(f"step() needs an action for every live agent; missing {missing}")
        for i, agent in enumerate(self.possible_agents):
            v, w = self.command_from_action(actions[agent])
            if self._current[i] is not None:  # else its observation was lost: the sim asks nothing
                self._robots[i].answer(self._current[i], v, w)
        self._owed = False
        self._cycles += 1
        heads, reward, state, skipped = self._next_tick(self._key)
        if heads is None:  # the episode's end went unseen (a stream overflowed): cut it here
            outcome, terminated, truncated = OUTCOME_LOST, False, True
            lost = [False] * self.n
        else:
            self._last_state = state
            self._key = (state.header.episode, state.header.tick)
            self._current = heads
            lost = self._observe(heads)
            outcome_code = int(state.outcome)
            outcome = wire.OUTCOME_NAMES.get(outcome_code, str(outcome_code))
            terminated = outcome_code in _TERMINAL
            ends = state.header.has(wire.FLAG_EPISODE_END)
            truncated = ends and not terminated
            if not ends:
                self._owed = True
                if self.max_cycles is not None and self._cycles >= self.max_cycles:
                    outcome, truncated = OUTCOME_MAX_CYCLES, True
        self._return += reward
        info = {
            "episode": self._key[0],
            "tick": self._key[1],
            "outcome": outcome,
            "skipped_ticks": skipped,
            "missed": 0 if state is None else int(state.missed),
        }
        if terminated or truncated:
            info["episode_return"] = self._return
        agents = self.agents
        observations = {a: self._observations[self._index[a]].copy() for a in agents}
        rewards = {a: reward for a in agents}
        terminations = {a: terminated for a in agents}
        truncations = {a: truncated for a in agents}
        infos = {a: dict(info, observation_lost=lost[self._index[a]]) for a in agents}
        if terminated or truncated:
            self.agents = []
        return observations, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        """The true state at the current tick (float32, ``8 N + 2``), team-major in the world's
        axes, relative to the robots' centroid (c): for every robot ``x - cx, y - cy, cos
        theta, sin theta`` (4 N), then ``goal - c`` (2), every robot's two desired edge lengths
        (2 N) and every robot's slot offset from the goal in the goal formation (2 N). The
        ``mlp`` critic's tick features without its rotation (core/src/features.rs)."""
        self._check_open()
        if self._last_state is None:
            raise FormationError("state() before reset()")
        raw, n = self._last_state, self.n
        poses = np.ctypeslib.as_array(raw.poses)[:n].astype(np.float64)
        centroid = poses[:, :2].mean(axis=0)
        out = np.empty(8 * n + 2, dtype=np.float32)
        team = np.empty((n, 4))
        team[:, :2] = poses[:, :2] - centroid
        team[:, 2] = np.cos(poses[:, 2])
        team[:, 3] = np.sin(poses[:, 2])
        out[: 4 * n] = team.reshape(-1)
        out[4 * n: 4 * n + 2] = np.asarray(raw.goal, dtype=np.float64) - centroid
        out[4 * n + 2: 6 * n + 2] = np.ctypeslib.as_array(raw.desired)[:n].reshape(-1)
        out[6 * n + 2:] = np.ctypeslib.as_array(raw.slots)[:n].reshape(-1)
        return out

    def obstacles(self) -> Optional[EpisodeObstacles]:
        """The current episode's obstacles as the sim published them (``formation/obstacles``):
        ``kind``, ``time_limit``, ``discs`` (centre x, y, radius) and ``walls`` (a.x, a.y, b.x,
        b.y, thickness), world frame, metres; empty lists in an open episode. None when they
        went unseen."""
        self._check_open()
        if self._last_state is None:
            raise FormationError("obstacles() before reset()")
        return self._episode_obstacles

    def _obstacles_of(self, episode: int) -> Optional[EpisodeObstacles]:
        """Episode ``episode``'s obstacles among those that arrived (published before its first
        tick: here once that tick's state is)."""
        found = None
        for published in self._observer.receive_obstacles():
            if published.episode == episode:
                found = published
        return found

    def world(self) -> WorldState:
        """The true state at the current tick as a ``WorldState`` (poses, goal, slots, ...)."""
        self._check_open()
        if self._last_state is None:
            raise FormationError("world() before reset()")
        return WorldState.from_payload(self._last_state)

    def render(self) -> None:
        """The sim renders through Rerun by itself: with ``render_mode="rerun"`` every tick is
        recorded to :attr:`recording` (``<run_dir>/recording.rrd``; open it with ``rerun``),
        or shown live with ``viewer="spawn"`` / ``"connect=URL"``. Nothing to do here."""
        if self.render_mode is None:
            gymnasium.logger.warn(
                "render() without a render_mode: FormationEnv(render_mode='rerun') records the run to "
                "<run_dir>/recording.rrd"
            )
        return None

    def close(self) -> None:
        """Stops the swarm (the sim ends the run cleanly; the robots hold still meanwhile),
        waits for its processes and checks that nothing of the run is left in /dev/shm (removes
        what a killed run left). Idempotent."""
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self._atexit)
        try:
            self._shutdown()
        finally:
            if self._own_base and not self.keep_runs and self.base_dir is not None:
                shutil.rmtree(self.base_dir, ignore_errors=True)

    def __enter__(self) -> "FormationEnv":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # --- units -------------------------------------------------------------------------------

    def command_from_action(self, action: Any) -> Tuple[float, float]:
        """(v, w) in m/s and rad/s for a normalised action (clipped to [-1, 1]^2)."""
        self._ensure_swarm()
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (wire.ACTION_DIM,):
            raise FormationError(f"an action is 2 numbers (normalised v, w), got shape {np.shape(action)}")
        a0 = min(max(a[0], -1.0), 1.0) if math.isfinite(a[0]) else a[0]
        a1 = min(max(a[1], -1.0), 1.0) if math.isfinite(a[1]) else a[1]
        return (a0 + 1.0) * 0.5 * self.run.v_max, a1 * self.run.w_max

    def action_from_command(self, v: float, w: float) -> np.ndarray:
        """The normalised action for a physical (v, w) (clipped to the robot's limits)."""
        self._ensure_swarm()
        a0 = min(max(2.0 * v / self.run.v_max - 1.0, -1.0), 1.0)
        a1 = min(max(w / self.run.w_max, -1.0), 1.0)
        return np.array([a0, a1], dtype=np.float32)

    # --- the swarm ---------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise FormationError("the env is closed")

    def _log_tail(self, lines: int = 15) -> str:
        log = self.base_dir / f"swarm-{self._launches}.log"
        try:
            text = log.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return f"\n{log} (last lines):\n" + "\n".join(text[-lines:])

    def _make_base_dir(self) -> Path:
        """:attr:`base_dir`, made on first use."""
        if self.base_dir is None:
            run_dir = self._args["run_dir"]
            if run_dir is None:
                self.base_dir = Path(tempfile.mkdtemp(prefix="formation-env-"))
            else:
                Path(run_dir).mkdir(parents=True, exist_ok=True)
                self.base_dir = Path(tempfile.mkdtemp(prefix="copy-", dir=run_dir)) if self._copy else Path(run_dir)
        return self.base_dir

    def _launch(self, seed: int) -> None:
        """Starts run_swarm.sh for ``seed``, waits for run.json, attaches every robot slot."""
        self._make_base_dir()
        self._launches += 1
        k = self._launches
        run_dir = self.base_dir / f"swarm-{k}"
        config = self.base_dir / f"config-{k}.toml"
        config.write_text(
            f"# FormationEnv: {self.config or 'the defaults'}, with the env's tick deadline"
            + (" and reality=" if self.reality is not None else "") + "\n"
            + swarm_config(self.config, self.step_timeout_s, self.reality)
        )
        args = [
            str(self.launcher.command), str(self.n),
            "--external", "all", "--mode", "eval", "--episodes", str(RUN_EPISODES),
            "--seed", str(seed), "--viewer", self.viewer, "--placement", self.placement,
            "--config", str(config), "--run-dir", str(run_dir),
        ]
        if self.shape:
            args += ["--shape", self.shape]
        if self.obstacle_kind is not None:
            args += ["--obstacles", self.obstacle_kind]
        environ = dict(os.environ)
        if self.launcher.bin_dir is not None:
            environ["FORMATION_BIN_DIR"] = str(self.launcher.bin_dir)
        else:
            environ.pop("FORMATION_BIN_DIR", None)
        with open(self.base_dir / f"swarm-{k}.log", "wb") as log:
            self._proc = subprocess.Popen(
                args, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, env=environ,
                start_new_session=True,
            )
        self._seed = seed
        self.run_dir = run_dir
        self._reaper = subprocess.Popen(
            [sys.executable, "-c", _REAPER, str(self._proc.pid), str(run_dir), str(ORPHAN_GRACE_S)],
            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
        )
        deadline = time.monotonic() + self.launch_timeout_s
        while not (run_dir / "run.json").is_file():
            if self._proc.poll() is not None:
                raise FormationError(f"run_swarm.sh exited with status {self._proc.returncode}{self._log_tail()}")
            if time.monotonic() > deadline:
                raise FormationError(f"no {run_dir / 'run.json'} after {self.launch_timeout_s} s{self._log_tail()}")
            time.sleep(0.05)
        self.run = connect(run_dir, timeout=10)
        self._hold_clients_lock()
        if self.run.n_agents != self.n:
            raise FormationError(f"run.json says {self.run.n_agents} robots, the env asked for {self.n}")
        self._observer = Observer(self.run, name="env")
        self._robots = [Robot(self.run, i, None) for i in range(self.n)]
        self._waitset = (
            iox2.WaitSetBuilder.new()
            .signal_handling_mode(iox2.SignalHandlingMode.Disabled)
            .create(iox2.ServiceType.Ipc)
        )
        self._guards = [self._waitset.attach_notification(r.listener) for r in self._robots]
        self._guards.append(self._waitset.attach_notification(self._observer.listener))
        self._slice = iox2.Duration.from_secs_f64(WAIT_SLICE_S)
        self._queues: List[Deque[Tick]] = [collections.deque() for _ in range(self.n)]
        self._states: Deque[wire.State] = collections.deque()
        self._current: List[Optional[Tick]] = []
        self._observations: List[np.ndarray] = []
        self._owed = False
        self._key = (0, 0)
        self._last_episode = -1
        self._last_state: Optional[wire.State] = None
        self._cycles = 0
        self._return = 0.0
        self._run_ended = False
        for robot in self._robots:
            robot.greet()

    def _drain(self) -> bool:
        """Moves everything the sim sent into the queues; True when anything came."""
        came = False
        for robot, queue in zip(self._robots, self._queues):
            messages = robot.receive()
            if messages:
                came = True
                queue.extend(messages)
                if messages[-1].run_end:
                    self._run_ended = True
        states = self._observer.receive_raw()
        if states:
            came = True
            self._states.extend(s for s in states if not s.header.flags & wire.FLAG_RUN_END)
        return came

    def _wait(self) -> None:
        """Sleeps until any robot's ``observation_ready`` or the critic wake-up (raised at every
        episode's end, whose observations wake no robot) fires, or a slice passes."""
        self._waitset.wait_and_process_with_timeout(self._slice)
        for robot in self._robots:
            robot.take_wakeups()
        self._observer.take_wakeups()

    def _idle(self) -> None:
        """Nothing new arrived for a slice: greets while unheard, raises when the swarm is gone."""
        if self._run_ended:
            raise SimGone(f"the sim ended run {self.run.run_id}{self._log_tail()}")
        if self._proc is not None and self._proc.poll() is not None:
            raise SimGone(f"run_swarm.sh exited with status {self._proc.returncode}{self._log_tail()}")
        for robot in self._robots:
            try:
                robot.check_sim()
            except SimGone as err:
                raise SimGone(f"{err}{self._log_tail()}") from err

    def _take_state(self, key: Tuple[int, int], after: Tuple[int, int]) -> Tuple[Optional[wire.State], float]:
        """The state of tick ``key`` and the summed reward of the states after ``after`` up to
        it (None while it has not arrived); consumes the states up to ``key``."""
        for state in self._states:
            skey = (state.header.episode, state.header.tick)
            if skey == key:
                break
            if skey > key:
                return None, 0.0
        else:
            return None, 0.0
        reward = 0.0
        while True:
            state = self._states.popleft()
            skey = (state.header.episode, state.header.tick)
            if after < skey <= key and skey[0] == key[0]:
                reward += float(state.reward)
            if skey == key:
                return state, reward

    def _next_tick(self, key: Tuple[int, int]):
        """Waits for the newest state of episode ``key[0]`` after ``key`` and for the tick's
        observation at every robot whose observation was not lost (``State.observation_lost``).

        Returns (heads, reward, state, skipped ticks), a robot whose observation was lost
        having None in heads; heads None when the episode's end was lost (a later episode
        showed up first)."""
        episode = key[0]
        came = True
        while True:
            if not came:
                self._idle()
            for queue in self._queues:
                while queue and queue[0].key <= key:
                    queue.popleft()  # already answered (or stale)
            ahead = [q[0] for q in self._queues if q and (q[0].run_end or q[0].episode != episode)]
            if any(h.run_end for h in ahead):
                raise SimGone(f"the sim ended run {self.run.run_id} mid-episode{self._log_tail()}")
            if ahead:  # a robot is past the episode without its end (never lost): it went unseen
                return None, 0.0, None, 0
            newest, lost = None, []
            for state in self._states:
                if state.header.episode == episode and state.header.tick > key[1]:
                    newest, lost = state.header.tick, self._lost(state)
            if newest is not None:
                for queue in self._queues:
                    while queue and queue[0].episode == episode and queue[0].tick < newest:
                        queue.popleft()
                if all(lost[i] or (q and q[0].key == (episode, newest)) for i, q in enumerate(self._queues)):
                    state, reward = self._take_state((episode, newest), key)
                    if state is not None:
                        heads = [None if lost[i] else q.popleft() for i, q in enumerate(self._queues)]
                        return heads, reward, state, newest - key[1] - 1
            self._wait()
            came = self._drain()

    def _lost(self, state: wire.State) -> List[bool]:
        """Whose observation of ``state``'s tick was lost (not published, not waited for)."""
        mask = int(state.observation_lost)
        return [bool(mask >> i & 1) for i in range(self.n)]

    def _next_episode(self) -> List[Optional[Tick]]:
        """Waits for the state of tick 0 of the next episode (after ``_last_episode``) and that
        tick at every robot whose observation of it was not lost (None in the list for one
        that was), answering (0, 0) to any tick of an episode still running meanwhile."""
        came = self._drain()
        while True:
            if not came:
                self._idle()
            start = None
            for state in self._states:
                if state.header.tick == 0 and state.header.episode > self._last_episode:
                    start = state  # the newest episode started
            episode = None if start is None else start.header.episode
            for robot, queue in zip(self._robots, self._queues):
                while queue:
                    m = queue[0]
                    if m.run_end:
                        raise SimGone(f"the sim ended run {self.run.run_id}{self._log_tail()}")
                    if episode is not None and m.episode >= episode:
                        break  # its tick 0 (or a later tick, tick 0's observation lost)
                    if episode is None and m.episode_start and not m.episode_end and m.episode > self._last_episode:
                        break  # its state has not come yet
                    if len(queue) == 1 and not m.episode_end:
                        robot.answer(m, 0.0, 0.0)  # a tick of an episode played out: hold still
                    queue.popleft()
            if start is not None:
                lost = self._lost(start)
                if all(lost[i] or (q and q[0].key == (episode, 0)) for i, q in enumerate(self._queues)):
                    state, _ = self._take_state((episode, 0), (episode, -1))
                    self._last_state = state
                    return [None if lost[i] else q.popleft() for i, q in enumerate(self._queues)]
            self._wait()
            came = self._drain()

    def _shutdown(self) -> None:
        """Ends the running swarm: SIGINT to the launcher (it asks the sim to end the run),
        robots answering (0, 0) until the sim announces the end, ports released, the launcher
        waited for; past ``close_timeout_s`` its process group is killed and the run's shared
        memory removed. Whatever fails on the way, the ports go and the launcher is waited for
        (so nothing of the run writes into its directory once this returns or raises)."""
        proc = self._proc
        deadline = time.monotonic() + self.close_timeout_s
        try:
            if proc is not None and proc.poll() is None:
                try:
                    os.kill(proc.pid, signal.SIGINT)
                except ProcessLookupError:
                    pass
                if self._robots and self._waitset is not None:
                    try:
                        self._play_out(proc, deadline)
                    except FormationError:
                        pass
        finally:
            try:
                self._release_ports()
                self._release_clients_lock()
            finally:
                self._end_processes(proc, deadline)

    def _end_processes(self, proc: Optional[subprocess.Popen], deadline: float) -> None:
        """Waits for the launcher (past ``deadline`` kills its group), lets the watcher go and
        removes what the run left in /dev/shm."""
        if proc is not None:
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    pass
                proc.wait()
            self._proc = None
        if self._reaper is not None:
            try:
                self._reaper.communicate(b"done\n", timeout=5)
            except (subprocess.TimeoutExpired, OSError, ValueError):
                self._reaper.kill()
                self._reaper.wait()
            self._reaper = None
        run = self.run
        if run is None and self.run_dir is not None and (self.run_dir / "run.json").is_file():
            try:
                run = RunInfo.from_dict(self.run_dir, json.loads((self.run_dir / "run.json").read_text()))
            except (FormationError, ValueError, OSError):
                run = None
        if run is not None:
            self._remove_leftovers(run)
        self.agents = []

    def _play_out(self, proc: subprocess.Popen, deadline: float) -> None:
        """While the sim winds the run down: answer every live tick with (0, 0), until the sim
        announces the run's end or its node is gone.

        A sim can end without the announcement (killed by the signal before it could catch it,
        or stopped while it was starting). Then nothing is left to answer, and the ports must go
        at once: the launcher waits for them only briefly after its members have exited, then
        removes the run's files, and a port dropped after that warns of "a corrupted system"
        for each of its files."""
        if self._owed:
            for robot, tick in zip(self._robots, self._current):
                if tick is not None:
                    robot.answer(tick, 0.0, 0.0)
            self._owed = False
        while not self._run_ended and proc.poll() is None and time.monotonic() < deadline:
            self._wait()
            came = self._drain()
            for robot, queue in zip(self._robots, self._queues):
                if queue and not queue[-1].episode_end and not queue[-1].run_end:
                    robot.answer(queue[-1], 0.0, 0.0)
                queue.clear()
            if not came and not self.run.node_alive("sim"):
                return

    def _hold_clients_lock(self) -> None:
        """The run's clients lock while the ports are open (``RunInfo.hold_clients_lock``)."""
        self._clients_lock = self.run.hold_clients_lock()

    def _release_ports(self) -> None:
        for guard in self._guards:
            guard.delete()
        self._guards = []
        if self._waitset is not None:
            self._waitset.delete()
            self._waitset = None
        for robot in self._robots:
            robot.close()
        self._robots = []
        if self._observer is not None:
            self._observer.close()
            self._observer = None

    def _release_clients_lock(self) -> None:
        """Once the ports are gone (and whatever still referred to them: a collection first),
        lets the launcher remove the run's files."""
        if self._clients_lock is not None:
            gc.collect()
            os.close(self._clients_lock)
            self._clients_lock = None

    @staticmethod
    def _remove_leftovers(run: RunInfo) -> None:
        """What a killed launcher could not remove: the run's /dev/shm files and root path."""
        try:
            names = os.listdir("/dev/shm")
        except OSError:
            return
        for name in names:
            if name.startswith(run.shm_prefix):
                try:
                    os.remove(os.path.join("/dev/shm", name))
                except OSError:
                    pass
        shutil.rmtree(run.root_path, ignore_errors=True)
