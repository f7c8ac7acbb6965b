"""Python over iceoryx2 for formation-swarm: play a robot slot, or watch a run, from Python.

    import formation_swarm as fs
    fs.run_robot("runs/demo", 2, fs.Baseline())       # robot 2 of the run in runs/demo

Built on the ``iceoryx2`` PyPI bindings (same release as the Rust crate); the payload mirrors
in ``formation_swarm.wire`` are checked against the Rust layout (``layout.json``).
"""

from .baseline import Baseline
from .observer import Observer, WorldState
from .robot import Robot, RobotStats, run_robot
from .run import FormationError, RunInfo, SimGone, connect
from .wire import (
    FLAG_EPISODE_END,
    FLAG_EPISODE_START,
    FLAG_EVAL_EPISODE,
    FLAG_HELLO,
    FLAG_RUN_END,
    PROTOCOL_VERSION,
    Command,
    CriticProgress,
    Header,
    Observation,
    State,
    WeightsHeader,
)

__all__ = [
    "Baseline",
    "Command",
    "CriticProgress",
    "FLAG_EPISODE_END",
    "FLAG_EPISODE_START",
    "FLAG_EVAL_EPISODE",
    "FLAG_HELLO",
    "FLAG_RUN_END",
    "FormationError",
    "Header",
    "Observation",
    "Observer",
    "PROTOCOL_VERSION",
    "Robot",
    "RobotStats",
    "RunInfo",
    "SimGone",
    "State",
    "WeightsHeader",
    "WorldState",
    "connect",
    "run_robot",
]
__version__ = "0.1.0"
