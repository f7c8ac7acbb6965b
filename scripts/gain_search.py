#!/usr/bin/env python3
"""The fair hand-written rival (issue 28, item 5): searches the scripted baseline's gains for one
condition of the reality grid and reports the whole search as a success against steps-to-goal
front, with the learned policy's point on it.

Each gain set is a run config with a `[baseline]` section (OUT/sets/set-NN.toml) played by the
baseline on every robot, at each N, on episodes from --seed (default 2000: not the held-out 1000
and up). "Scripted tuned" is the most successful set (success averaged over the N list), ties
broken by fewer mean steps to the goal; it is written as OUT/tuned-ROW.toml, which
scripts/reality_grid.py --tuned OUT reads.

  scripts/gain_search.py --row field --n 3,12,32 --episodes 20
  FORMATION_BIN_DIR=target/debug scripts/gain_search.py --row ideal --sets 20 --episodes 10

The sets: the defaults, the issue's softer gains (k_form 0.75, k_goal 0.3, k_turn 1.25), the
defaults' formation/goal/turn gains scaled together, and the rest drawn log-uniformly from a
seeded Latin hypercube (--search-seed) over the ranges in RANGES. Then --refine more sets, one
at a time, each the best set so far (most successful, then fewest steps) with every gain
multiplied by exp(N(0, 0.25)) and kept in RANGES: a (1+1) local search that finds the fast end
of the front, which a hypercube of a few dozen points in five dimensions misses. (Hand-written:
a dozen lines, seeded and deterministic; the cost is the runs, not the optimiser.)

Among obstacles (--obstacles forest|passage|trap): the potential field. The same sets and local
search over SEVEN gains, the five plus k_obstacle and obstacle_range_m (OBSTACLE_RANGES), each set
played by `formation-play --team scripted --obstacles KIND --config SET.toml --n ... --episodes ...
--seed ...` (in-process, seconds a set; binary from FORMATION_BIN_DIR, default target/debug; no
reality unless --config has one, no learned point, no pace floor). Ranked by success averaged over
N, ties by fewer collisions (obstacle + robot), then fewer steps. Writes OUT/tuned-KIND.toml (the
winner's `[baseline]`, all seven gains, under a header with the command, seeds and score),
OUT/front.png, OUT/search.csv and OUT/search.json; the shipped tuned potential fields are copies:

  scripts/gain_search.py --obstacles forest --n 4,8,16 --episodes 20 --seed 2000 --sets 64 --refine 64 \\
      --out runs/gain-search-forest
  cp runs/gain-search-forest/tuned-forest.toml configs/potential-field-forest.toml
  cp runs/gain-search-forest/front.png docs/potential_field_forest.png

With --circulating the search takes in the field's three obstacle options too (TEN gains,
CIRCULATING_RANGES: k_circulation, obstacle_yield, brake_range_m), for the circulating, braking
potential field (configs/potential-field-circulating-KIND.toml). With --detouring, the detour
reach as well (ELEVEN gains, DETOURING_RANGES: detour_range_m), for the detouring field
(configs/potential-field-detouring-KIND.toml).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import random
import shlex
import subprocess
import sys
import time
import tomllib
from pathlib import Path

sys.dont_write_bytecode = True  # no __pycache__ in scripts/
import reality_runs as rr  # noqa: E402

#: Search ranges of each gain (lo, hi), drawn log-uniformly.
RANGES = {
    "k_form": (0.15, 3.0),
    "k_goal": (0.15, 2.4),
    "k_turn": (0.6, 5.0),
    "repulsion_range": (0.3, 0.9),
    "k_repulsion": (1.0, 6.0),
}
#: Among obstacles: the five and the potential field's two, with the defaults of the latter
#: (core/src/baseline.rs).
OBSTACLE_RANGES = {**RANGES, "k_obstacle": (0.3, 10.0), "obstacle_range_m": (0.2, 1.2)}
OBSTACLE_GAINS = {**rr.DEFAULT_GAINS, "k_obstacle": 1.0, "obstacle_range_m": 0.5}
#: With --circulating: the seven and the field's three obstacle options (core/src/baseline.rs),
#: which start on at a set that worked in the forest (docs/OBSTACLES.md).
CIRCULATING_RANGES = {**OBSTACLE_RANGES, "k_circulation": (0.3, 6.0), "obstacle_yield": (0.3, 20.0),
                      "brake_range_m": (0.1, 1.0)}
CIRCULATING_GAINS = {**OBSTACLE_GAINS, "k_circulation": 2.0, "obstacle_yield": 5.0, "brake_range_m": 0.3}
#: With --detouring: the ten and the detour reach, up to the range sensor's 2 m.
DETOURING_RANGES = {**CIRCULATING_RANGES, "detour_range_m": (0.5, 2.0)}
DETOURING_GAINS = {**CIRCULATING_GAINS, "detour_range_m": 2.0}
#: The defaults' k_form, k_goal and k_turn multiplied together by these.
SCALES = (0.35, 0.5, 0.6, 0.75, 0.9, 1.25)


def gain_sets(count: int, seed: int, ranges: dict = RANGES, defaults: dict = rr.DEFAULT_GAINS) -> list[dict]:
    """count gain sets: defaults, the issue's softer set, the scaled family, then a hypercube."""
    sets = [dict(defaults), {**defaults, "k_form": 0.75, "k_goal": 0.3, "k_turn": 1.25}]
    for s in SCALES:
        if s != 0.5:  # 0.5 is the set
            sets.append({**defaults, **{k: round(defaults[k] * s, 4) for k in ("k_form", "k_goal", "k_turn")}})
    rng = random.Random(seed)
    rest = max(0, count - len(sets))
    strata = {name: rng.sample(range(rest), rest) for name in ranges}
    for i in range(rest):
        gains = {}
        for name in ranges:
            lo, hi = ranges[name]
            u = (strata[name][i] + rng.random()) / rest
            gains[name] = round(math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo))), 4)
        sets.append(gains)
    return sets[:count]


