#!/usr/bin/env python3
"""Two controllers compared on the same episodes, episode by episode.

Each of A and B is a directory that `formation-play --out DIR` wrote (one nN.csv per swarm size,
a row per episode), or a directory holding several of them (e.g. one per obstacle kind), played
on the same seeds and episodes. Every CSV under A is paired with the one at the same relative
path under B, and every episode with the same episode. For each file and over all of them it
prints the two success rates, the episodes B gained and lost against A, the difference and its
paired standard deviation: two files whose means differ by less than about twice that are not
told apart by these episodes. Where the CSVs hold formation-play's `episode_return` (the
undiscounted sum of the training reward) the mean returns are paired the same way.

  for k in forest trap; do
    formation-play --team model --checkpoint A.safetensors --config C --obstacles $k --n 4,8,16 \\
        --episodes 100 --seed 6168263 --out runs/cmp/a/$k
    formation-play --team model --checkpoint B.safetensors --config C --obstacles $k --n 4,8,16 \\
        --episodes 100 --seed 6168263 --out runs/cmp/b/$k
  done
  scripts/paired_compare.py runs/cmp/a runs/cmp/b
"""
from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path


def episodes(path: Path) -> dict[str, tuple[bool, float | None]]:
    """Each episode's success and return (None where the CSV has no `episode_return`) in a
    formation-play CSV, by episode number."""
    with path.open(newline="") as f:
        return {row["episode"]: (row["outcome"] == "success",
                                 float(row["episode_return"]) if row.get("episode_return") else None)
                for row in csv.DictReader(f)}


def mean_and_sd(diffs: list[float]) -> tuple[float, float]:
    """The mean of per-episode differences and its paired standard deviation."""
    n = len(diffs)
    mean = sum(diffs) / n
    var = sum((d - mean) ** 2 for d in diffs) / (n - 1) if n > 1 else 0.0
    return mean, math.sqrt(var / n)


def compare(a: list[bool], b: list[bool]) -> dict[str, float]:
    """Success of A and B on the same episodes, B's gains and losses, the difference and its
    paired standard deviation."""
    n = len(a)
    diff, sd = mean_and_sd([int(y) - int(x) for x, y in zip(a, b)])
    return {"episodes": n, "a": sum(a) / n, "b": sum(b) / n,
            "gained": sum(1 for x, y in zip(a, b) if y and not x),
            "lost": sum(1 for x, y in zip(a, b) if x and not y), "diff": diff, "sd": sd}


def compare_returns(a: list[float], b: list[float]) -> dict[str, float]:
    """Mean return of A and B on the same episodes, the mean of B - A and its paired standard
    deviation."""
    diff, sd = mean_and_sd([y - x for x, y in zip(a, b)])
    return {"return_a": sum(a) / len(a), "return_b": sum(b) / len(b), "return_diff": diff, "return_sd": sd}


def paired_row(a: list[tuple[bool, float | None]], b: list[tuple[bool, float | None]]) -> dict[str, float]:
    """Success compared as `compare` does, and the returns as `compare_returns` does when every
    episode of both has one."""
    row = compare([x[0] for x in a], [y[0] for y in b])
    if all(x[1] is not None for x in a + b):
        row.update(compare_returns([x[1] for x in a], [y[1] for y in b]))
    return row


def by_size(rel: Path) -> tuple[str, int]:
    """A CSV's place in the table: its folder, then its swarm size (n4 before n16)."""
    digits = rel.stem[1:]
    return (str(rel.parent), int(digits) if digits.isdigit() else 0)


def paired(a_dir: Path, b_dir: Path) -> list[tuple[str, dict[str, float]]]:
    """Rows per CSV found under both directories, then the total; exits with the reason when
    the two do not hold the same files and episodes."""
    files = sorted((p.relative_to(a_dir) for p in a_dir.rglob("n*.csv")), key=by_size)
    if not files:
        sys.exit(f"paired_compare.py: no formation-play CSV (nN.csv) under {a_dir}")
    rows, all_a, all_b = [], [], []
    for rel in files:
        if not (b_dir / rel).is_file():
            sys.exit(f"paired_compare.py: {b_dir / rel} is missing: B must be played on the same sizes")
        a, b = episodes(a_dir / rel), episodes(b_dir / rel)
        if a.keys() != b.keys():
            sys.exit(f"paired_compare.py: {rel}: A and B hold different episodes: play both with the same --seed and --episodes")
        keys = sorted(a, key=int)
        rows.append((str(rel), paired_row([a[k] for k in keys], [b[k] for k in keys])))
        all_a += [a[k] for k in keys]
        all_b += [b[k] for k in keys]
    extra = sorted(set(p.relative_to(b_dir) for p in b_dir.rglob("n*.csv")) - set(files))
    if extra:
        sys.exit(f"paired_compare.py: B has files A lacks: {', '.join(map(str, extra))}")
    rows.append(("all", paired_row(all_a, all_b)))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("a", type=Path, help="formation-play --out directory (or a tree of them) of controller A")
    parser.add_argument("b", type=Path, help="the same for controller B, on the same episodes")
    args = parser.parse_args()
    for d in (args.a, args.b):
        if not d.is_dir():
            sys.exit(f"paired_compare.py: {d} is not a directory")
    print("| file | episodes | A | B | B gained | B lost | B - A | paired sd "
          "| A return | B return | B - A return | paired sd |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, r in paired(args.a, args.b):
        returns = (f"{r['return_a']:.1f} | {r['return_b']:.1f} | {r['return_diff']:+.2f} | {r['return_sd']:.2f}"
                   if "return_a" in r else "- | - | - | -")
        print(f"| {name} | {r['episodes']} | {r['a']:.3f} | {r['b']:.3f} | {r['gained']} | {r['lost']} "
              f"| {r['diff']:+.3f} | {r['sd']:.3f} | {returns} |")


if __name__ == "__main__":
    main()
