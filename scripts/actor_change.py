#!/usr/bin/env python3
"""How far an RL stage moved the actor from its start, or a start moved at random by as much.

  scripts/actor_change.py START.safetensors CHECKPOINT.safetensors...
      prints, for each checkpoint, the rms and largest change of its actor weights (tensors named
      actor*) against START's, beside the rms of START's actor weights
  scripts/actor_change.py START.safetensors --perturb 1e-4 --seed 1 --out OUT.safetensors
      writes a copy of START with every actor weight moved by +-SIZE, each sign drawn at random:
      the size of one Adam step at that learning rate, without a critic (docs/RESULTS.md,
      "A sharper target, and how far one actor step moves the policy")

Reads and writes float32 safetensors files with numpy alone; everything else in the file is
copied byte for byte.
"""
from __future__ import annotations

import argparse
import json
import struct
import sys
from pathlib import Path

import numpy as np


def read(path: Path) -> tuple[bytearray, int, dict]:
    """The file's bytes, where its data starts, and its header."""
    data = bytearray(path.read_bytes())
    (length,) = struct.unpack("<Q", data[:8])
    return data, 8 + length, json.loads(data[8 : 8 + length])


def actor_tensors(data: bytearray, base: int, header: dict) -> dict[str, tuple[int, int]]:
    """Byte ranges of the float32 actor tensors."""
    ranges = {}
    for name, entry in header.items():
        if name == "__metadata__" or not name.startswith("actor"):
            continue
        if entry["dtype"] != "F32":
            sys.exit(f"actor_change.py: {name} is {entry['dtype']}, not F32")
        begin, end = entry["data_offsets"]
        ranges[name] = (base + begin, base + end)
    if not ranges:
        sys.exit("actor_change.py: no actor tensors in the file")
    return ranges


def weights(data: bytearray, ranges: dict[str, tuple[int, int]]) -> dict[str, np.ndarray]:
    return {name: np.frombuffer(bytes(data[a:b]), dtype=np.float32).copy() for name, (a, b) in ranges.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("start", type=Path)
    parser.add_argument("checkpoints", type=Path, nargs="*")
    parser.add_argument("--perturb", type=float, help="move every actor weight of START by +-this")
    parser.add_argument("--seed", type=int, default=1, help="seeds the signs of --perturb")
    parser.add_argument("--out", type=Path, help="where --perturb writes its copy")
    args = parser.parse_args()
    data, base, header = read(args.start)
    ranges = actor_tensors(data, base, header)
    start = weights(data, ranges)
    if args.perturb is not None:
        if args.out is None or args.checkpoints:
            sys.exit("actor_change.py: --perturb needs --out and no checkpoints")
        if args.out.exists():
            sys.exit(f"actor_change.py: {args.out} exists")
        rng = np.random.default_rng(args.seed)
        for name, (a, b) in ranges.items():
            moved = start[name] + np.float32(args.perturb) * rng.choice([-1.0, 1.0], size=start[name].size).astype(np.float32)
            data[a:b] = moved.tobytes()
        args.out.write_bytes(bytes(data))
        print(f"{args.out}: {sum(w.size for w in start.values())} actor weights moved by +-{args.perturb}")
        return
    if not args.checkpoints:
        sys.exit("actor_change.py: give checkpoints to compare, or --perturb")
    flat_start = np.concatenate(list(start.values()))
    for path in args.checkpoints:
        other_data, other_base, other_header = read(path)
        other = weights(other_data, actor_tensors(other_data, other_base, other_header))
        if other.keys() != start.keys() or any(other[k].size != start[k].size for k in start):
            sys.exit(f"actor_change.py: {path}'s actor is not shaped as {args.start}'s")
        change = np.concatenate([other[k] - start[k] for k in start])
        print(
            f"{path}: {change.size} actor weights, rms change {np.sqrt(np.mean(change**2)):.2e}, "
            f"largest {np.max(np.abs(change)):.2e}, rms weight {np.sqrt(np.mean(flat_start**2)):.2e}"
        )


if __name__ == "__main__":
    main()