def perturbed(gains: dict, rng: random.Random, sigma: float = 0.25, ranges: dict = RANGES) -> dict:
    """gains with each multiplied by exp(N(0, sigma)), kept in the ranges."""
    out = {}
    for name in ranges:
        lo, hi = ranges[name]
        out[name] = round(min(max(gains[name] * math.exp(rng.gauss(0.0, sigma)), lo), hi), 4)
    return out


def fmt_ratio(ratio) -> str:
    """A pace over the floor, or '-'."""
    return "-" if ratio is None else f"{ratio:.2f}"


def rank_key(result: dict):
    """Most successful first, then fewer steps."""
    return (-round(result["success"], 9), result["steps"])


def obstacle_rank_key(result: dict):
    """Most successful first, then fewer collisions (obstacle + robot), then fewer steps."""
    return (-round(result["success"], 9), round(result["collisions"], 9), result["steps"])


def play(kind: str, config: Path, ns: list[int], episodes: int, seed: int) -> list[dict]:
    """formation-play's scripted team among `kind` obstacles: a summary per N (the keys pooled()
    and plot() read, plus obstacle_collisions)."""
    binary = Path(os.environ.get("FORMATION_BIN_DIR") or rr.ROOT / "target" / "debug") / "formation-play"
    if not binary.is_file():
        raise SystemExit(f"error: no {binary}: cargo build -p formation-critic --bin formation-play, "
                         "or set FORMATION_BIN_DIR")
    cmd = [str(binary), "--team", "scripted", "--obstacles", kind, "--config", str(config),
           "--n", ",".join(map(str, ns)), "--episodes", str(episodes), "--seed", str(seed)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"error: {shlex.join(cmd)} failed:\n{done.stderr}")
    by_n = {d["n"]: d for d in map(json.loads, done.stdout.splitlines())}
    return [{"episodes": d["episodes"], "success_rate": d["success"],
             "collision_rate": d["robot_collisions"] + d["obstacle_collisions"],
             "obstacle_collisions": d["obstacle_collisions"], "mean_steps_to_goal": d["steps_to_goal"]}
            for d in (by_n[n] for n in ns)]


def pooled(summaries: list[dict | None]) -> dict:
    """Success and collisions averaged over the N list (a failed run counts as 0 success), and the
    mean steps to the goal of every successful episode of the N list (infinity: none)."""
    ok = [s for s in summaries if s is not None]
    reached = [(s["success_rate"] * s["episodes"], s["mean_steps_to_goal"]) for s in ok if s.get("mean_steps_to_goal") is not None]
    successes = sum(count for count, _ in reached)
    return {
        "success": sum(s["success_rate"] for s in ok) / len(summaries),
        "collisions": sum(s["collision_rate"] for s in ok) / max(1, len(ok)),
        "steps": sum(count * steps for count, steps in reached) / successes if successes else math.inf,
        "failed_runs": len(summaries) - len(ok),
    }


