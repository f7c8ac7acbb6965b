#!/usr/bin/env python3
"""One held-out episode per kind of obstacle (forest, passage, trap), played by the potential
field (tuned: configs/potential-field-KIND.toml, or the default gains while that is missing), the
circulating, detouring and gap-searching fields (configs/potential-field-{circulating,detouring,gap}-KIND.toml,
when there is one), the planner
and the shipped model, drawn on one figure per kind: docs/obstacles_KIND.png.

  scripts/obstacle_pictures.py                      # seed 1000, episode 0, N = 8
  scripts/obstacle_pictures.py --episode 3 --out /tmp/pictures

Each controller's run is `formation-play --trace-episode K --out DIR` (from $FORMATION_BIN_DIR,
default target/debug); its traces and CSV rows stay in --runs.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Circle, Polygon  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
KINDS = ("forest", "passage", "trap")
COLOURS = {"field": "tab:orange", "circulating": "tab:purple", "detouring": "tab:brown", "gap": "tab:red",
           "planner": "tab:blue", "model": "tab:green", "model-recovery": "tab:olive"}
#: The hand-written variants of the potential field drawn where a config of theirs exists.
VARIANTS = {"circulating": "circulating field (tuned)", "detouring": "detouring field (tuned)",
            "gap": "gap-searching field"}


def controllers(kind: str) -> dict[str, tuple[str, list[str]]]:
    """Each controller's legend name and formation-play arguments."""
    tuned = ROOT / "configs" / f"potential-field-{kind}.toml"
    field = ("potential field (tuned)", ["--team", "scripted", "--config", str(tuned.relative_to(ROOT))]) \
        if tuned.is_file() else ("potential field (default gains)", ["--team", "scripted"])
    # formation-play's default model among obstacles: the shipped obstacle policy.
    rivals = {"field": field}
    for name, legend in VARIANTS.items():
        tuned_variant = ROOT / "configs" / f"potential-field-{name}-{kind}.toml"
        if tuned_variant.is_file():
            rivals[name] = (legend, ["--team", "scripted", "--config", str(tuned_variant.relative_to(ROOT))])
    return {**rivals, "planner": ("planner", ["--team", "oracle"]),
            "model": ("learned (the shipped obstacle policy)", ["--team", "model"]),
            "model-recovery": ("learned, with the recovery behaviour",
                               ["--team", "model", "--config", "configs/obstacles-recovery.toml"])}


#: Drawn unless --controllers names them.
OPTIONAL = {"model-recovery"}


def play(args, kind: str, extra: list[str], out: Path) -> tuple[dict, dict]:
    """The episode's trace and its episodes.csv row."""
    cmd = [str(Path(args.bin_dir) / "formation-play"), *extra, "--obstacles", kind, "--n", str(args.n),
           "--episodes", str(args.episode + 1), "--seed", str(args.seed), "--out", str(out),
           "--trace-episode", str(args.episode)]
    print("$", " ".join(cmd), file=sys.stderr, flush=True)
    subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    trace = json.loads((out / f"trace-n{args.n}-e{args.episode}.json").read_text())
    with open(out / f"n{args.n}.csv") as f:
        row = [r for r in csv.DictReader(f) if int(r["episode"]) == args.episode][0]
    return trace, row


def outcome(row: dict) -> str:
    steps = row["steps"]
    if row["outcome"] == "success":
        return f"success in {steps} steps"
    if row["outcome"] == "collision":
        return f"hit an obstacle at step {steps}" if int(row["obstacle_collisions"]) else f"robots collided at step {steps}"
    return f"{row['outcome']} after {steps} steps"


def draw_obstacles(ax, obstacles: list[dict]) -> None:
    for ob in obstacles:
        if "disc" in ob:
            ax.add_patch(Circle(ob["disc"]["centre"], ob["disc"]["radius"], color="0.6", zorder=1))
        else:
            (ax_, ay), (bx, by), t = ob["wall"]["a"], ob["wall"]["b"], ob["wall"]["thickness"]
            length = ((bx - ax_) ** 2 + (by - ay) ** 2) ** 0.5
            nx, ny = -(by - ay) / length * t / 2, (bx - ax_) / length * t / 2
            ax.add_patch(Polygon([(ax_ + nx, ay + ny), (bx + nx, by + ny), (bx - nx, by - ny), (ax_ - nx, ay - ny)],
                                 color="0.45", zorder=1))


def picture(args, kind: str) -> Path:
    fig, ax = plt.subplots(figsize=(8, 8))
    xs, ys = [], []
    for key, (name, extra) in controllers(kind).items():
        if (key not in args.controllers) if args.controllers else key in OPTIONAL:
            continue
        trace, row = play(args, kind, extra, args.runs / kind / key)
        for robot in range(args.n):
            path = [tick[robot] for tick in trace["poses"]]
            ax.plot([p[0] for p in path], [p[1] for p in path], color=COLOURS[key], lw=1.2, alpha=0.85, zorder=3,
                    label=f"{name}: {outcome(row)}" if robot == 0 else None)
            ax.plot(path[-1][0], path[-1][1], "o", ms=4, color=COLOURS[key], zorder=4)
        xs += [p[0] for tick in trace["poses"] for p in tick]
        ys += [p[1] for tick in trace["poses"] for p in tick]
    draw_obstacles(ax, trace["obstacles"])
    start = trace["poses"][0]
    ax.plot([p[0] for p in start], [p[1] for p in start], "ks", ms=6, mfc="none", zorder=5, label="start")
    goal = trace["goal"]
    ax.plot([goal[0] + s[0] for s in trace["slots"]], [goal[1] + s[1] for s in trace["slots"]], "kx", ms=8, mew=2,
            zorder=5, label="goal slots")
    pad = 0.7
    ax.set_xlim(min(xs) - pad, max(xs) + pad)
    ax.set_ylim(min(ys) - pad, max(ys) + pad)
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{kind}: N = {args.n}, held-out episode {args.episode} of seed {args.seed}")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=2, fontsize=9)
    png = args.out / (args.name or f"obstacles_{kind}.png")
    fig.savefig(png, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return png


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--episode", type=int, default=0)
    parser.add_argument("--n", type=int, default=8)
    parser.add_argument("--kinds", default=",".join(KINDS))
    parser.add_argument("--out", type=Path, default=ROOT / "docs")
    parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "obstacle-pictures")
    parser.add_argument("--bin-dir", default=os.environ.get("FORMATION_BIN_DIR", "target/debug"))
    parser.add_argument("--controllers", type=lambda text: set(text.split(",")), default=None,
                        help="draw only these (comma-separated) of field, circulating, detouring, gap, planner, "
                             "model, model-recovery (the learned policy with configs/obstacles-recovery.toml); "
                             "default: all but model-recovery")
    parser.add_argument("--name", help="the PNG's name (default obstacles_KIND.png)")
    args = parser.parse_args()
    known = set(COLOURS)
    if args.controllers and not args.controllers <= known:
        parser.error(f"--controllers: unknown {sorted(args.controllers - known)}; known: {sorted(known)}")
    if args.name and "," in args.kinds:
        parser.error("--name draws one picture: give one of --kinds")
    args.out.mkdir(parents=True, exist_ok=True)
    for kind in args.kinds.split(","):
        print(picture(args, kind))


if __name__ == "__main__":
    main()
