"""ctypes mirrors of the payloads in ``protocol/src/wire.rs``.

Every class carries the same iceoryx2 type name as its Rust twin (``type_name()``), so the
bindings' service builder declares the same payload type (name, size, alignment) and the
services open across languages. ``tests/test_layout.py`` checks sizes, alignments and field
offsets against ``layout.json``, which a Rust unit test keeps equal to the build.

The observation models are not restated here: ``OBSERVATION_MODELS`` reads each one's dimension
and named blocks from ``layout.json`` (``formation_core::observation::Layout``).
"""

from __future__ import annotations

import ctypes
import dataclasses
import json
from pathlib import Path
from typing import Dict, Optional, Tuple

#: Bumped whenever a payload's layout or meaning changes (``wire::PROTOCOL_VERSION``).
PROTOCOL_VERSION = 6

#: ``Header.flags``: first tick of an episode (robots reset their history).
FLAG_EPISODE_START = 1
#: ``Header.flags``: the episode has ended at this tick; no command is expected.
FLAG_EPISODE_END = 2
#: ``Header.flags``: the run is over; every process finishes and exits.
FLAG_RUN_END = 4
#: ``Header.flags`` on a command: a greeting sent at start-up, not a command for a tick.
FLAG_HELLO = 8
#: ``Header.flags``: a train-mode episode played without exploration noise.
FLAG_EVAL_EPISODE = 16

#: ``State.outcome`` of the transition into a tick.
OUTCOME_RUNNING = 0
OUTCOME_SUCCESS = 1
OUTCOME_COLLISION = 2
OUTCOME_TIMEOUT = 3
OUTCOME_ABORTED = 4
OUTCOME_NAMES = {
    OUTCOME_RUNNING: "running",
    OUTCOME_SUCCESS: "success",
    OUTCOME_COLLISION: "collision",
    OUTCOME_TIMEOUT: "timeout",
    OUTCOME_ABORTED: "aborted",
}

#: Largest swarm the payloads have room for.
MAX_AGENTS = 64
#: Smallest swarm.
MIN_AGENTS = 3
#: Neighbours each robot observes: (i+1) mod N and (i+2) mod N.
NEIGHBOURS = 2
#: Room for the largest observation model's floats.
MAX_OBS_DIM = 32
#: Room for one episode's obstacles (``ObstaclesMsg``; a draw never makes more).
MAX_OBSTACLES = 128
#: Actions are (v, w).
ACTION_DIM = 2
#: Largest actuation delay, ticks: room for the commands queued at a robot's motors.
MAX_DELAY_TICKS = 10
#: Ports each service keeps for replacements and observers (``services::SPARE_PORTS``).
SPARE_PORTS = 4


