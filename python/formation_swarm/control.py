"""The live control service (``formation/control``): change a running episode's formation,
goal or team from Python.

    import formation_swarm as fs
    control = fs.Control("runs/demo")
    ack = control.set_formation("ring", scale=1.0, orientation=0.0)
    print(ack.tick)   # the first tick whose observations and state carry the ring

Each call is one iceoryx2 request; the sim answers it at its next tick (after the step, never
waiting for requests) with an acknowledgement naming the tick the change is in force from, or
a refusal (``ControlRefused``) saying why. A change lasts for the current episode.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, Optional, Union

import iceoryx2 as iox2

from . import run as runmod
from . import wire
from .run import FormationError, RunInfo, SimGone

#: How often a waiting call checks that the run is still alive, seconds.
ALIVE_CHECK_S = 0.5


class ControlRefused(FormationError):
    """The sim refused a control request; ``reason`` says why."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclasses.dataclass(frozen=True)
class ControlAck:
    """The sim obeyed: the change is in force from ``tick`` of ``episode``."""

    episode: int
    tick: int


class Control:
    """A client of the run's control service (the run in ``run_dir``, or its ``RunInfo``)."""

    def __init__(
        self,
        run_dir: Union[str, Path, RunInfo],
        *,
        connect_timeout: Optional[float] = 60.0,
        name: str = "control",
    ) -> None:
        self.run = run_dir if isinstance(run_dir, RunInfo) else runmod.connect(run_dir, connect_timeout)
        self._node = self.run.create_node(name)
        deadline = None if connect_timeout is None else time.monotonic() + connect_timeout
        while True:
            try:
                service = runmod.control_service(self._node, self.run)
                break
            except iox2.RequestResponseOpenError as err:
                # The sim creates the service when it starts; until then it does not exist.
                if deadline is not None and time.monotonic() >= deadline:
                    raise FormationError(f"no control service in run {self.run.run_id}: {err!r}") from err
                time.sleep(0.05)
        self._client = service.client_builder().create()
        self._answered = runmod.control_answered_event(self._node, self.run).listener_builder().create()

    def set_formation(
        self, shape: str, scale: float = 1.0, orientation: float = 0.0, timeout: float = 10.0
    ) -> ControlAck:
        """A new formation for the rest of the episode: ``shape`` (``random``, ``ring``,
        ``line``, ``wedge``, ``grid``) as the sim draws it, times ``scale``, turned by
        ``orientation`` radians, around the goal; the robots take its slots by the mission
        planner's optimal assignment."""
        request = wire.ControlRequest()
        request.protocol_version = wire.PROTOCOL_VERSION
        request.kind = wire.CONTROL_SET_FORMATION
        name = shape.encode("utf-8")[: len(request.shape)]
        request.shape[: len(name)] = list(name)
        request.scale = scale
        request.orientation = orientation
        return self._request(request, timeout)

    def set_goal(self, x: float, y: float, timeout: float = 10.0) -> ControlAck:
        """A new goal (world frame, metres) for the rest of the episode, the formation in force
        around it."""
        request = wire.ControlRequest()
        request.protocol_version = wire.PROTOCOL_VERSION
        request.kind = wire.CONTROL_SET_GOAL
        request.goal[0], request.goal[1] = x, y
        return self._request(request, timeout)

    def remove_robot(self, robot: int, timeout: float = 10.0) -> ControlAck:
        """Takes robot ``robot`` out of the formation for the rest of the episode: the others
        re-form the same formation for one robot fewer, and it is commanded to stand still.
        Refused for an unknown robot, one already out, or when fewer than 3 would stay."""
        return self._team(wire.CONTROL_REMOVE_ROBOT, robot, timeout)

    def restore_robot(self, robot: int, timeout: float = 10.0) -> ControlAck:
        """Brings robot ``robot``, removed earlier in the episode, back into the formation (the
        others re-form around it). Refused for a robot that is in, or out for another reason
        (its controller failed, or it is silent)."""
        return self._team(wire.CONTROL_RESTORE_ROBOT, robot, timeout)

    def _team(self, kind: int, robot: int, timeout: float) -> ControlAck:
        request = wire.ControlRequest()
        request.protocol_version = wire.PROTOCOL_VERSION
        request.kind = kind
        request.robot = robot
        return self._request(request, timeout)

    def _request(self, request: wire.ControlRequest, timeout: float) -> ControlAck:
        pending = self._client.send_copy(request)
        deadline = time.monotonic() + timeout
        try:
            while True:
                response = pending.receive()
                if response is not None:
                    reply = wire.ControlReply.from_buffer_copy(response.payload().contents)
                    response.delete()
                    return _answer(reply)
                left = deadline - time.monotonic()
                if left <= 0:
                    raise FormationError(f"no control reply within {timeout} s")
                if not self.run.launcher_alive():
                    raise SimGone(f"run {self.run.run_id} ended before the sim answered")
                try:
                    self._answered.timed_wait(iox2.Duration.from_secs_f64(min(left, ALIVE_CHECK_S)))
                except iox2.ListenerWaitError:
                    pass
        finally:
            pending.delete()

    def close(self) -> None:
        """Releases the ports and the node."""
        for port in ("_client", "_answered"):
            obj = getattr(self, port, None)
            if obj is not None:
                obj.delete()
                setattr(self, port, None)
        self._node = None

    def __enter__(self) -> "Control":
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()


def _answer(reply: wire.ControlReply) -> ControlAck:
    if reply.status == wire.CONTROL_OK:
        return ControlAck(episode=reply.episode, tick=reply.tick)
    reason = bytes(reply.message).split(b"\0", 1)[0].decode("utf-8", "replace")
    raise ControlRefused(reason)
