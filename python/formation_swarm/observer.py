"""Reading the live true state (``formation/state``) and each episode's obstacles
(``formation/obstacles``) of a running swarm."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, Iterator, List, Optional, Tuple, Union

import iceoryx2 as iox2

from . import run as runmod
from . import wire
from .run import RunInfo


@dataclasses.dataclass(frozen=True)
class WorldState:
    """One tick of the true world (a copy of ``formation::State``, trimmed to ``n_agents``)."""

    episode: int
    tick: int
    flags: int
    sequence: int
    n_agents: int
    outcome: int
    reward: float
    missed: int
    #: World poses (x, y, theta) of every robot.
    poses: List[Tuple[float, float, float]]
    #: Commands (v, w) applied in the transition into this tick.
    applied: List[Tuple[float, float]]
    #: Desired length of each robot's two observed edges.
    desired: List[Tuple[float, float]]
    #: Each robot's offset from the goal in the goal formation.
    slots: List[Tuple[float, float]]
    #: Goal of the formation's centroid.
    goal: Tuple[float, float]
    #: Whether each robot is in the formation (out: its controller failed, it was removed, or
    #: it has been silent for 10 ticks).
    present: List[bool]
    #: The slot map: the slot each robot holds in the formation in force (robot i in slot i
    #: until the mission planner reassigns them at a change of formation); ``None`` for a robot
    #: out of the formation. Robot i observes the robots in the next two slots.
    slot: List[Optional[int]]
    #: The raw payload copy.
    raw: wire.State = dataclasses.field(repr=False, compare=False)

    @property
    def run_end(self) -> bool:
        """True for the sim's end-of-run message (no world in it)."""
        return bool(self.flags & wire.FLAG_RUN_END)

    @property
    def outcome_name(self) -> str:
        """``running``, ``success``, ``collision``, ``timeout`` or ``aborted``."""
        return wire.OUTCOME_NAMES.get(self.outcome, str(self.outcome))

    @classmethod
    def from_payload(cls, raw: wire.State) -> "WorldState":
        """Copies what is in use of a ``formation::State``."""
        n = min(int(raw.n_agents), wire.MAX_AGENTS)
        return cls(
            episode=raw.header.episode,
            tick=raw.header.tick,
            flags=raw.header.flags,
            sequence=raw.sequence,
            n_agents=n,
            outcome=raw.outcome,
            reward=raw.reward,
            missed=raw.missed,
            poses=[tuple(raw.poses[i]) for i in range(n)],
            applied=[tuple(raw.applied[i]) for i in range(n)],
            desired=[tuple(raw.desired[i]) for i in range(n)],
            slots=[tuple(raw.slots[i]) for i in range(n)],
            goal=(raw.goal[0], raw.goal[1]),
            present=[bool(raw.present >> i & 1) for i in range(n)],
            slot=[int(raw.slot[i]) if raw.slot[i] < n else None for i in range(n)],
            raw=raw,
        )

    @property
    def robot_in_slot(self) -> List[int]:
        """The inverse of :attr:`slot`: the robot holding each slot, slot by slot."""
        held = sorted((s, robot) for robot, s in enumerate(self.slot) if s is not None)
        return [robot for _, robot in held]

    @property
    def observed(self) -> List[Tuple[int, int]]:
        """The two robots each robot observes: those in the next two slots of the formation
        (modulo the robots in it); a robot out of the formation observes itself."""
        holders = self.robot_in_slot
        m = len(holders)
        return [
            (robot, robot) if s is None else (holders[(s + 1) % m], holders[(s + 2) % m])
            for robot, s in enumerate(self.slot)
        ]


@dataclasses.dataclass(frozen=True)
class EpisodeObstacles:
    """One episode's obstacles, world frame, metres (a copy of ``formation::Obstacles``, which
    the sim publishes once per episode before its first tick; none in an open episode)."""

    episode: int
    #: The kind the episode drew: ``none``, ``forest``, ``passage`` or ``trap`` (a ``mixed``
    #: run draws one of the three per episode).
    kind: str
    #: The episode's time limit, steps (it depends on the obstacles and the goal distance).
    time_limit: int
    #: Discs: centre x, centre y, radius.
    discs: List[Tuple[float, float, float]]
    #: Walls: a.x, a.y, b.x, b.y, thickness (a rectangle whose centre line runs from a to b,
    #: flat ends).
    walls: List[Tuple[float, float, float, float, float]]
    #: The raw payload copy.
    raw: wire.Obstacles = dataclasses.field(repr=False, compare=False)

    @classmethod
    def from_payload(cls, raw: wire.Obstacles) -> "EpisodeObstacles":
        """Copies the ``count`` obstacles in use of a ``formation::Obstacles``."""
        discs, walls = [], []
        for k in range(min(int(raw.count), wire.MAX_OBSTACLES)):
            values = tuple(float(v) for v in raw.values[k])
            if raw.shapes[k] == wire.OBSTACLE_DISC:
                discs.append(values[:3])
            elif raw.shapes[k] == wire.OBSTACLE_WALL:
                walls.append(values)
            else:
                raise runmod.FormationError(f"obstacle {k} of episode {raw.header.episode} has shape {raw.shapes[k]}")
        return cls(
            episode=raw.header.episode,
            kind=wire.OBSTACLE_KIND_NAMES.get(raw.kind, str(raw.kind)),
            time_limit=raw.time_limit,
            discs=discs,
            walls=walls,
            raw=raw,
        )


