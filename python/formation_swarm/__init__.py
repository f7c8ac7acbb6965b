"""Python over iceoryx2 for formation-swarm: play a robot slot, or watch a run, from Python.

    import formation_swarm as fs
    fs.run_robot("runs/demo", 2, fs.Baseline())       # robot 2 of the run in runs/demo
    env = fs.FormationEnv(n=3, seed=1)                # a whole swarm as a PettingZoo ParallelEnv
    fs.Control("runs/demo").set_formation("ring")     # a new formation, live
    actor = fs.NumpyActor.from_file("models/formation.safetensors")  # a learned policy, numpy only

Built on the ``iceoryx2`` PyPI bindings (same release as the Rust crate); the payload mirrors
in ``formation_swarm.wire`` are checked against the Rust layout (``layout.json``).
"""

from .baseline import Baseline
from .control import Control, ControlAck, ControlRefused
from .observer import EpisodeObstacles, Observer, WorldState
from .policy import NumpyActor
from .robot import Robot, RobotStats, Tick, run_robot
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
    "Control",
    "ControlAck",
    "ControlRefused",
    "CriticProgress",
    "EpisodeObstacles",
    "FLAG_EPISODE_END",
    "FLAG_EPISODE_START",
    "FLAG_EVAL_EPISODE",
    "FLAG_HELLO",
    "FLAG_RUN_END",
    "FormationError",
    "Header",
    "NumpyActor",
    "Observation",
    "Observer",
    "PROTOCOL_VERSION",
    "Robot",
    "RobotStats",
    "RunInfo",
    "SimGone",
    "State",
    "Tick",
    "WeightsHeader",
    "WorldState",
    "connect",
    "run_robot",
]
__version__ = "0.1.0"


def __getattr__(name):
    # FormationEnv needs the optional pettingzoo extra: imported on first use only, so that
    # the rest of the package works without pettingzoo and gymnasium (and it is left out of
    # __all__, so that `from formation_swarm import *` does too).
    if name == "FormationEnv":
        from .env import FormationEnv

        return FormationEnv
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