def front_check(results: list[dict], learned: dict) -> list[dict]:
    """The sets that beat the learned policy on the front: success at least the learned one's - 0.02
    in fewer than 1.2x its mean steps (issue 28's acceptance)."""
    return [
        r for r in results
        if r["success"] >= learned["success"] - 0.02 and r["steps"] < 1.2 * learned["steps"]
    ]


def with_pace(result: dict, run_dirs: list[Path], floors: dict[int, list] | None, ns: list[int]) -> dict:
    """result with "x_floor": its steps over the pace floor's on its successful episodes (None
    without a floor or a success)."""
    total = [0, 0]
    if floors is not None:
        for n, run_dir in zip(ns, run_dirs):
            if (run_dir / "episodes.csv").is_file():
                steps, floor = rr.pace_over_floor(run_dir, floors[n])
                total = [total[0] + steps, total[1] + floor]
    return {**result, "x_floor": total[0] / total[1] if total[1] else None}


def plot(results: list[dict], learned: dict | None, tuned: dict, ns: list[int], title: str, path: Path,
         floors: dict[int, list] | None = None, first: str = "defaults") -> None:
    """Success against mean steps to the goal, one point per gain set, per N and pooled, with the
    pace floor (no controller is faster on these episodes) as a dashed line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("all N (mean)", None)] + [(f"N = {n}", i) for i, n in enumerate(ns)] if len(ns) > 1 else [(f"N = {ns[0]}", 0)]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4), squeeze=False)
    for ax, (name, i) in zip(axes[0], panels):
        def point(r):
            if i is None:
                return r["steps"], r["success"]
            s = r["per_n"][i]
            return (math.inf, 0.0) if s is None else (rr.steps_or_inf(s), s["success_rate"])

        for local, colour, label in ((False, "tab:blue", "gain set (scripted)"), (True, "tab:orange", "local search (scripted)")):
            finite = [point(r) for r in results if r.get("local", False) == local and math.isfinite(point(r)[0])]
            if finite:
                ax.scatter(*zip(*finite), c=colour, s=22, label=label)
        for r, style in ((results[0], dict(marker="s", c="tab:gray", label=first)), (tuned, dict(marker="D", c="tab:green", label="tuned"))):
            x, y = point(r)
            if math.isfinite(x):
                ax.scatter([x], [y], s=60, edgecolors="k", zorder=3, **style)
        if learned is not None:
            x, y = point(learned)
            if math.isfinite(x):
                ax.scatter([x], [y], marker="*", s=220, c="tab:red", edgecolors="k", zorder=4, label="learned")
        if floors is not None:
            bounds = [b for n in (ns if i is None else [ns[i]]) for b in floors[n] if b is not None]
            if bounds:
                ax.axvline(sum(bounds) / len(bounds), ls="--", c="k", lw=1, label="pace floor (mean)")
        ax.set_title(name)
        ax.set_xlabel("mean steps to goal (successful episodes)")
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("success rate")
    if axes[0][0].get_legend_handles_labels()[0]:
        axes[0][0].legend(fontsize=8, loc="lower right")
    else:
        axes[0][0].text(0.5, 0.5, "no gain set reached the goal", ha="center", transform=axes[0][0].transAxes)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def obstacle_report(args, kind: str, ns: list[int], results: list[dict], out: Path) -> int:
    """The --obstacles search's tuned config, files, front plot and table."""
    for r in results:
        r["obstacle_collisions"] = sum(s["obstacle_collisions"] for s in r["per_n"]) / len(ns)
    ranked = sorted(results, key=obstacle_rank_key)
    tuned = ranked[0]
    names = list(DETOURING_RANGES if args.detouring else CIRCULATING_RANGES if args.circulating else OBSTACLE_RANGES)
    score = (f"success {tuned['success']:.3f}, collisions {tuned['collisions']:.3f} (obstacle {tuned['obstacle_collisions']:.3f}), "
             f"mean steps to goal {rr.fmt_steps(None if math.isinf(tuned['steps']) else tuned['steps'])}")
    (out / f"tuned-{kind}.toml").write_text(
        f"# Tuned potential field for '{kind}' obstacles: the scripted baseline's {len(names)} gains that scored best in\n"
        f"# scripts/gain_search.py's search (set {tuned['set']} of {len(results)}; most successful over the N list, ties\n"
        "# by fewer obstacle + robot collisions, then fewer steps). Searched with\n"
        f"#   {shlex.join(['scripts/gain_search.py', *sys.argv[1:]])}\n"
        f"# on episodes from seed {args.seed} (search seeds; the held-out ones are 1000-1999), N = {args.n}, {args.episodes} each:\n"
        f"# {score}.\n"
        f"# Play: formation-play --team scripted --obstacles {kind} --config THIS_FILE --n 4,8,16 --seed 1000\n"
        + rr.to_toml({"baseline": tuned["gains"]})
    )
    with open(out / "search.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["set", *names, "n", "success", "collisions", "obstacle_collisions", "steps_to_goal"])
        for r in results:
            for n, s in zip(ns, r["per_n"]):
                w.writerow([r["set"], *(r["gains"][g] for g in names), n, s["success_rate"], s["collision_rate"],
                            s["obstacle_collisions"], s["mean_steps_to_goal"]])
    json.dump({"obstacles": kind, "ns": ns, "episodes": args.episodes, "seed": args.seed, "results": results,
               "tuned": tuned["set"]}, open(out / "search.json", "w"), indent=1, default=str)
    field = "detouring field" if args.detouring else "circulating field" if args.circulating else "potential field"
    first = "start" if args.start else "defaults"
    plot(results, None, tuned, ns, f"{field} among {kind} obstacles: {len(results)} gain sets, "
         f"{args.episodes} episodes/N from seed {args.seed}", out / "front.png", first=first)

    print(f"### Potential field search: {kind} (N = {args.n}, {args.episodes} episodes each from seed {args.seed})\n")
    print("| rank | set | " + " | ".join(names) + " | success | collisions | obstacle collisions | steps to goal |")
    print("|---" * (len(names) + 6) + "|")
    for i, r in enumerate(ranked):
        note = f" ({first})" if r["set"] == 0 else (" (local)" if r["local"] else "")
        print(f"| {i + 1} | {r['set']}{note} | " + " | ".join(str(r["gains"][g]) for g in names)
              + f" | {r['success']:.2f} | {r['collisions']:.2f} | {r['obstacle_collisions']:.2f} | "
              f"{rr.fmt_steps(None if math.isinf(r['steps']) else r['steps'])} |")
    print(f"\ntuned: {out}/tuned-{kind}.toml (set {tuned['set']}: {score}); front: {out}/front.png")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--row", choices=rr.ROW_NAMES, help="grid condition to search (default field)")
    ap.add_argument("--obstacles", choices=("forest", "passage", "trap"),
                    help="search the potential field's seven gains among these obstacles with formation-play "
                         "instead (no --row)")
    ap.add_argument("--circulating", action="store_true",
                    help="with --obstacles: search the field's three obstacle options too (k_circulation, "
                         "obstacle_yield, brake_range_m), ten gains")
    ap.add_argument("--detouring", action="store_true",
                    help="with --obstacles: the ten of --circulating and the detour reach (detour_range_m), eleven gains")
    ap.add_argument("--start", type=Path,
                    help="a config whose [baseline] gains are the search's first set and the defaults of the "
                         "scaled family (e.g. a tuned field to refine)")
    ap.add_argument("--n", default="3,12,32", help="swarm sizes, comma-separated (default 3,12,32)")
    ap.add_argument("--episodes", type=int, default=20, help="episodes per gain set and N (default 20)")
    ap.add_argument("--seed", type=int, default=2000, help="episode seed (default 2000; the held-out seeds are 1000 and up, below 2000)")
    ap.add_argument("--sets", type=int, default=24, help="gain sets (default 24, at least 20 for the issue)")
    ap.add_argument("--refine", type=int, default=16,
                    help="sets of the local search around the best so far, after --sets (default 16; 0 = off)")
    ap.add_argument("--search-seed", type=int, default=7, help="seed of the hypercube and local-search sets (default 7)")
    ap.add_argument("--sets-from", type=Path,
                    help="play the gain sets of an earlier search (its OUT directory, search.json) instead of drawing "
                         "them, e.g. a search's sets on held-out episodes (--sets and --refine are then ignored)")
    rr.add_cell_options(ap)
    ap.add_argument("--no-learned", action="store_true", help="leave out the learned policy's point")
    ap.add_argument("--out", type=Path, help="output directory (default runs/gain-search-ROW-<time>)")
    args = ap.parse_args()
    if args.episodes < 1 or args.sets < 1 or args.refine < 0:
        ap.error("--episodes and --sets must be at least 1, --refine at least 0")
    if args.obstacles and args.row:
        ap.error("--row is the open arena's; --obstacles searches without a reality row")
    if args.obstacles and args.shape:
        ap.error("--shape is the open arena's; put the shape in --config among obstacles")
    args.row = args.row or "field"
    if 1000 <= args.seed < 2000:
        print("gain_search.py: warning: seeds 1000-1999 are the grid's held-out episodes", file=sys.stderr)

    ns = rr.parse_list(args.n)
    kind = args.obstacles
    name = kind or args.row
    if (args.circulating or args.detouring) and not kind:
        ap.error("--circulating and --detouring are for the potential field among --obstacles")
    if args.detouring:
        ranges, defaults, key = DETOURING_RANGES, DETOURING_GAINS, obstacle_rank_key
    elif args.circulating:
        ranges, defaults, key = CIRCULATING_RANGES, CIRCULATING_GAINS, obstacle_rank_key
    elif kind:
        ranges, defaults, key = OBSTACLE_RANGES, OBSTACLE_GAINS, obstacle_rank_key
    else:
        ranges, defaults, key = RANGES, rr.DEFAULT_GAINS, rank_key
    if args.start:
        start = tomllib.loads(args.start.read_text()).get("baseline", {})
        unknown = sorted(set(start) - set(ranges))
        if unknown:
            ap.error(f"--start {args.start}: [baseline] keys {unknown} are not searched here")
        defaults = {**defaults, **start}
    out = args.out or rr.ROOT / "runs" / f"gain-search-{name}-{time.strftime('%Y%m%d-%H%M%S')}"
    (out / "sets").mkdir(parents=True, exist_ok=True)
    reality = {} if kind else rr.rows(args.field or rr.preset_path("field"), args.lab or rr.preset_path("lab"))[args.row]
    base = rr.load_base(args.config)
    if args.sets_from:
        earlier = json.load(open(args.sets_from / "search.json"))
        played = sorted(earlier["results"], key=lambda r: r["set"])
        sets, local_sets = [{**defaults, **r["gains"]} for r in played], {r["set"] for r in played if r.get("local")}
        args.refine = 0
    else:
        sets = gain_sets(args.sets, args.search_seed, ranges, defaults)
        local_sets = set()

    progress = rr.Progress((len(sets) + args.refine) * (1 if kind else len(ns)) + (0 if args.no_learned or kind else len(ns)))
    print(f"gain search: {name}, {len(sets)} gain sets and {args.refine} of local search, N = {ns}, {args.episodes} episodes from seed {args.seed}, "
          f"binaries: {rr.bin_dir_note()}, into {out}", file=sys.stderr)
    results = []
    local = random.Random(args.search_seed + 1)
    for k in range(len(sets) + args.refine):
        gains = sets[k] if k < len(sets) else perturbed(min(results, key=key)["gains"], local, ranges=ranges)
        config = out / "sets" / f"set-{k:02d}.toml"
        config.write_text(f"# gain set {k} of the {name} search (scripts/gain_search.py)\n"
                          + rr.to_toml(rr.cell_config(base, reality, gains)))
        if kind:
            start = time.monotonic()
            per_n = play(kind, config, ns, args.episodes, args.seed)
            p = pooled(per_n)
            progress.step(f"set {k:02d}", {"success_rate": p["success"], "mean_steps_to_goal": None if math.isinf(p["steps"]) else p["steps"]},
                          time.monotonic() - start)
        else:
            per_n = [
                rr.timed_run(rr.Cell(n, "scripted", config, out / "runs" / f"set-{k:02d}-n{n}", args.episodes, args.seed, shape=args.shape),
                             progress, f"set {k:02d} N={n}")
                for n in ns
            ]
        results.append({"set": k, "gains": gains, "per_n": per_n, "local": k >= len(sets) or k in local_sets,
                        **pooled(per_n)})
    if kind:
        return obstacle_report(args, kind, ns, results, out)
    floors = rr.pace_floors(out / "sets" / "set-00.toml", ns, args.episodes, args.seed, args.shape)
    results = [with_pace(r, [out / "runs" / f"set-{r['set']:02d}-n{n}" for n in ns], floors, ns) for r in results]
    learned = None
    if not args.no_learned:
        config = out / "sets" / "learned.toml"
        config.write_text(rr.to_toml(rr.cell_config(base, reality, None)))
        per_n = [
            rr.timed_run(rr.Cell(n, "learned", config, out / "runs" / f"learned-n{n}", args.episodes, args.seed,
                                 checkpoint=args.checkpoint, shape=args.shape), progress, f"learned N={n}")
            for n in ns
        ]
        learned = with_pace({"set": "learned", "per_n": per_n, **pooled(per_n)},
                            [out / "runs" / f"learned-n{n}" for n in ns], floors, ns)

    ranked = sorted(results, key=rank_key)
    tuned = ranked[0]
    (out / f"tuned-{args.row}.toml").write_text(
        f"# Scripted tuned for '{args.row}': gain set {tuned['set']} of {len(results)}, success {tuned['success']:.3f}, "
        f"mean steps {tuned['steps']:.1f} at N = {args.n}, {args.episodes} episodes from seed {args.seed}\n"
        "# (scripts/gain_search.py; the most successful set, ties broken by fewer steps)\n"
        + rr.to_toml({"baseline": tuned["gains"]})
    )
    with open(out / "search.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["set", *rr.GAIN_NAMES, "n", "success", "collisions", "steps_to_goal"])
        for r in results + ([learned] if learned else []):
            for n, s in zip(ns, r["per_n"]):
                gains = [r["gains"][g] for g in rr.GAIN_NAMES] if "gains" in r else [""] * len(rr.GAIN_NAMES)
                w.writerow([r["set"], *gains, n, *(["", "", ""] if s is None else
                            [s["success_rate"], s["collision_rate"], s.get("mean_steps_to_goal")])])
    json.dump({"row": args.row, "reality": reality, "ns": ns, "episodes": args.episodes, "seed": args.seed,
               "results": results, "learned": learned, "tuned": tuned["set"], "pace_floors": floors},
              open(out / "search.json", "w"), indent=1, default=str)
    title = f"gain search, {rr.ROW_TITLES[args.row]}: {len(results)} sets, {args.episodes} episodes/N from seed {args.seed}"
    plot(results, learned, tuned, ns, title, out / "front.png", floors)

    print(f"### Gain search: {rr.ROW_TITLES[args.row]} (N = {args.n}, {args.episodes} episodes each from seed {args.seed})\n")
    print("| rank | set | k_form | k_goal | k_turn | repulsion_range | k_repulsion | success | collisions | steps to goal | x floor |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for i, r in enumerate(ranked):
        g = r["gains"]
        note = " (defaults)" if r["set"] == 0 else (" (issue's softer)" if r["set"] == 1 else (" (local)" if r["local"] else ""))
        print(f"| {i + 1} | {r['set']}{note} | {g['k_form']} | {g['k_goal']} | {g['k_turn']} | {g['repulsion_range']} | "
              f"{g['k_repulsion']} | {r['success']:.2f} | {r['collisions']:.2f} | {rr.fmt_steps(None if math.isinf(r['steps']) else r['steps'])} | "
              f"{fmt_ratio(r['x_floor'])} |")
    if learned:
        print(f"| - | learned | | | | | | {learned['success']:.2f} | {learned['collisions']:.2f} | "
              f"{rr.fmt_steps(None if math.isinf(learned['steps']) else learned['steps'])} | {fmt_ratio(learned['x_floor'])} |")
        beaten_by = front_check(results, learned) if math.isfinite(learned["steps"]) else results
        print(f"\nFront check (a set with success >= learned - 0.02 in < 1.2x the learned steps beats it): "
              + ("learned not beaten" if not beaten_by else "beaten by set(s) " + ", ".join(str(r["set"]) for r in beaten_by)))
    if floors is not None:
        mean_floor = {n: sum(b for b in floors[n] if b is not None) / max(1, sum(b is not None for b in floors[n])) for n in ns}
        print("\nPace floor (formation-pace-floor: no controller reaches the goal sooner on these episodes): "
              + ", ".join(f"N = {n} {mean_floor[n]:.1f}" for n in ns) + " steps; 'x floor' is a team's steps over "
              "the floor's on its successful episodes. A policy beats a set by the front check's 1.2x only at "
              "the set's 'x floor' / 1.2 or less: below 1.0 no controller can be.")
    failed = sum(r["failed_runs"] for r in results)
    if failed:
        print(f"\n{failed} run(s) failed: see {out}/runs/*.log")
    print(f"\ntuned: {out}/tuned-{args.row}.toml (set {tuned['set']}); front: {out}/front.png; all runs: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