class Observer:
    """Subscribes to the true state of the run in ``run_dir``.

    Sleeps on ``formation/critic/wake`` (the sim raises it every half critic window and at
    every episode's end) or at most ``poll_s`` between looks; the state subscriber keeps the
    last ``2 * critic_window + 16`` states, so an observer that keeps up misses none. The
    stream overwrites the oldest state for a slow observer: it never holds the sim back.
    """

    def __init__(
        self,
        run_dir: Union[str, Path, RunInfo],
        *,
        connect_timeout: Optional[float] = 60.0,
        poll_s: float = 0.05,
        name: str = "observer",
    ) -> None:
        self.run = run_dir if isinstance(run_dir, RunInfo) else runmod.connect(run_dir, connect_timeout)
        self.poll_s = poll_s
        self._node = self.run.create_node(name)
        self._states = runmod.state_stream(self._node, self.run).subscriber_builder().create()
        self._obstacles = runmod.obstacles_stream(self._node, self.run).subscriber_builder().create()
        self._wake = runmod.critic_wake_event(self._node, self.run).listener_builder().create()
        self.run_ended = False

    def receive(self) -> List[WorldState]:
        """Every state that arrived since the last call (oldest first), without waiting."""
        return [WorldState.from_payload(raw) for raw in self.receive_raw()]

    def receive_raw(self) -> List[wire.State]:
        """Like :meth:`receive`, as copies of the raw payloads (``wire.State``, all 64 robots'
        room; nothing else is built: the cheap way to keep up every tick)."""
        out = []
        while True:
            sample = self._states.receive()
            if sample is None:
                return out
            raw = wire.State.from_buffer_copy(sample.payload().contents)
            sample.delete()
            if raw.header.flags & wire.FLAG_RUN_END:
                self.run_ended = True
            out.append(raw)

    def receive_obstacles(self) -> List[EpisodeObstacles]:
        """The obstacles of every episode that started since the last call (oldest first; the
        subscriber holds the last 2), without waiting. The sim publishes an episode's obstacles
        before its first tick, so they are here once that tick's state is."""
        out = []
        while True:
            sample = self._obstacles.receive()
            if sample is None:
                return out
            raw = wire.Obstacles.from_buffer_copy(sample.payload().contents)
            sample.delete()
            out.append(EpisodeObstacles.from_payload(raw))

    @property
    def listener(self) -> Any:
        """The ``formation/critic/wake`` listener (raised every half critic window and at
        every episode's end), to attach to an ``iceoryx2.WaitSet``; see :meth:`take_wakeups`."""
        return self._wake

    def take_wakeups(self) -> None:
        """Consumes the pending wake-ups without waiting."""
        runmod.take_wakeups(self._wake)

    def wait(self, timeout: float) -> List[WorldState]:
        """Waits up to ``timeout`` seconds for states; returns what arrived (maybe nothing)."""
        deadline = time.monotonic() + timeout
        while True:
            states = self.receive()
            left = deadline - time.monotonic()
            if states or left <= 0:
                return states
            try:
                self._wake.timed_wait(iox2.Duration.from_secs_f64(min(left, self.poll_s)))
            except iox2.ListenerWaitError:
                pass

    def states(self, timeout: Optional[float] = None) -> Iterator[WorldState]:
        """Yields every state until the run ends (its end-of-run state, or the sim's process
        gone), or until none came for ``timeout`` seconds."""
        idle_since = time.monotonic()
        heard = False
        while not self.run_ended:
            batch = self.wait(0.5)
            for state in batch:
                if state.run_end:
                    return
                heard = True
                yield state
            now = time.monotonic()
            if batch:
                idle_since = now
                continue
            if heard and not self.run.node_alive("sim"):
                # The sim exited before its end-of-run state was read (it goes with the sim).
                self.run_ended = True
                return
            if timeout is not None and now - idle_since >= timeout:
                return

    def close(self) -> None:
        """Releases the ports and the node."""
        for port in ("_states", "_obstacles", "_wake"):
            obj = getattr(self, port, None)
            if obj is not None:
                obj.delete()
                setattr(self, port, None)
        self._node = None

    def __enter__(self) -> "Observer":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

