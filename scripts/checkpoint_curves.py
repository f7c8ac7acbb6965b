#!/usr/bin/env python3
"""Learning curves computed afterwards from the checkpoints a training run kept.

A run with `learn.keep_checkpoints = true` keeps every checkpoint as
RUN/checkpoints/updates-<U>.safetensors. This plays each of them with formation-play on episodes
no training run used (default: seed 1000, the held-out seeds) under the run's own config
(RUN/config.toml: observation model, obstacles, reward), and plots success against gradient
updates, one line per run, beside the selection score the run measured live (training.csv).

  scripts/checkpoint_curves.py runs/forest/rl-long-s1 runs/forest/rl-long-s2 --n 4 --episodes 50 \\
      --out docs/forest_learning_curves.png
  scripts/checkpoint_curves.py runs/detour/line/rl-s1 --n 8,16 --obstacles trap --out runs/trap-curves.png

Writes OUT (a PNG) and OUT with .json (every point), and prints a Markdown table.
formation-play comes from $FORMATION_BIN_DIR (default target/debug).

--pick FILE applies the selection rule before any held-out play and copies its choice to FILE:
of every kept checkpoint of the runs on which the actor had stepped (past
`learn.critic_warmup_updates`: the ones before it hold the run's start), the best selection
score (success over the selection episodes, then mean success over the sizes, then fewer steps;
the trainer's `best.safetensors` rule).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import re
import shutil
import struct
import subprocess
import tomllib
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def play(bin_dir: str, run: Path, checkpoint: Path, n: str, episodes: int, seed: int,
         obstacles: str | None = None) -> dict[int, dict]:
    cmd = [str(Path(bin_dir) / "formation-play"), "--team", "model", "--checkpoint", str(checkpoint),
           "--config", str(run / "config.toml"), "--n", n, "--episodes", str(episodes), "--seed", str(seed)]
    if obstacles:
        cmd += ["--obstacles", obstacles]
    out = subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.PIPE, text=True).stdout
    return {line["n"]: line for line in (json.loads(l) for l in out.splitlines() if l.startswith("{"))}


def metadata(path: Path) -> dict[str, str]:
    """A safetensors file's string metadata."""
    with path.open("rb") as f:
        (length,) = struct.unpack("<Q", f.read(8))
        return json.loads(f.read(length)).get("__metadata__", {})


def pick(runs: list[Path]) -> Path:
    """The selection rule over the kept checkpoints on which the actor had stepped."""
    candidates = []
    for run in runs:
        warmup = tomllib.loads((run / "config.toml").read_text()).get("learn", {}).get("critic_warmup_updates", 0)
        for checkpoint in sorted((run / "checkpoints").glob("updates-*.safetensors")):
            meta = metadata(checkpoint)
            stepped = int(meta["run_actor_steps"]) > 0 if "run_actor_steps" in meta else int(meta["updates"]) > warmup
            if stepped and "selection_success" in meta:
                sizes = [float(size.split(":")[1]) for size in meta["selection_by_size"].split(",")]
                key = (float(meta["selection_success"]), sum(sizes) / len(sizes), -float(meta["selection_mean_steps"]))
                candidates.append((key, str(checkpoint)))
    if not candidates:
        sys.exit("checkpoint_curves.py --pick: no kept checkpoint on which the actor had stepped")
    key, best = max(candidates)
    print(f"picked {best}: selection success {key[0]:.3f} (of {len(candidates)} candidates)", file=sys.stderr)
    return Path(best)


def selection_curve(run: Path) -> list[tuple[int, float]]:
    """(updates, selection success) at every checkpoint the run scored live."""
    path = run / "training.csv"
    if not path.is_file():
        return []
    with path.open() as f:
        rows = [r for r in csv.DictReader(f) if r.get("selection_success")]
    points: dict[int, float] = {}
    for row in rows:
        points[int(row["updates"])] = float(row["selection_success"])
    return sorted(points.items())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="training run directories")
    parser.add_argument("--n", default="4", help="swarm sizes, comma-separated")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    parser.add_argument("--bin-dir", default=os.environ.get("FORMATION_BIN_DIR", "target/debug"))
    parser.add_argument("--pick", type=Path, help="copy the selection rule's choice here before any held-out play")
    parser.add_argument("--obstacles", choices=("none", "forest", "passage", "trap", "mixed"),
                        help="play among these obstacles instead of the run's own (e.g. one kind of a mixed run)")
    parser.add_argument("--every", type=int, default=1,
                        help="play every K-th kept checkpoint of a run (its last always), to save time")
    args = parser.parse_args()
    if args.every < 1:
        parser.error(f"--every must be at least 1, not {args.every}")
    if args.pick:
        chosen = pick(args.runs)
        args.pick.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(chosen, args.pick)
        print(f"copied {chosen} to {args.pick}", file=sys.stderr)
    curves = {}
    for run in args.runs:
        kept = sorted((run / "checkpoints").glob("updates-*.safetensors"))
        if not kept:
            parser.error(f"{run}: no kept checkpoints (train with learn.keep_checkpoints = true)")
        kept = [c for k, c in enumerate(kept) if k % args.every == 0 or k == len(kept) - 1]
        points = []
        for k, checkpoint in enumerate(kept):
            updates = int(re.search(r"updates-(\d+)", checkpoint.name).group(1))
            lines = play(args.bin_dir, run, checkpoint, args.n, args.episodes, args.seed, args.obstacles)
            points.append({"updates": updates, "by_n": {str(n): line for n, line in lines.items()}})
            print(f"{run.name}: {k + 1}/{len(kept)} checkpoints played", file=sys.stderr, flush=True)
        curves[str(run)] = {"held_out": points, "selection": selection_curve(run)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(
        {"n": args.n, "episodes": args.episodes, "seed": args.seed, "obstacles": args.obstacles, "runs": curves},
        indent=1) + "\n")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ns = args.n.split(",")
    fig, axes = plt.subplots(1, len(ns), figsize=(6 * len(ns), 4), squeeze=False)
    for ax, n in zip(axes[0], ns):
        for k, (run, curve) in enumerate(curves.items()):
            colour = f"C{k}"
            xs = [p["updates"] for p in curve["held_out"]]
            ax.plot(xs, [p["by_n"][n]["success"] for p in curve["held_out"]], "-o", color=colour, ms=3,
                    label=f"{Path(run).name}: held-out (seed {args.seed}, {args.episodes} eps)")
            if len(ns) == 1 and curve["selection"]:
                sx, sy = zip(*curve["selection"])
                ax.plot(sx, sy, ":", color=colour, label=f"{Path(run).name}: selection (live)")
        ax.set_xlabel("gradient updates")
        ax.set_ylabel("success")
        ax.set_ylim(-0.02, 1.02)
        ax.set_title(f"N = {n}" + (f", {args.obstacles}" if args.obstacles else ""))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print("| run | updates | " + " | ".join(f"success N={n}" for n in ns) + " |")
    print("|---|---|" + "---|" * len(ns))
    for run, curve in curves.items():
        for p in curve["held_out"]:
            print(f"| {Path(run).name} | {p['updates']} | "
                  + " | ".join(f"{p['by_n'][n]['success']:.2f}" for n in ns) + " |")


if __name__ == "__main__":
    main()
