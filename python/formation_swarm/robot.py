"""One robot slot of a running swarm, played from Python exactly as ``formation-agent`` plays it
(``agent/src/run.rs``, ``agent/src/ports.rs``)."""

from __future__ import annotations

import dataclasses
import math
import os
import secrets
import time
from pathlib import Path
from typing import Any, Callable, List, Optional, Sequence, Tuple, Union

import iceoryx2 as iox2

from . import run as runmod
from . import wire
from .run import FormationError, RunInfo, SimGone

try:  # numpy is optional: without it a policy gets a list of floats.
    import numpy as _np
except ImportError:  # pragma: no cover - exercised only without numpy
    _np = None

Policy = Callable[[Any], Tuple[float, float]]

#: How long one wait on the wake-up event lasts before the loop checks the sim's health.
WAIT_SLICE_S = 0.1


@dataclasses.dataclass(frozen=True)
class Tick:
    """One message of the sim to a robot (``formation::Observation``), as :meth:`Robot.receive`
    hands it out."""

    episode: int
    tick: int
    flags: int
    #: The observation's ``dim`` floats (a list), also at an episode's end; None at the run's end.
    obs: Optional[List[float]]

    @property
    def key(self) -> Tuple[int, int]:
        """(episode, tick), which orders the ticks of a run."""
        return (self.episode, self.tick)

    @property
    def episode_start(self) -> bool:
        """Tick 0 of an episode."""
        return bool(self.flags & wire.FLAG_EPISODE_START)

    @property
    def episode_end(self) -> bool:
        """The episode ended at this tick: no answer is expected."""
        return bool(self.flags & wire.FLAG_EPISODE_END)

    @property
    def run_end(self) -> bool:
        """The run is over."""
        return bool(self.flags & wire.FLAG_RUN_END)


@dataclasses.dataclass
class RobotStats:
    """What a robot did."""

    commands: int = 0
    episodes: int = 0
    greetings: int = 0
    policy_errors: int = 0


