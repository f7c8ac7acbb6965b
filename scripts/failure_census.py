#!/usr/bin/env python3
"""Why a team fails among obstacles: plays the episodes with `formation-play`, traces every
failed one and sorts it into one cause, printed as a Markdown table (one row a swarm size).

    scripts/failure_census.py --team model --obstacles forest --n 4,8,16 --seed 1000
    scripts/failure_census.py --team scripted --config configs/obstacles-detouring.toml \\
        --obstacles passage --n 8 --episodes 50 --seed 7000

The causes (each failed episode gets the first that fits):
  hit an obstacle   the episode ended on a robot touching an obstacle;
  robots collided   it ended on two robots touching;
  stalled           a timeout with a robot more than FAR m from its slot that moved less than
                    0.3 m over the last STILL ticks within NEAR m of an obstacle's surface (the
                    deterministic actor at a fixed point: it neither drives nor turns away);
  on its way        a timeout with a robot more than FAR m from its slot, none stalled (slow);
  at the goal       a timeout with every robot within FAR m of its slot, out of formation.
Robots, slots and obstacles come from `formation-play --trace-episode` (OUT/trace-n<N>-e<K>.json);
formation-play from $FORMATION_BIN_DIR (default target/debug). --json writes each episode's cause.
"""
import argparse
import csv
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CAUSES = ["hit an obstacle", "robots collided", "stalled", "on its way", "at the goal"]


def surface_distance(point, obstacle):
    """Distance from `point` to an obstacle's surface (a disc or a wall of some thickness)."""
    if "disc" in obstacle:
        disc = obstacle["disc"]
        return math.dist(point, disc["centre"]) - disc["radius"]
    wall = obstacle["wall"]
    (ax, ay), (bx, by) = wall["a"], wall["b"]
    dx, dy = bx - ax, by - ay
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0 else max(0.0, min(1.0, ((point[0] - ax) * dx + (point[1] - ay) * dy) / length2))
    return math.dist(point, (ax + t * dx, ay + t * dy)) - wall["thickness"] / 2


def cause_of(row, trace, far, near, still):
    """The cause of one failed episode (`row` its CSV row, `trace` its trajectories)."""
    if row["outcome"] == "collision":
        return "hit an obstacle" if int(row["obstacle_collisions"]) > 0 else "robots collided"
    poses, goal, slots = trace["poses"], trace["goal"], trace["slots"]
    last = poses[-1]
    away = [i for i, slot in enumerate(slots)
            if math.dist(last[i][:2], (goal[0] + slot[0], goal[1] + slot[1])) > far]
    if not away:
        return "at the goal"
    back = poses[max(0, len(poses) - 1 - still)]
    for i in away:
        moved = max(math.dist(tick[i][:2], last[i][:2]) for tick in poses[len(poses) - 1 - still:])
        if len(poses) > still and moved < 0.3 and math.dist(back[i][:2], last[i][:2]) < 0.3 and any(
                surface_distance(last[i][:2], o) < near for o in trace["obstacles"]):
            return "stalled"
    return "on its way"


def play(args, n, out, trace=()):
    binary = Path(os.environ.get("FORMATION_BIN_DIR") or ROOT / "target" / "debug") / "formation-play"
    if not binary.exists():
        sys.exit(f"failure_census.py: {binary} is missing: run `cargo build --bins` or set FORMATION_BIN_DIR")
    cmd = [str(binary), "--team", args.team, "--obstacles", args.obstacles, "--n", str(n),
           "--episodes", str(args.episodes), "--seed", str(args.seed), "--out", str(out)]
    for flag in ("config", "checkpoint", "reality"):
        if getattr(args, flag):
            cmd += [f"--{flag}", getattr(args, flag)]
    if trace:
        cmd += ["--trace-episode", ",".join(map(str, trace))]
    result = subprocess.run(cmd, capture_output=True, text=True)
    if result.returncode != 0:
        sys.exit(f"failure_census.py: {' '.join(cmd)} failed:\n{result.stderr.strip()}")
    with open(out / f"n{n}.csv", newline="") as f:
        return list(csv.DictReader(f))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--team", default="model", choices=["model", "scripted", "oracle", "solo", "solo-local"])
    parser.add_argument("--checkpoint", help="the model's file (default: the shipped model of the world)")
    parser.add_argument("--config", default=str(ROOT / "configs" / "obstacles-detouring.toml"))
    parser.add_argument("--reality", help="a [reality] preset, e.g. configs/reality-field-ranging.toml")
    parser.add_argument("--obstacles", default="forest", choices=["forest", "passage", "trap", "mixed"])
    parser.add_argument("--n", default="4,8,16", help="swarm sizes, comma-separated")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--far", type=float, default=1.0, help="metres from its slot a robot counts as away")
    parser.add_argument("--near", type=float, default=0.5, help="metres from an obstacle a stalled robot stands")
    parser.add_argument("--still", type=int, default=200, help="ticks a stalled robot has not moved")
    parser.add_argument("--json", type=Path, help="write every failed episode's cause here")
    args = parser.parse_args()
    try:
        sizes = [int(n) for n in args.n.split(",")]
    except ValueError:
        parser.error(f"--n {args.n!r}: expected sizes such as 4,8,16")
    if args.episodes < 1:
        parser.error("--episodes must be at least 1")
    print(f"| N | success | {' | '.join(CAUSES)} |")
    print("|---|---|" + "---|" * len(CAUSES))
    every = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            out = Path(tmp) / f"n{n}"
            rows = play(args, n, out)
            failed = [k for k, row in enumerate(rows) if row["outcome"] != "success"]
            if failed:
                play(args, n, out, failed)
            causes = {}
            for k in failed:
                trace = json.loads((out / f"trace-n{n}-e{k}.json").read_text())
                causes[k] = cause_of(rows[k], trace, args.far, args.near, args.still)
            every[n] = causes
            counts = [sum(1 for c in causes.values() if c == cause) for cause in CAUSES]
            print(f"| {n} | {len(rows) - len(failed)} | {' | '.join(map(str, counts))} |", flush=True)
    if args.json:
        args.json.write_text(json.dumps({str(n): {str(k): c for k, c in causes.items()} for n, causes in every.items()},
                                        indent=1))


if __name__ == "__main__":
    main()