class Header(ctypes.Structure):
    """Common to every payload: who may read it and which tick it belongs to."""

    _fields_ = [
        ("protocol_version", ctypes.c_uint32),
        ("episode", ctypes.c_uint32),
        ("tick", ctypes.c_uint32),
        ("flags", ctypes.c_uint32),
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name, as ``#[type_name]`` declares it in Rust."""
        return "formation::Header"

    @classmethod
    def new(cls, episode: int, tick: int, flags: int) -> "Header":
        """A header of this protocol version."""
        return cls(PROTOCOL_VERSION, episode, tick, flags)

    def has(self, flag: int) -> bool:
        """True when ``flag`` is set."""
        return bool(self.flags & flag)


class Observation(ctypes.Structure):
    """sim -> robot i (``ObservationMsg``): what robot i sees at a tick, in its own frame."""

    _fields_ = [
        ("header", Header),
        ("agent", ctypes.c_uint32),
        ("n_agents", ctypes.c_uint32),
        ("dim", ctypes.c_uint32),
        ("obs", ctypes.c_float * MAX_OBS_DIM),
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return "formation::Observation"


class Command(ctypes.Structure):
    """robot i -> sim (``CommandMsg``): the command for one tick."""

    _fields_ = [
        ("header", Header),
        ("agent", ctypes.c_uint32),
        ("policy_version", ctypes.c_uint32),
        ("v", ctypes.c_float),
        ("w", ctypes.c_float),
        ("session", ctypes.c_uint32),
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return "formation::Command"


class State(ctypes.Structure):
    """sim -> critic and observers (``StateMsg``): the true world at a tick."""

    _fields_ = [
        ("header", Header),
        ("n_agents", ctypes.c_uint32),
        ("outcome", ctypes.c_uint32),
        ("reward", ctypes.c_float),
        ("missed", ctypes.c_uint32),
        ("sequence", ctypes.c_uint64),
        ("observation_lost", ctypes.c_uint64),
        ("poses", (ctypes.c_float * 3) * MAX_AGENTS),
        ("applied", (ctypes.c_float * ACTION_DIM) * MAX_AGENTS),
        ("acting", (ctypes.c_float * ACTION_DIM) * MAX_AGENTS),
        ("queued", ((ctypes.c_float * ACTION_DIM) * MAX_DELAY_TICKS) * MAX_AGENTS),
        ("queued_len", ctypes.c_uint32 * MAX_AGENTS),
        ("observations", (ctypes.c_float * MAX_OBS_DIM) * MAX_AGENTS),
        ("desired", (ctypes.c_float * NEIGHBOURS) * MAX_AGENTS),
        ("slots", (ctypes.c_float * 2) * MAX_AGENTS),
        ("goal", ctypes.c_float * 2),
        ("slot", ctypes.c_uint32 * MAX_AGENTS),
        ("present", ctypes.c_uint64),
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return "formation::State"


class CriticProgress(ctypes.Structure):
    """critic -> sim (``CriticProgressMsg``): train-mode flow control."""

    _fields_ = [
        ("protocol_version", ctypes.c_uint32),
        ("weights_version", ctypes.c_uint32),
        ("acknowledged_sequence", ctypes.c_uint64),
        ("updates", ctypes.c_uint64),
        ("session", ctypes.c_uint64),
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return "formation::CriticProgress"


class WeightsHeader(ctypes.Structure):
    """critic -> robots: the user header in front of one actor's flat ``[f32]`` weights."""

    _fields_ = [
        ("protocol_version", ctypes.c_uint32),
        ("actor_index", ctypes.c_uint32),
        ("version", ctypes.c_uint32),
        ("len", ctypes.c_uint32),
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return "formation::WeightsHeader"


#: ``Obstacles.shapes``: a disc, ``values`` = centre x, centre y, radius, 0, 0.
OBSTACLE_DISC = 1
#: ``Obstacles.shapes``: a wall, ``values`` = a.x, a.y, b.x, b.y, thickness (a rectangle whose
#: centre line runs from a to b, flat ends).
OBSTACLE_WALL = 2
#: ``Obstacles.kind``: the kind an episode drew (``[obstacles] kind``; ``mixed`` draws one of the
#: three per episode).
OBSTACLE_KIND_NAMES = {0: "none", 1: "forest", 2: "passage", 3: "trap"}


class Obstacles(ctypes.Structure):
    """sim -> robots, critic and observers (``ObstaclesMsg``, ``formation/obstacles``), once per
    episode before its first tick: the episode's obstacles, world frame, metres (``count`` 0 in
    an open episode)."""

    _fields_ = [
        ("header", Header),
        ("count", ctypes.c_uint32),
        ("kind", ctypes.c_uint32),
        ("time_limit", ctypes.c_uint32),
        ("shapes", ctypes.c_uint32 * MAX_OBSTACLES),
        ("values", (ctypes.c_double * 5) * MAX_OBSTACLES),
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return "formation::Obstacles"


class Truth(ctypes.Structure):
    """sim -> privileged planners and observers (``TruthMsg``, ``formation/truth``), every tick
    before the observations: the true poses and the formation in force."""

    _fields_ = [
        ("header", Header),
        ("n_agents", ctypes.c_uint32),
        ("present", ctypes.c_uint64),
        ("poses", (ctypes.c_float * 3) * MAX_AGENTS),
        ("slots", (ctypes.c_float * 2) * MAX_AGENTS),
        ("goal", ctypes.c_float * 2),
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return "formation::Truth"


#: ``ControlRequest.kind``: a new formation (``shape``, ``scale``, ``orientation``).
CONTROL_SET_FORMATION = 1
#: ``ControlRequest.kind``: a new goal.
CONTROL_SET_GOAL = 2
#: ``ControlRequest.kind``: take robot ``robot`` out of the formation.
CONTROL_REMOVE_ROBOT = 3
#: ``ControlRequest.kind``: bring robot ``robot``, removed earlier, back.
CONTROL_RESTORE_ROBOT = 4
#: ``State.slot`` of a robot out of the formation.
SLOT_NONE = 0xFFFFFFFF
#: ``ControlReply.status``: in force from ``ControlReply.tick``.
CONTROL_OK = 0
#: ``ControlReply.status``: refused; ``ControlReply.message`` says why.
CONTROL_REFUSED = 1


class ControlRequest(ctypes.Structure):
    """client -> sim (request-response ``formation/control``): a live change to the episode."""

    _fields_ = [
        ("protocol_version", ctypes.c_uint32),
        ("kind", ctypes.c_uint32),
        ("shape", ctypes.c_uint8 * 16),
        ("scale", ctypes.c_float),
        ("orientation", ctypes.c_float),
        ("goal", ctypes.c_float * 2),
        ("robot", ctypes.c_uint32),
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return "formation::ControlRequest"


class ControlReply(ctypes.Structure):
    """sim -> client: the answer to a ``ControlRequest``."""

    _fields_ = [
        ("protocol_version", ctypes.c_uint32),
        ("status", ctypes.c_uint32),
        ("episode", ctypes.c_uint32),
        ("tick", ctypes.c_uint32),
        ("message", ctypes.c_uint8 * 120),
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return "formation::ControlReply"


#: Every mirror, by its Rust struct name (the ``rust`` key of ``layout.json``).
PAYLOADS = {
    "Header": Header,
    "ObservationMsg": Observation,
    "CommandMsg": Command,
    "StateMsg": State,
    "ObstaclesMsg": Obstacles,
    "TruthMsg": Truth,
    "CriticProgressMsg": CriticProgress,
    "WeightsHeader": WeightsHeader,
    "ControlRequest": ControlRequest,
    "ControlReply": ControlReply,
}


@dataclasses.dataclass(frozen=True)
class ObservationLayout:
    """One observation model as ``layout.json`` lists it: its name, its floats, and each block
    (``neighbour_0``, ``neighbour_1``, ``goal``, ``slot``, ``proximity``, ``scan``) with its first
    float and the names of its floats."""

    name: str
    dim: int
    blocks: Dict[str, Tuple[int, Tuple[str, ...]]]

    def index(self, block: str, field: str = "x") -> Optional[int]:
        """Where ``field`` of ``block`` sits in an observation (``index("neighbour_1",
        "desired")``), or None when this model has no such block."""
        if block not in self.blocks:
            return None
        offset, fields = self.blocks[block]
        return offset + fields.index(field)

    def span(self, block: str) -> Optional[slice]:
        """The floats of ``block`` as a slice of an observation (``obs[layout.span("scan")]``:
        the range sensor's rays), or None when this model has no such block."""
        if block not in self.blocks:
            return None
        offset, fields = self.blocks[block]
        return slice(offset, offset + len(fields))


def _observation_models() -> Dict[str, ObservationLayout]:
    raw = json.loads((Path(__file__).parent / "layout.json").read_text())
    return {
        model["name"]: ObservationLayout(
            name=model["name"],
            dim=int(model["dim"]),
            blocks={b["name"]: (int(b["offset"]), tuple(b["fields"])) for b in model["blocks"]},
        )
        for model in raw["observation_models"]
    }


#: Every observation model by name (``env.observation``), read from ``layout.json``.
OBSERVATION_MODELS: Dict[str, ObservationLayout] = _observation_models()


def observation_layout(dim: int) -> ObservationLayout:
    """The observation model whose observations have ``dim`` floats (each model's is its own)."""
    for model in OBSERVATION_MODELS.values():
        if model.dim == dim:
            return model
    dims = sorted(m.dim for m in OBSERVATION_MODELS.values())
    raise ValueError(f"no observation model has {dim} floats (layout.json has {dims})")
