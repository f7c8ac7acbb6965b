#!/usr/bin/env python3
"""The obstacles grid: the controllers among each kind of obstacle, in the ideal world and the
field preset with a noisy range sensor, at several swarm sizes, on held-out episodes (seed 1000).

Rows: kinds none / forest / passage / trap x N. Worlds: ideal (no [reality]) and field
(configs/reality-field-ranging.toml). Controllers (formation-play --team ...):
  default  the scripted potential field with its default gains (no config)
  tuned    the same with configs/potential-field-KIND.toml (not for kind none; "not yet tuned"
           while the file is missing)
  circulating  the circulating, braking potential field, configs/potential-field-circulating-KIND.toml
           (the field's three obstacle options on; "not yet tuned" while the file is missing)
  detouring  the detouring field, configs/potential-field-detouring-KIND.toml (the circulating
           field that also follows a wall round when its way to the slot is blocked)
  planner  the privileged planner that knows the map (--team oracle)
  solo     each robot's own planner over the map, no team plan (--team solo; tried as a DAgger
           teacher)
  model    the open-arena model, models/formation.safetensors (its own observation model: it
           does not see obstacles)
  learned  the actor of --learned FILE (default: the shipped obstacle policy of each kind, the
           one the launcher loads: models/formation-obstacles-passage.safetensors in the passage,
           models/formation-obstacles.safetensors otherwise)

  scripts/obstacle_grid.py                                  # 100 episodes a cell, N = 4, 8, 16
  scripts/obstacle_grid.py --episodes 10 --n 4 --kinds forest --out runs/obstacle-grid-try
  scripts/obstacle_grid.py --learned runs/forest/rl-s1/best.safetensors --controllers tuned,planner,learned

Writes OUT/grid.json (every cell's formation-play line) and OUT/grid.md, and prints the Markdown.
formation-play comes from $FORMATION_BIN_DIR (default target/debug).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
KINDS = ("none", "forest", "passage", "trap")
WORLDS = {"ideal": None, "field": "configs/reality-field-ranging.toml"}
WORLD_TITLES = {"ideal": "Ideal world", "field": "Field preset + noisy range sensor (configs/reality-field-ranging.toml)"}
CONTROLLERS = ("default", "tuned", "circulating", "detouring", "planner", "solo", "model", "learned")
TITLES = {"default": "potential field (default)", "tuned": "potential field (tuned)",
          "circulating": "circulating field (tuned)", "detouring": "detouring field (tuned)", "planner": "planner", "solo": "per-robot planner",
          "model": "open-arena model", "learned": "learned"}
TEAM = {"default": "scripted", "tuned": "scripted", "circulating": "scripted", "detouring": "scripted", "planner": "oracle", "solo": "solo",
        "model": "model", "learned": "model"}


def tuned_config(kind: str, controller: str = "tuned") -> Path:
    field = f"potential-field-{controller}" if controller in ("circulating", "detouring") else "potential-field"
    return ROOT / "configs" / f"{field}-{kind}.toml"


def play(args, kind: str, world: str, controller: str) -> dict[int, dict] | str:
    """One formation-play run: its line per N, or why it was not run."""
    cmd = [str(Path(args.bin_dir) / "formation-play"), "--team", TEAM[controller], "--obstacles", kind,
           "--n", args.n, "--episodes", str(args.episodes), "--seed", str(args.seed)]
    if controller in ("tuned", "circulating", "detouring"):
        if kind == "none":
            return "-"
        if not tuned_config(kind, controller).is_file():
            return "not yet tuned"
        cmd += ["--config", str(tuned_config(kind, controller).relative_to(ROOT))]
    if controller == "model":
        cmd += ["--checkpoint", "models/formation.safetensors"]
    if controller == "learned" and args.learned:
        cmd += ["--checkpoint", str(args.learned)]
    if WORLDS[world]:
        cmd += ["--reality", WORLDS[world]]
    print("$", " ".join(cmd), file=sys.stderr, flush=True)
    out = subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.PIPE, text=True).stdout
    lines = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    return {line["n"]: line for line in lines}


def cell(line: dict) -> str:
    steps = "-" if line["steps_to_goal"] is None else f"{line['steps_to_goal']:.0f}"
    return (f"{line['success']:.2f} | {line['robot_collisions']:.2f} | {line['obstacle_collisions']:.2f} | "
            f"{line['timeouts']:.2f} | {steps} | {1000 * line['final_edge_error_m']:.1f}")


def table(results: dict, world: str, kinds: list[str], ns: list[int], controllers: list[str]) -> str:
    lines = [f"**{WORLD_TITLES[world]}**", "",
             "| kind | N | controller | success | robot coll. | obstacle coll. | timeouts | steps to goal | final edge error (mm) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for kind in kinds:
        for n in ns:
            for controller in controllers:
                got = results[world][kind][controller]
                if got == "-":
                    continue
                body = f"{got} | | | | | " if isinstance(got, str) else cell(got[n])
                lines.append(f"| {kind} | {n} | {TITLES[controller]} | {body} |")
    return "\n".join(lines)


def glance(results: dict, worlds: list[str], kinds: list[str], ns: list[int], controllers: list[str]) -> str:
    """Success only: rows kind x N, a column per world and controller (default, tuned: the potential
    field with default or tuned gains)."""
    cols = [(w, c) for w in worlds for c in controllers]
    lines = ["**Success at a glance**", "",
             "| kind | N | " + " | ".join(f"{c}, {w}" for w, c in cols) + " |",
             "|---|---|" + "---|" * len(cols)]
    for kind in kinds:
        for n in ns:
            cells = [results[w][kind][c] for w, c in cols]
            lines.append(f"| {kind} | {n} | " + " | ".join(
                v if isinstance(v, str) else f"{v[n]['success']:.2f}" for v in cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", default="4,8,16", help="swarm sizes, comma-separated")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--kinds", default=",".join(KINDS))
    parser.add_argument("--worlds", default=",".join(WORLDS))
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "obstacle-grid")
    parser.add_argument("--bin-dir", default=os.environ.get("FORMATION_BIN_DIR", "target/debug"))
    parser.add_argument("--learned", type=Path,
                        help="the checkpoint the 'learned' controller plays (default: each kind's shipped obstacle policy)")
    parser.add_argument("--controllers", default=",".join(CONTROLLERS),
                        help="comma-separated subset of " + ",".join(CONTROLLERS))
    args = parser.parse_args()
    kinds, worlds = args.kinds.split(","), args.worlds.split(",")
    controllers = args.controllers.split(",")
    unknown = [c for c in controllers if c not in CONTROLLERS]
    if unknown:
        parser.error(f"unknown controllers {unknown}: choose from {', '.join(CONTROLLERS)}")
    if "learned" in controllers and args.learned and not args.learned.is_file():
        parser.error(f"--learned {args.learned}: no such file")
    ns = [int(n) for n in args.n.split(",")]

    results = {w: {k: {c: play(args, k, w, c) for c in controllers} for k in kinds} for w in worlds}
    for kind in kinds:
        if kind != "none" and not tuned_config(kind).is_file():
            print(f"note: {tuned_config(kind).relative_to(ROOT)} is missing: its tuned column is 'not yet tuned'", file=sys.stderr)

    header = (f"{args.episodes} episodes a cell from seed {args.seed}. Rates are fractions of the episodes; "
              "steps to goal: mean over successful episodes; final edge error: mean |d_ij - dbar_ij| at the "
              "episode's end over all episodes.")
    if "learned" in controllers and args.learned:
        header += f" learned: {args.learned.resolve().relative_to(ROOT) if args.learned.resolve().is_relative_to(ROOT) else args.learned}."
    elif "learned" in controllers:
        header += (" learned: each kind's shipped obstacle policy (models/formation-obstacles-passage.safetensors in the"
                   " passage, models/formation-obstacles.safetensors otherwise).")
    markdown = "\n\n".join([header, glance(results, worlds, kinds, ns, controllers)]
                           + [table(results, w, kinds, ns, controllers) for w in worlds]) + "\n"
    args.out.mkdir(parents=True, exist_ok=True)
    json_results = {w: {k: {c: (v if isinstance(v, str) else {str(n): line for n, line in v.items()})
                            for c, v in row.items()} for k, row in per.items()} for w, per in results.items()}
    (args.out / "grid.json").write_text(json.dumps({"episodes": args.episodes, "seed": args.seed, "n": ns,
                                                    "cells": json_results}, indent=1) + "\n")
    (args.out / "grid.md").write_text(markdown)
    print(markdown)


if __name__ == "__main__":
    main()
