#!/usr/bin/env python3
"""The reality comparison grid: the scripted baseline, the tuned baseline and
the learned policy under each condition of the real world, at several swarm sizes, on held-out
episodes (seed 1000 and up). Prints a Markdown table and writes a grouped-bar PNG.

Rows: ideal; each effect alone at the field preset's strength (noise: position and heading noise;
delay: actuation delay; lag: both acceleration limits; loss: command and observation loss);
3-4 ticks of actuation delay alone (delay-3-4: past the field preset's 1-3); the lab preset;
the field preset; field with controller_failure = 1 and dead_robot = "stop" (reported only).
Columns: scripted (default gains), scripted tuned (the gain search's best set for the row,
scripts/gain_search.py), learned (the shipped model or --checkpoint).

  scripts/reality_grid.py                                   # the full grid: 100 episodes a cell
  FORMATION_BIN_DIR=target/debug scripts/reality_grid.py --episodes 10 --n 3,12
  scripts/reality_grid.py --rows ideal,field --tuned runs/gain-search-field-.../

Every cell is a real multi-process run of scripts/run_swarm.sh --mode eval --viewer off with a
config holding the row's [reality] section (and, for scripted tuned, a [baseline] section),
written to OUT/configs/. Summaries, logs and run directories stay in OUT.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.dont_write_bytecode = True  # no __pycache__ in scripts/
import reality_runs as rr  # noqa: E402

COLUMNS = ("scripted", "tuned", "learned")
COLUMN_TITLES = {"scripted": "scripted", "tuned": "scripted tuned", "learned": "learned"}


def tuned_gains(tuned: Path | None, row: str) -> tuple[dict, str] | None:
    """The row's tuned gains and where they came from: DIR/tuned-ROW.toml in a --tuned directory
    (gain_search.py's output, several directories comma-separated), or a --tuned file for every row."""
    if tuned is None:
        return None
    candidates = [tuned] if tuned.is_file() else [d / f"tuned-{row}.toml" for d in map(Path, str(tuned).split(","))]
    for path in candidates:
        if path.is_file():
            section = rr.load_base(path).get("baseline")
            if not isinstance(section, dict):
                raise SystemExit(f"error: {path} has no [baseline] section")
            return section, str(path)
    return None


def fmt_count(summary: dict, key: str) -> str:
    value = summary.get(key)
    return "-" if value is None else str(value)


def table(results: dict, paces: dict, rows: list[str], ns: list[int], columns: list[str], episodes: int, seed: int) -> str:
    """The Markdown table of every cell (`paces`: each cell's steps over the pace floor's)."""
    lines = [
        f"{episodes} episodes a cell from seed {seed}. Edge error: final mean |d_ij - dbar_ij| averaged over all "
        "episodes; steps: mean over successful episodes; late / lost: summed over the cell's episodes "
        "(`-`: not in summary.json); x floor: the steps over the pace floor's on the same successful episodes "
        "(formation-pace-floor: no controller reaches the goal sooner).",
        "",
        "| condition | N | team | success | collisions | final edge error | steps to goal | x floor | formation held "
        "| late cmds | lost cmds | lost obs | missed ticks |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        for n in ns:
            for col in columns:
                s = results.get((row, n, col))
                head = f"| {rr.ROW_TITLES[row]} | {n} | {COLUMN_TITLES[col]} |"
                if s is None:
                    lines.append(head + " not run (no tuned gains) | | | | | | | | | |" if col == "tuned" and (row, n, col) not in results
                                 else head + " run failed | | | | | | | | | |")
                    continue
                lines.append(
                    f"{head} {s['success_rate']:.2f} | {s['collision_rate']:.2f} | "
                    f"{1000 * s['mean_final_edge_error_m']:.1f} mm | {rr.fmt_steps(s.get('mean_steps_to_goal'))} | "
                    f"{'-' if paces.get((row, n, col)) is None else f'{paces[(row, n, col)]:.2f}'} | "
                    f"{s['formation_hold_rate']:.2f} | {fmt_count(s, 'late_commands')} | {fmt_count(s, 'lost_commands')} | "
                    f"{fmt_count(s, 'lost_observations')} | {fmt_count(s, 'missed_ticks')} |"
                )
    return "\n".join(lines)


def plot(results: dict, rows: list[str], ns: list[int], columns: list[str], title: str, path: Path) -> None:
    """Grouped bars per N: success (top) and steps to goal (bottom) per condition and team."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {"scripted": "tab:gray", "tuned": "tab:green", "learned": "tab:red"}
    fig, axes = plt.subplots(2, len(ns), figsize=(max(4.5, 0.65 * len(rows)) * len(ns), 6.5), squeeze=False, sharex="col")
    width = 0.8 / len(columns)
    for j, n in enumerate(ns):
        for k, col in enumerate(columns):
            xs = [i + (k - (len(columns) - 1) / 2) * width for i in range(len(rows))]
            cells = [results.get((row, n, col)) for row in rows]
            success = [0.0 if s is None else s["success_rate"] for s in cells]
            steps = [0.0 if s is None or s.get("mean_steps_to_goal") is None else s["mean_steps_to_goal"] for s in cells]
            axes[0][j].bar(xs, success, width, color=colours[col], label=COLUMN_TITLES[col])
            axes[1][j].bar(xs, steps, width, color=colours[col], label=COLUMN_TITLES[col])
        axes[0][j].set_title(f"N = {n}")
        axes[0][j].set_ylim(0, 1.05)
        axes[0][j].set_ylabel("success rate")
        axes[1][j].set_ylabel("steps to goal (successful)")
        axes[1][j].set_xticks(range(len(rows)))
        axes[1][j].set_xticklabels([rr.ROW_TITLES[r].replace(" (field)", "").replace(" + ", "\n+ ") for r in rows],
                                   rotation=30, ha="right", fontsize=8)
        for ax in (axes[0][j], axes[1][j]):
            ax.grid(axis="y", alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper right", ncol=len(columns), fontsize=8)
    fig.suptitle(title, x=0.02, ha="left")
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=100, help="episodes per cell (default 100)")
    ap.add_argument("--n", default="3,12,32", help="swarm sizes, comma-separated (default 3,12,32)")
    ap.add_argument("--seed", type=int, default=1000, help="episode seed (default 1000: held out from every training run)")
    ap.add_argument("--rows", default=",".join(rr.ROW_NAMES), help=f"conditions, comma-separated (default all: {','.join(rr.ROW_NAMES)})")
    ap.add_argument("--columns", default=",".join(COLUMNS), help="teams, comma-separated (default scripted,tuned,learned)")
    ap.add_argument("--tuned", type=Path, help="gain_search.py output directories (comma-separated; tuned-ROW.toml in each), "
                    "or one TOML file with a [baseline] section for every row")
    rr.add_cell_options(ap)
    ap.add_argument("--out", type=Path, help="output directory (default runs/reality-grid-<time>)")
    args = ap.parse_args()
    if args.episodes < 1:
        ap.error("--episodes must be at least 1")
    ns = rr.parse_list(args.n)
    rows = rr.parse_list(args.rows, str)
    columns = rr.parse_list(args.columns, str)
    for row in rows:
        if row not in rr.ROW_NAMES:
            ap.error(f"unknown row '{row}' (one of {', '.join(rr.ROW_NAMES)})")
    for col in columns:
        if col not in COLUMNS:
            ap.error(f"unknown column '{col}' (one of {', '.join(COLUMNS)})")

    out = args.out or rr.ROOT / "runs" / f"reality-grid-{time.strftime('%Y%m%d-%H%M%S')}"
    (out / "configs").mkdir(parents=True, exist_ok=True)
    realities = rr.rows(args.field or rr.preset_path("field"), args.lab or rr.preset_path("lab"))
    base = rr.load_base(args.config)

    cells: list[tuple[tuple[str, int, str], rr.Cell]] = []
    sources: dict[str, str] = {}
    for row in rows:
        for col in columns:
            gains = None
            if col == "tuned":
                found = tuned_gains(args.tuned, row)
                if found is None:
                    continue
                gains, sources[row] = found
            config = out / "configs" / f"{row}-{col}.toml"
            config.write_text(f"# {rr.ROW_TITLES[row]}, {COLUMN_TITLES[col]} (scripts/reality_grid.py)\n"
                              + rr.to_toml(rr.cell_config(base, realities[row], gains)))
            for n in ns:
                team = "learned" if col == "learned" else "scripted"
                cells.append(((row, n, col), rr.Cell(n, team, config, out / "runs" / f"{row}-n{n}-{col}", args.episodes,
                                                    args.seed, checkpoint=args.checkpoint, shape=args.shape)))
    cells.sort(key=lambda c: (rows.index(c[0][0]), ns.index(c[0][1]), columns.index(c[0][2])))

    print(f"reality grid: {len(cells)} cells ({len(rows)} conditions x {len(columns)} teams x N = {ns}), "
          f"{args.episodes} episodes each from seed {args.seed}, binaries: {rr.bin_dir_note()}, into {out}", file=sys.stderr)
    if "tuned" in columns and len(sources) < len(rows):
        missing = [r for r in rows if r not in sources]
        print(f"reality grid: no tuned gains for {', '.join(missing)} (--tuned): those cells are left out", file=sys.stderr)
    progress = rr.Progress(len(cells))
    results: dict = {}
    for key, cell in cells:
        results[key] = rr.timed_run(cell, progress, f"{key[0]} N={key[1]} {COLUMN_TITLES[key[2]]}")

    # A row's episodes and motors are the same for every team: one floor per row.
    floors = {row: rr.pace_floors(cell.config, ns, args.episodes, args.seed, args.shape)
              for row, cell in {key[0]: cell for key, cell in cells}.items()}
    paces = {}
    for (row, n, col), cell in cells:
        if floors[row] is not None and (cell.run_dir / "episodes.csv").is_file():
            steps, floor = rr.pace_over_floor(cell.run_dir, floors[row][n])
            paces[(row, n, col)] = steps / floor if floor else None
    text = table(results, paces, rows, ns, columns, args.episodes, args.seed)
    if sources:
        text += "\n\nScripted tuned gains: " + "; ".join(f"{rr.ROW_TITLES[r]}: {p}" for r, p in sources.items())
    (out / "table.md").write_text(text + "\n")
    json.dump({"episodes": args.episodes, "seed": args.seed, "ns": ns, "rows": rows, "columns": columns,
               "realities": {r: realities[r] for r in rows}, "tuned_sources": sources,
               "cells": [{"row": r, "n": n, "team": c, "summary": s, "x_floor": paces.get((r, n, c))}
                         for (r, n, c), s in results.items()]},
              open(out / "grid.json", "w"), indent=1)
    plot(results, rows, ns, columns, f"reality grid: {args.episodes} held-out episodes a cell from seed {args.seed}",
         out / "grid.png")
    print(text)
    print(f"\ntable: {out}/table.md; plot: {out}/grid.png; runs: {out}/runs")
    return 0 if all(s is not None for s in results.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
