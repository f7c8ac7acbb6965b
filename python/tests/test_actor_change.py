"""scripts/actor_change.py: how far a checkpoint's actor moved from its start, and a start moved at random."""

import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "actor_change.py"


def write_file(path: Path, tensors: dict[str, np.ndarray]) -> None:
    """A float32 safetensors file of `tensors`, with metadata."""
    header, blobs, offset = {"__metadata__": {"format": "test"}}, [], 0
    for name, values in tensors.items():
        blob = values.astype(np.float32).tobytes()
        header[name] = {"dtype": "F32", "shape": list(values.shape), "data_offsets": [offset, offset + len(blob)]}
        blobs.append(blob)
        offset += len(blob)
    text = json.dumps(header).encode()
    path.write_bytes(struct.pack("<Q", len(text)) + text + b"".join(blobs))


def run(*args: str) -> str:
    return subprocess.run([sys.executable, str(SCRIPT), *args], check=True, capture_output=True, text=True).stdout


def test_a_perturbed_copy_moves_every_actor_weight_by_the_size_and_nothing_else(tmp_path):
    rng = np.random.default_rng(3)
    actor = rng.normal(size=(8, 4))
    critic = rng.normal(size=(5,))
    write_file(tmp_path / "start.safetensors", {"actor0.layer0.weight": actor, "critic0.head.bias": critic})
    run(str(tmp_path / "start.safetensors"), "--perturb", "0.01", "--seed", "2", "--out", str(tmp_path / "moved.safetensors"))
    out = run(str(tmp_path / "start.safetensors"), str(tmp_path / "moved.safetensors"))
    assert "32 actor weights, rms change 1.00e-02, largest 1.00e-02" in out, out
    # The critic is copied byte for byte: only the actor's bytes differ.
    start, moved = (tmp_path / "start.safetensors").read_bytes(), (tmp_path / "moved.safetensors").read_bytes()
    assert len(start) == len(moved)
    assert start[-critic.size * 4 :] == moved[-critic.size * 4 :]
    assert start[: -critic.size * 4] != moved[: -critic.size * 4]


def test_the_change_is_measured_against_the_start(tmp_path):
    actor = np.zeros((2, 3))
    write_file(tmp_path / "start.safetensors", {"actor0.layer0.weight": actor})
    changed = actor.copy()
    changed[0, 0] = 0.6
    write_file(tmp_path / "later.safetensors", {"actor0.layer0.weight": changed})
    out = run(str(tmp_path / "start.safetensors"), str(tmp_path / "later.safetensors"))
    # rms of one 0.6 among six weights: sqrt(0.36 / 6).
    assert f"rms change {np.sqrt(0.36 / 6):.2e}, largest 6.00e-01" in out, out
