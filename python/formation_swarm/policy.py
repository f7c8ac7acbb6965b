"""A learned actor in numpy: a safetensors checkpoint of this project (``format = formation-rl/1``,
``models/``) read without candle, torch or the ``safetensors`` package, played as the Rust agent
plays it (``model/src/actor.rs``, ``model/src/history.rs``, ``agent/src/run.rs``).

    actor = NumpyActor.from_file("models/formation.safetensors")
    actor.reset()                 # an episode starts: the next observation fills the window
    v, w = actor(obs)             # one observation of the checkpoint's model -> the command

* The network: an MLP over the window of the last H observations, oldest first, flattened;
  ReLU hidden layers, tanh outputs (f32, as the agents compute it).
* The window (``ObservationHistory``): at an episode's first observation every one of its H
  slots holds that observation; each later one drops the oldest and is appended.
* The head: a **command** head's two outputs a are the normalised command,
  ``v = (a0 + 1) / 2 v_max``, ``w = a1 w_max`` (``EnvConfig::command_from_action``); a **gains**
  head's five outputs are the baseline's gains, each log-uniform over its range
  (``BaselineGains::from_unit``), and the baseline's law with them turns the newest observation
  into (v, w) (``formation_swarm.Baseline``).

``formation_swarm.Robot`` (``python -m formation_swarm robot RUN_DIR I --policy FILE``) and
``formation_swarm.ros2.Ros2Node`` (``ros2-node I --policy FILE``) reset it at each episode.
``python/tests/test_policy.py`` checks the outputs and commands against golden values the Rust
agent's code wrote (``model/tests/actor_golden.rs``)."""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Union

from . import wire
from .baseline import Baseline
from .run import FormationError

#: The ``format`` metadata of this project's checkpoints.
FORMAT = "formation-rl/1"
#: The range of each gain a gains head outputs, log-uniformly from -1 to 1, in the order
#: k_form, k_goal, k_turn, repulsion_range, k_repulsion (``SCHEDULED_GAIN_RANGES``).
SCHEDULED_GAIN_RANGES = ((0.2, 4.0), (0.25, 1.6), (0.5, 5.0), (0.25, 1.0), (0.5, 6.0))
GAIN_NAMES = ("k_form", "k_goal", "k_turn", "repulsion_range", "k_repulsion")
HEADS = {"command": 2, "gains": len(SCHEDULED_GAIN_RANGES)}
#: The observation width of files written before the metadata named their observation model.
_PAPER_OBS_DIM = 12
_MAX_HEADER = 100 * 1024 * 1024


def read_safetensors(path: Union[str, Path]) -> Tuple[Dict[str, str], Dict[str, "object"]]:
    """(metadata, tensors by name) of a safetensors file of little-endian f32 tensors: 8 bytes of
    header length (little-endian u64), the JSON header (each tensor's dtype, shape and
    data_offsets into the bytes after it; ``__metadata__`` the string pairs), then the data."""
    import numpy as np

    path = Path(path)
    if not path.is_file():
        raise FormationError(f"checkpoint {path} does not exist" if not path.exists()
                             else f"checkpoint {path} is not a file")
    data = path.read_bytes()
    if len(data) < 8:
        raise FormationError(f"checkpoint {path} is not a safetensors file: {len(data)} bytes")
    (length,) = struct.unpack("<Q", data[:8])
    if length > min(len(data) - 8, _MAX_HEADER):
        raise FormationError(f"checkpoint {path} is not a safetensors file: a header of {length} bytes "
                             f"in a file of {len(data)}")
    try:
        header = json.loads(data[8:8 + length].decode("utf-8"))
        if not isinstance(header, dict):
            raise ValueError("the header is not a JSON object")
    except (UnicodeDecodeError, ValueError) as err:
        raise FormationError(f"checkpoint {path} is not a safetensors file: {err}") from None
    metadata = header.pop("__metadata__", None) or {}
    body = memoryview(data)[8 + length:]
    tensors = {}
    for name, info in header.items():
        try:
            dtype, shape, (start, end) = info["dtype"], [int(s) for s in info["shape"]], info["data_offsets"]
        except (KeyError, TypeError, ValueError):
            raise FormationError(f"checkpoint {path} is not a safetensors file: tensor {name!r} is "
                                 f"described as {info!r}") from None
        if dtype != "F32":
            raise FormationError(f"checkpoint {path}: tensor {name} is {dtype}, expected F32")
        count = math.prod(shape)
        if not (0 <= start <= end <= len(body)) or end - start != 4 * count:
            raise FormationError(f"checkpoint {path} is corrupted: tensor {name} of shape {shape} spans bytes "
                                 f"{start}..{end} of {len(body)}")
        tensors[name] = np.frombuffer(body[start:end], dtype="<f4").reshape(shape).astype(np.float32)
    return dict(metadata), tensors