class Robot:
    """Plays robot ``index`` of the run in ``run_dir`` with ``policy(obs) -> (v, w)``.

    * greets the sim (``FLAG_HELLO``, a random non-zero session) until the sim answers;
    * sleeps on its ``observation_ready`` event (never spins), takes every observation that
      arrived and answers the newest with ``policy(obs[:dim])``;
    * on ``FLAG_EPISODE_START`` (or a new episode number) calls ``policy.reset(episode, explore)``
      when the policy has one; ignores ``FLAG_EPISODE_END`` states (no answer is expected);
    * returns on ``FLAG_RUN_END``; raises ``SimGone`` when the sim falls silent and its process
      is gone (or stays silent past the start-up timeout).

    ``obs`` is a float32 numpy array when numpy is installed (``numpy=False``: a list).

    :meth:`run_forever` is the whole loop. Its pieces serve a caller that drives the robot
    itself (``formation_swarm.FormationEnv`` plays every robot of a swarm from one process):
    :meth:`greet`, :meth:`receive` (every message since the last call, without waiting),
    :meth:`answer` (the command for one tick), :meth:`check_sim` (while nothing arrives) and
    :attr:`listener` (to wait on several robots at once). ``policy`` may then be None.
    """

    def __init__(
        self,
        run_dir: Union[str, Path, RunInfo],
        index: int,
        policy: Optional[Policy] = None,
        *,
        numpy: Optional[bool] = None,
        connect_timeout: Optional[float] = 60.0,
        policy_version: int = 0,
    ) -> None:
        self.run = run_dir if isinstance(run_dir, RunInfo) else runmod.connect(run_dir, connect_timeout)
        if not 0 <= index < self.run.n_agents:
            raise FormationError(
                f"robot {index} does not exist in a swarm of {self.run.n_agents} "
                f"(robots are 0..{self.run.n_agents - 1})"
            )
        self.index = index
        self.policy = policy
        self.policy_version = policy_version
        self.use_numpy = (_np is not None) if numpy is None else bool(numpy)
        if self.use_numpy and _np is None:
            raise FormationError("numpy=True but numpy is not installed")
        #: Random per Robot, so the sim tells a restarted robot from its predecessor.
        self.session = secrets.randbelow(2**32 - 2) + 1
        self.stats = RobotStats()
        #: True once any message of the sim arrived (until then, :meth:`check_sim` greets).
        self.heard_any = False
        #: True once the sim announced the end of the run.
        self.run_ended = False
        self._warned = False
        self._last_heard = time.monotonic()
        self._episode: Optional[int] = None
        #: The run's clients lock while the ports are open (see ``RunInfo.hold_clients_lock``).
        self._clients_lock = self.run.hold_clients_lock()
        self._node = self.run.create_node(f"agent{index}")
        run = self.run
        self._observations = (
            runmod.observation_stream(self._node, run, index).subscriber_builder().buffer_size(16).create()
        )
        self._wake = runmod.observation_event(self._node, run, index).listener_builder().create()
        self._commands = runmod.command_stream(self._node, run, index).publisher_builder().create()
        self._command_ready = (
            runmod.command_event(self._node, run)
            .notifier_builder()
            .default_event_id(iox2.EventId.new(index))
            .create()
        )

    # --- ports ---------------------------------------------------------------------------

    def _send(self, episode: int, tick: int, flags: int, v: float, w: float, version: int) -> None:
        command = wire.Command(
            header=wire.Header.new(episode, tick, flags),
            agent=self.index,
            policy_version=version,
            v=v,
            w=w,
            session=self.session,
        )
        self._commands.loan_uninit().write_payload(command).send()
        self._command_ready.notify()

    def greet(self) -> None:
        """Greets the sim (history 1 keeps the greeting for a sim that starts later)."""
        self._send(0, 0, wire.FLAG_HELLO, 0.0, 0.0, 0)
        self.stats.greetings += 1

    def _wait(self, timeout_s: float) -> None:
        try:
            self._wake.timed_wait(iox2.Duration.from_secs_f64(timeout_s))
        except iox2.ListenerWaitError:
            # A signal interrupted the wait: Python runs its handler (KeyboardInterrupt) next.
            pass

    def close(self) -> None:
        """Releases the ports and the node (also done when the Robot is garbage collected)."""
        for port in ("_observations", "_wake", "_commands", "_command_ready"):
            obj = getattr(self, port, None)
            if obj is not None:
                obj.delete()
                setattr(self, port, None)
        self._node = None
        if getattr(self, "_clients_lock", None) is not None:
            os.close(self._clients_lock)
            self._clients_lock = None

    def __enter__(self) -> "Robot":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # --- the loop, piece by piece ----------------------------------------------------------

    def _as_obs(self, values: Sequence[float]) -> Any:
        if self.use_numpy:
            return _np.array(values, dtype=_np.float32)
        return list(values)

    @property
    def listener(self) -> Any:
        """The ``observation_ready`` listener (to attach to an ``iceoryx2.WaitSet``; consume
        its events with :meth:`take_wakeups`)."""
        return self._wake

    def take_wakeups(self) -> None:
        """Consumes the pending wake-ups without waiting (after a ``WaitSet`` woke up)."""
        runmod.take_wakeups(self._wake)

    def receive(self) -> List[Tick]:
        """Every message the sim sent since the last call (oldest first), without waiting.

        Applies the protocol's rules to each: refuses another protocol version and an
        observation of the wrong size (``FormationError``), counts a new episode and calls
        ``policy.reset(episode, explore)`` for it, and stops at ``FLAG_RUN_END`` (the last
        message; :attr:`run_ended` turns True). ``Tick.obs`` is the list of the observation's
        floats (:meth:`run_forever` converts only the one it answers), also at an episode's end
        (the final observation), None at the run's end.
        """
        run = self.run
        agent = self.index
        out: List[Tick] = []
        while True:
            sample = self._observations.receive()
            if sample is None:
                break
            msg = sample.payload().contents
            header = msg.header
            version, ep, tick, flags = header.protocol_version, header.episode, header.tick, header.flags
            dim = msg.dim
            values = msg.obs[:dim] if not flags & wire.FLAG_RUN_END else None
            sample.delete()
            if version != wire.PROTOCOL_VERSION:
                raise FormationError(
                    f"robot {agent}: the sim speaks protocol {version}, formation_swarm "
                    f"{wire.PROTOCOL_VERSION}: install the python/ package of the same checkout"
                )
            self.heard_any = True
            self._warned = False
            self._last_heard = time.monotonic()
            if flags & wire.FLAG_RUN_END:
                self.run_ended = True
                out.append(Tick(ep, tick, flags, None))
                return out
            if dim != run.observation_dim:
                raise FormationError(
                    f"robot {agent}: the sim sends observations of {dim} floats, run.json says "
                    f"{run.observation_dim} ({run.observation!r})"
                )
            if not flags & wire.FLAG_EPISODE_END and (flags & wire.FLAG_EPISODE_START or self._episode != ep):
                self._episode = ep
                self.stats.episodes += 1
                reset = getattr(self.policy, "reset", None)
                if callable(reset):
                    reset(ep, not flags & wire.FLAG_EVAL_EPISODE and run.mode == "train")
            out.append(Tick(ep, tick, flags, values))
        return out

    def answer(self, tick: Tick, v: float, w: float) -> None:
        """Sends the command (v, w) for ``tick`` (an observation tick from :meth:`receive`).

        A non-finite command is replaced by (0, 0), which the sim accepts, and said once."""
        v, w = float(v), float(w)
        if not (math.isfinite(v) and math.isfinite(w)):
            # The sim refuses non-finite commands; hold still instead and say so once.
            self.stats.policy_errors += 1
            if self.stats.policy_errors == 1:
                print(f"robot {self.index}: the policy returned a non-finite command; sending (0, 0)", flush=True)
            v, w = 0.0, 0.0
        self._send(tick.episode, tick.tick, 0, v, w, self.policy_version)
        self.stats.commands += 1

    def check_sim(self) -> None:
        """Call while nothing arrives: greets again until the sim has answered once, and raises
        ``SimGone`` when the launcher has ended, the sim fell silent for ``sim_silence_ms`` and
        its process is gone, or it stayed silent past ``startup_timeout_s`` (warns once while a
        live sim is silent)."""
        run = self.run
        agent = self.index
        if not self.heard_any:
            # A publisher hands its history only to subscribers it has seen: greet
            # again until the sim has connected and answered.
            self.greet()
        quiet = time.monotonic() - self._last_heard
        if quiet > 1.0 and not run.launcher_alive():
            raise SimGone(f"robot {agent}: the launcher of run {run.run_id} has ended")
        if quiet > run.startup_timeout_s:
            raise SimGone(f"robot {agent}: no observation from the sim for {quiet:.1f} s; is it alive?")
        silence_s = run.sim_silence_ms / 1000.0
        if self.heard_any and quiet > silence_s and not run.node_alive("sim"):
            raise SimGone(f"robot {agent}: the sim has been silent for {quiet:.1f} s and its process is gone")
        if self.heard_any and quiet > silence_s and not self._warned:
            self._warned = True
            print(
                f"robot {agent}: the sim has been silent for {quiet:.1f} s but its process is alive; "
                f"waiting up to {run.startup_timeout_s:.0f} s",
                flush=True,
            )

    # --- the loop -------------------------------------------------------------------------

    def run_forever(self) -> RobotStats:
        """Plays until the sim announces the end of the run; returns what it did."""
        if self.policy is None:
            raise FormationError(f"robot {self.index}: run_forever needs a policy")
        self.greet()
        self._last_heard = time.monotonic()
        while True:
            self._wait(WAIT_SLICE_S)
            messages = self.receive()
            newest = messages[-1] if messages else None
            if newest is not None and newest.run_end:
                return self.stats
            if newest is None or newest.episode_end:
                # Nothing to answer (an episode's end needs no answer).
                self.check_sim()
                continue
            v, w = self.policy(self._as_obs(newest.obs))
            self.answer(newest, v, w)


def run_robot(run_dir: Union[str, Path], index: int, policy: Policy, **kwargs: Any) -> RobotStats:
    """Connects robot ``index`` of the run in ``run_dir``, plays until the run ends, closes."""
    with Robot(run_dir, index, policy, **kwargs) as robot:
        return robot.run_forever()
