"""Attaching to a running swarm: ``run.json``, the run-unique iceoryx2 configuration, service
names and sizes.

Mirrors ``protocol/src/services.rs``: the shared-memory prefix ``fc_<run id>_``, the root path
``$TMPDIR/formation-iox2/<run id>/`` and, for every service a Python process opens, exactly the
sizes the Rust processes ask for (so whichever side creates a service first, the other opens it).
"""

from __future__ import annotations

import dataclasses
import fcntl
import json
import os
import time
from pathlib import Path
from typing import Any, Optional, Union

import iceoryx2 as iox2

from . import wire


class FormationError(RuntimeError):
    """Something about the run or the wire is not as this client expects."""


class SimGone(FormationError):
    """The sim fell silent and its process is gone (or it stayed silent too long)."""


#: Floats per observation model (``formation_core::observation::Layout::dim``, from layout.json).
OBSERVATION_DIMS = {name: model.dim for name, model in wire.OBSERVATION_MODELS.items()}


@dataclasses.dataclass(frozen=True)
class RunInfo:
    """What ``scripts/run_swarm.sh`` writes into ``<run dir>/run.json`` before anything starts."""

    run_dir: Path
    run_id: str
    n_agents: int
    shm_prefix: str
    root_path: str
    protocol_version: int
    observation: str
    observation_dim: int
    critic_window: int
    startup_timeout_s: float
    sim_silence_ms: int
    command_timeout_ms: int
    v_max: float
    w_max: float
    proximity_range_m: float
    mode: str
    external: tuple
    launcher_pid: int

    @classmethod
    def from_dict(cls, run_dir: Path, raw: dict) -> "RunInfo":
        """Parses run.json's contents; unknown keys are ignored, missing ones are an error."""
        try:
            return cls(
                run_dir=run_dir,
                run_id=str(raw["run_id"]),
                n_agents=int(raw["n_agents"]),
                shm_prefix=str(raw["shm_prefix"]),
                root_path=str(raw["root_path"]),
                protocol_version=int(raw["protocol_version"]),
                observation=str(raw["observation"]),
                observation_dim=int(raw["observation_dim"]),
                critic_window=int(raw["critic_window"]),
                startup_timeout_s=float(raw["startup_timeout_s"]),
                sim_silence_ms=int(raw["sim_silence_ms"]),
                command_timeout_ms=int(raw["command_timeout_ms"]),
                v_max=float(raw["v_max"]),
                w_max=float(raw["w_max"]),
                proximity_range_m=float(raw["proximity_range_m"]),
                mode=str(raw["mode"]),
                external=tuple(int(i) for i in raw.get("external", [])),
                launcher_pid=int(raw.get("launcher_pid", 0)),
            )
        except (KeyError, TypeError, ValueError) as err:
            raise FormationError(f"{run_dir / 'run.json'} is malformed: {err!r}") from err

    def launcher_alive(self) -> bool:
        """True while the launcher that wrote run.json still runs (False for a finished run):
        while someone holds the run's lock file, ``/dev/shm/<shm prefix>launcher.lock``, which
        the launcher locks (``flock``) for its whole life and removes with the run's files. A
        pid would not do: a launcher in another PID namespace sharing /dev/shm has none here.
        A run.json written by hand (``launcher_pid`` 0: no launcher) counts as alive."""
        if self.launcher_pid <= 0:
            return True
        try:
            os.close(self._shared_lock("launcher.lock"))
        except FileNotFoundError:
            return False
        except BlockingIOError:
            return True
        return False

    def hold_clients_lock(self) -> Optional[int]:
        """Takes a shared ``flock`` on the run's ``/dev/shm/<shm prefix>clients.lock`` for as
        long as a client's ports are open; returns its file descriptor (close it once the ports
        are gone), or None when the run is gone or being removed. At the run's end the launcher
        waits for the lock (a few seconds at most) before it removes the run's files, so ports
        that outlive the sim remove their services themselves (iceoryx2 would otherwise warn of
        "a corrupted system" for each)."""
        try:
            return self._shared_lock("clients.lock")
        except OSError:  # gone, or the launcher is already removing the run
            return None

    def _shared_lock(self, name: str) -> int:
        """A shared, non-blocking ``flock`` on the run's ``/dev/shm/<shm prefix><name>``: its file
        descriptor. Raises ``FileNotFoundError`` without the file, ``BlockingIOError`` while
        someone holds it exclusively."""
        fd = os.open(f"/dev/shm/{self.shm_prefix}{name}", os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise
        return fd

    # --- service sizing, as protocol/src/services.rs derives it -----------------------------

    @property
    def stream_buffer(self) -> int:
        """``Sizing::stream_buffer``: samples a subscriber may hold."""
        return 2 * self.critic_window + 16

    @property
    def shared_nodes(self) -> int:
        """``Sizing::shared_nodes``."""
        return self.n_agents + 2 + wire.SPARE_PORTS

    def iceoryx_config(self) -> Any:
        """The iceoryx2 configuration every process of this run uses (its prefix and root path).

        A Python client does not clean up dead nodes when its own nodes go (it still does when
        it creates one): a client that closes after a sim was killed would race the run's other
        processes over the dead node's files, and iceoryx2 prints "No config file was loaded"
        when it finds one half removed. The launcher removes the run's files at its end."""
        config = iox2.config.default()
        config.global_cfg.prefix = iox2.FileName.new(self.shm_prefix)
        root = self.root_path if self.root_path.endswith("/") else self.root_path + "/"
        config.global_cfg.root_path = iox2.Path.new(root)
        config.global_cfg.node.cleanup_dead_nodes_on_destruction = False
        return config

    def create_node(self, name: str) -> Any:
        """A node of this run named ``name`` (shown by ``iox2 node list``).

        iceoryx2's own signal handler is disabled so that Python keeps its SIGINT handling
        (``KeyboardInterrupt``)."""
        return (
            iox2.NodeBuilder.new()
            .name(iox2.NodeName.new(name))
            .config(self.iceoryx_config())
            .signal_handling_mode(iox2.SignalHandlingMode.Disabled)
            .create(iox2.ServiceType.Ipc)
        )

    def node_alive(self, name: str) -> bool:
        """True while a live process of the run holds a node named ``name``."""
        for state in iox2.Node.list(iox2.ServiceType.Ipc, self.iceoryx_config()):
            if isinstance(state, iox2.NodeState.Alive):
                details = state[0].details
                if details is not None and details.name.as_str() == name:
                    return True
        return False


def run_contract(run: RunInfo) -> Any:
    """The attributes every service of the run carries (``services::RunContract``): a process
    of another protocol version, swarm size or observation model fails at open."""
    verifier = iox2.AttributeVerifier.new()
    for key, value in (
        ("formation.protocol_version", wire.PROTOCOL_VERSION),
        ("formation.n_agents", run.n_agents),
        ("formation.observation_dim", run.observation_dim),
    ):
        verifier = verifier.require(iox2.AttributeKey.new(key), iox2.AttributeValue.new(str(value)))
    return verifier


def _stream(
    node: Any, run: RunInfo, name: str, payload: type, history: int, max_nodes: int,
    readers: int = 2, buffer: Optional[int] = None,
) -> Any:
    """A publish-subscribe service as ``services::stream_for`` sizes it: ``readers``
    subscribers besides the spares, ``history`` samples kept for late subscribers, subscribers
    holding ``buffer`` samples (default: the stream buffer, at least the history)."""
    return (
        node.service_builder(iox2.ServiceName.new(name))
        .publish_subscribe(payload)
        .max_publishers(1 + wire.SPARE_PORTS)
        .max_subscribers(readers + wire.SPARE_PORTS)
        .max_nodes(max_nodes)
        .history_size(history)
        .subscriber_max_buffer_size(max(run.stream_buffer, history) if buffer is None else buffer)
        .open_or_create_with_attributes(run_contract(run))
    )


def _event(node: Any, run: RunInfo, name: str, notifiers: int) -> Any:
    return (
        node.service_builder(iox2.ServiceName.new(name))
        .event()
        .max_notifiers(notifiers + wire.SPARE_PORTS)
        .max_listeners(1 + wire.SPARE_PORTS)
        .max_nodes(run.shared_nodes)
        .event_id_max_value(wire.MAX_AGENTS)
        .open_or_create_with_attributes(run_contract(run))
    )


def observation_stream(node: Any, run: RunInfo, agent: int) -> Any:
    """``formation/agent/<i>/observation``: history 0, at most 2 + spare nodes."""
    name = f"formation/agent/{agent}/observation"
    return _stream(node, run, name, wire.Observation, 0, 2 + wire.SPARE_PORTS)


def observation_event(node: Any, run: RunInfo, agent: int) -> Any:
    """``formation/agent/<i>/observation_ready``: the sim wakes robot i."""
    return _event(node, run, f"formation/agent/{agent}/observation_ready", 1)


def command_stream(node: Any, run: RunInfo, agent: int) -> Any:
    """``formation/agent/<i>/command``: history 1 keeps the greeting for a sim that starts later."""
    name = f"formation/agent/{agent}/command"
    return _stream(node, run, name, wire.Command, 1, 2 + wire.SPARE_PORTS)


def command_event(node: Any, run: RunInfo) -> Any:
    """``formation/command_ready``: every robot raises it (event id = robot index)."""
    return _event(node, run, "formation/command_ready", run.n_agents)


def state_stream(node: Any, run: RunInfo) -> Any:
    """``formation/state``: the true world, every tick."""
    return _stream(node, run, "formation/state", wire.State, 0, run.shared_nodes)


def obstacles_stream(node: Any, run: RunInfo) -> Any:
    """``formation/obstacles``: each episode's obstacles, published once before its first tick
    (history 1: a late subscriber gets the current episode's at once; every robot, the critic,
    the view and spares may read; subscribers hold 2)."""
    readers = run.n_agents + 2 + wire.SPARE_PORTS
    return _stream(node, run, "formation/obstacles", wire.Obstacles, 1, run.shared_nodes, readers, 2)


def critic_wake_event(node: Any, run: RunInfo) -> Any:
    """``formation/critic/wake``: raised every half critic window and at every episode's end."""
    return _event(node, run, "formation/critic/wake", 1)


def control_service(node: Any, run: RunInfo) -> Any:
    """``formation/control``: the sim's live control service (request-response; the sim
    creates it, a client only opens it)."""
    return (
        node.service_builder(iox2.ServiceName.new("formation/control"))
        .request_response(wire.ControlRequest, wire.ControlReply)
        .open_with_attributes(run_contract(run))
    )


def control_answered_event(node: Any, run: RunInfo) -> Any:
    """``formation/control/answered``: the sim raises it after a tick that answered requests."""
    return _event(node, run, "formation/control/answered", 1)


def take_wakeups(listener: Any) -> None:
    """Consumes a listener's pending events without waiting (after a ``WaitSet`` woke up)."""
    try:
        listener.try_wait()
    except iox2.ListenerWaitError:
        pass


def connect(run_dir: Union[str, Path], timeout: Optional[float] = 60.0) -> RunInfo:
    """Reads ``<run_dir>/run.json`` of a running swarm.

    Waits up to ``timeout`` seconds (``None``: forever) for the launcher to write it, and for a
    run.json left by a finished run to be replaced by a live one. Refuses a run whose binaries
    speak another protocol version than this package.
    """
    run_dir = Path(run_dir)
    path = run_dir / "run.json"
    deadline = None if timeout is None else time.monotonic() + timeout
    stale = None
    while True:
        info = None
        try:
            raw = json.loads(path.read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            raw = None  # not there yet (the launcher renames a finished file into place)
        if raw is not None:
            if raw.get("protocol_version") != wire.PROTOCOL_VERSION:
                raise FormationError(
                    f"run {raw.get('run_id')} speaks protocol {raw.get('protocol_version')}, formation_swarm "
                    f"{wire.PROTOCOL_VERSION}: install the python/ package of the same checkout"
                )
            info = RunInfo.from_dict(run_dir, raw)
            if info.launcher_alive():
                return info
            stale = info
        if deadline is not None and time.monotonic() >= deadline:
            if stale is not None:
                raise FormationError(
                    f"{path} belongs to run {stale.run_id}, which has ended (launcher "
                    f"{stale.launcher_pid} is gone)"
                )
            raise FormationError(f"no {path} after {timeout} s: is scripts/run_swarm.sh running with --run-dir {run_dir}?")
        time.sleep(0.05)