class NumpyActor:
    """``actor(obs) -> (v, w)`` for one robot, with its window of observations; ``reset()`` at
    each episode start. ``v_max``, ``w_max`` (the run's ``env``) scale a command head's outputs;
    they, ``proximity_range`` (``env.proximity_range_m``), ``scan_range`` (``env.scan_range_m``)
    and ``robot_radius`` (half ``env.eps_coll_m``) are the baseline's for a gains head. The
    defaults are the Rust defaults.

    Attributes: ``observation`` (the model's name), ``obs_dim``, ``history`` (H), ``hidden``,
    ``head`` (``command`` or ``gains``), ``metadata`` (every string pair of the file)."""

    def __init__(self, metadata: Dict[str, str], layers: List[Tuple["object", "object"]], path: str = "<memory>",
                 v_max: float = 0.5, w_max: float = 1.0, proximity_range: float = 1.0, scan_range: float = 2.0,
                 robot_radius: float = 0.1) -> None:
        import numpy as np

        self.path, self.metadata = path, dict(metadata)
        self.observation, self.obs_dim, self.history, self.hidden, self.head = _shape(metadata, path)
        self.layers = [(np.asarray(w, dtype=np.float32), np.asarray(b, dtype=np.float32)) for w, b in layers]
        expected = _layer_dims(self.obs_dim * self.history, self.hidden, HEADS[self.head])
        got = [(w.shape[1] if w.ndim == 2 else None, w.shape[0]) for w, _ in self.layers]
        if got != expected or any(b.shape != (out,) for (_, b), (_, out) in zip(self.layers, expected)):
            raise FormationError(f"checkpoint {path}: layers of (inputs, outputs) {got}, its metadata asks "
                                 f"for {expected}")
        self.v_max, self.w_max = v_max, w_max
        self._baseline_limits = dict(v_max=v_max, w_max=w_max, proximity_range=proximity_range,
                                     scan_range=scan_range, robot_radius=robot_radius)
        self._window = np.zeros((self.history, self.obs_dim), dtype=np.float32)
        self._fresh = True

    @classmethod
    def from_file(cls, path: Union[str, Path], agent: int = 0, **limits: float) -> "NumpyActor":
        """The actor robot ``agent`` uses in the checkpoint at ``path`` (the shared one when the
        file holds one, as every file in ``models/`` does). ``limits``: ``v_max``, ``w_max``,
        ``proximity_range``, ``scan_range``, ``robot_radius``. Refuses (``FormationError``, with
        the reason) a missing file, a file that is not a safetensors checkpoint of this project,
        one whose tensors do not make the actor its metadata describes."""
        metadata, tensors = read_safetensors(path)
        if metadata.get("format") != FORMAT:
            raise FormationError(f"{path} is not a formation checkpoint: its metadata has format "
                                 f"{metadata.get('format')!r}, expected {FORMAT!r}")
        n_actors = _number(metadata, "n_actors", path)
        index = 0 if n_actors == 1 else agent
        if not 0 <= index < n_actors:
            raise FormationError(f"checkpoint {path} holds {n_actors} independent actors; robot {agent} has none")
        observation, obs_dim, history, hidden, head = _shape(metadata, path)
        layers = []
        for i in range(len(hidden) + 1):
            names = [f"actor{index}.layer{i}.weight", f"actor{index}.layer{i}.bias"]
            missing = [n for n in names if n not in tensors]
            if missing:
                raise FormationError(f"checkpoint {path}: missing actor parameter {missing[0]}")
            layers.append((tensors[names[0]], tensors[names[1]]))
        for name, tensor in tensors.items():
            if name.startswith(f"actor{index}.") and not _finite(tensor):
                raise FormationError(f"checkpoint {path}: tensor {name} holds non-finite values")
        return cls(metadata, layers, str(path), **limits)

    # --- the observation model ------------------------------------------------------------

    def check_observation(self, model: Optional[str], dim: int) -> None:
        """Refuses (``FormationError``) observations of another model than the checkpoint's:
        ``model`` the run's model name (None: unknown, the width alone decides), ``dim`` its
        floats."""
        if (model is not None and model != self.observation) or dim != self.obs_dim:
            told = f"{model!r} ({dim} floats)" if model is not None else f"{dim} floats"
            raise FormationError(
                f"checkpoint {self.path} was trained on the {self.observation!r} observation ({self.obs_dim} floats), "
                f"but this run observes {told}: use a checkpoint trained on that observation, or run the swarm "
                f"with env.observation = {self.observation!r}")

    # --- the window -----------------------------------------------------------------------

    def reset(self, episode: Optional[int] = None, explore: Optional[bool] = None) -> None:
        """An episode starts: the next observation fills every slot of the window. (The
        arguments, which ``formation_swarm.Robot`` passes, are not needed.)"""
        self._fresh = True

    def observe(self, obs: Sequence[float]) -> None:
        """Puts ``obs`` into the window (every slot after :meth:`reset`, else the newest slot)
        without acting: an observation that was superseded before it was answered."""
        import numpy as np

        obs = np.asarray(obs, dtype=np.float32).reshape(-1)
        if obs.shape[0] != self.obs_dim:
            self.check_observation(None, obs.shape[0])
        if self._fresh:
            self._window[:] = obs
            self._fresh = False
        else:
            self._window[:-1] = self._window[1:]
            self._window[-1] = obs

    @property
    def window(self):
        """The window, oldest first, flattened (H x obs_dim floats)."""
        return self._window.reshape(-1).copy()

    def __call__(self, obs: Sequence[float]) -> Tuple[float, float]:
        """The command (v, w) for ``obs``, the robot's newest observation, with the window."""
        self.observe(obs)
        return self.command(self._window.reshape(-1))

    # --- the network ----------------------------------------------------------------------

    def outputs(self, window: Sequence[float]):
        """The network's outputs in [-1, 1] (float32) for one flattened window."""
        import numpy as np

        x = np.asarray(window, dtype=np.float32).reshape(-1)
        if x.shape[0] != self.obs_dim * self.history:
            raise FormationError(f"a window of {x.shape[0]} values, the actor takes {self.obs_dim * self.history}")
        last = len(self.layers) - 1
        for i, (weight, bias) in enumerate(self.layers):
            x = weight @ x + bias
            x = np.maximum(x, np.float32(0.0)) if i < last else np.tanh(x)
        return x

    def gains(self, outputs: Sequence[float]) -> Dict[str, float]:
        """A gains head's outputs as the baseline's gains (``BaselineGains::from_unit``)."""
        gains = {}
        for name, u, (lo, hi) in zip(GAIN_NAMES, outputs, SCHEDULED_GAIN_RANGES):
            t = (min(max(float(u), -1.0), 1.0) + 1.0) / 2.0
            gains[name] = lo * (hi / lo) ** t
        return gains

    def command(self, window: Sequence[float]) -> Tuple[float, float]:
        """(v, w) for one flattened window (newest observation last), as the head makes it."""
        import numpy as np

        outputs = self.outputs(window)
        if self.head == "command":
            a0, a1 = (min(max(float(a), -1.0), 1.0) for a in outputs[:2])
            return (a0 + 1.0) * 0.5 * self.v_max, a1 * self.w_max
        newest = np.asarray(window, dtype=np.float32).reshape(-1)[-self.obs_dim:]
        return Baseline(**self._baseline_limits, **self.gains(outputs))(newest)

    def __repr__(self) -> str:
        return (f"NumpyActor({self.path!r}: {self.head} head, {self.observation!r} x H = {self.history}, "
                f"hidden {self.hidden})")


def _number(metadata: Dict[str, str], key: str, path) -> int:
    if key not in metadata:
        raise FormationError(f"checkpoint {path} has no metadata field {key!r}")
    try:
        return int(metadata[key])
    except ValueError:
        raise FormationError(f"checkpoint {path}: metadata {key} is not a number: {metadata[key]!r}") from None


def _shape(metadata: Dict[str, str], path) -> Tuple[str, int, int, List[int], str]:
    """(observation model, obs_dim, H, hidden widths, head) from a checkpoint's metadata, with
    the defaults of files from before each key existed (``CheckpointMeta::from_map``)."""
    observation = metadata.get("observation", "paper")
    if observation not in wire.OBSERVATION_MODELS:
        raise FormationError(f"checkpoint {path}: unknown observation model {observation!r} "
                             f"(layout.json has {sorted(wire.OBSERVATION_MODELS)})")
    obs_dim = _number(metadata, "obs_dim", path) if "obs_dim" in metadata else _PAPER_OBS_DIM
    if obs_dim != wire.OBSERVATION_MODELS[observation].dim:
        raise FormationError(f"checkpoint {path}: obs_dim {obs_dim}, but {observation!r} has "
                             f"{wire.OBSERVATION_MODELS[observation].dim} floats")
    history = _number(metadata, "history", path)
    if history < 1:
        raise FormationError(f"checkpoint {path}: history {history}")
    try:
        hidden = [int(w) for w in json.loads(metadata.get("actor_hidden", "null"))]
    except (TypeError, ValueError):
        raise FormationError(f"checkpoint {path}: metadata actor_hidden is not a list: "
                             f"{metadata.get('actor_hidden')!r}") from None
    head = metadata.get("actor_head", "command")
    if head not in HEADS:
        raise FormationError(f"checkpoint {path}: unknown actor head {head!r}")
    return observation, obs_dim, history, hidden, head


def _layer_dims(inputs: int, hidden: List[int], outputs: int) -> List[Tuple[int, int]]:
    dims = []
    for width in hidden:
        dims.append((inputs, width))
        inputs = width
    return dims + [(inputs, outputs)]


def _finite(tensor) -> bool:
    import numpy as np

    return bool(np.isfinite(tensor).all())
