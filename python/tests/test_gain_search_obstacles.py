"""scripts/gain_search.py --obstacles KIND: the potential field's seven gains searched with
formation-play (FORMATION_BIN_DIR, default target/debug)."""

import csv
import math
import os
import random
import subprocess
import sys
import tomllib
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"
sys.path.insert(0, str(SCRIPTS))
sys.dont_write_bytecode = True
import gain_search  # noqa: E402


def search(out, env=None, extra=()):
    return subprocess.run(
        [sys.executable, str(SCRIPTS / "gain_search.py"), "--obstacles", "forest", "--n", "4,8", "--episodes", "3",
         "--seed", "2000", "--sets", "3", "--refine", "2", "--out", str(out), *extra],
        capture_output=True, text=True, timeout=600, env=env,
    )


def test_ties_in_success_go_to_fewer_collisions_before_fewer_steps():
    safe = {"success": 0.5, "collisions": 0.1, "steps": 400.0}
    fast = {"success": 0.5, "collisions": 0.3, "steps": 200.0}
    better = {"success": 0.6, "collisions": 0.9, "steps": 500.0}
    assert sorted([fast, safe, better], key=gain_search.obstacle_rank_key) == [better, safe, fast]


def test_a_forest_search_tunes_all_seven_gains_and_refines_around_its_best(tmp_path):
    out = tmp_path / "search"
    done = search(out)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = list(csv.DictReader(open(out / "search.csv")))
    assert [(int(r["set"]), int(r["n"])) for r in rows] == [(k, n) for k in range(5) for n in (4, 8)]
    names = list(gain_search.OBSTACLE_RANGES)
    sets = {}
    for r in rows:
        sets.setdefault(int(r["set"]), {"gains": {g: float(r[g]) for g in names}, "per_n": []})["per_n"].append(
            {"episodes": 3, "success_rate": float(r["success"]), "collision_rate": float(r["collisions"]),
             "mean_steps_to_goal": float(r["steps_to_goal"]) if r["steps_to_goal"] else None})
    scored = [{**s, "set": k, **gain_search.pooled(s["per_n"])} for k, s in sets.items()]
    assert sets[0]["gains"] == gain_search.OBSTACLE_GAINS
    # The first local set is the best of the three coarse sets, perturbed by the local stream
    # (--search-seed 7 + 1) in all seven ranges.
    best = min(scored[:3], key=gain_search.obstacle_rank_key)
    assert sets[3]["gains"] == gain_search.perturbed(best["gains"], random.Random(8), ranges=gain_search.OBSTACLE_RANGES)
    tuned = tomllib.load(open(out / "tuned-forest.toml", "rb"))
    assert tuned["baseline"] == min(scored, key=gain_search.obstacle_rank_key)["gains"]
    assert "--obstacles forest" in (out / "tuned-forest.toml").read_text()
    assert (out / "front.png").is_file()
    assert all(math.isfinite(float(r["obstacle_collisions"])) for r in rows)


def test_a_missing_formation_play_is_named(tmp_path):
    done = search(tmp_path / "search", env={**os.environ, "FORMATION_BIN_DIR": str(tmp_path / "nowhere")})
    assert done.returncode != 0 and "formation-play" in done.stderr


def test_a_circulating_search_starts_from_the_given_field_and_tunes_all_ten_gains(tmp_path):
    start = tmp_path / "start.toml"
    start.write_text("[baseline]\nk_turn = 3.0\nk_circulation = 1.5\nbrake_range_m = 0.4\n")
    out = tmp_path / "search"
    done = search(out, extra=["--circulating", "--start", str(start)])
    assert done.returncode == 0, done.stderr[-2000:]
    rows = list(csv.DictReader(open(out / "search.csv")))
    names = list(gain_search.CIRCULATING_RANGES)
    assert len(names) == 10 and all(name in rows[0] for name in names)
    first = {g: float(rows[0][g]) for g in names}
    assert first == {**gain_search.CIRCULATING_GAINS, "k_turn": 3.0, "k_circulation": 1.5, "brake_range_m": 0.4}
    tuned = tomllib.load(open(out / "tuned-forest.toml", "rb"))["baseline"]
    assert set(tuned) == set(names)
    assert "10 gains" in (out / "tuned-forest.toml").read_text()


def test_start_keys_outside_the_search_are_refused(tmp_path):
    start = tmp_path / "start.toml"
    start.write_text("[baseline]\nk_circulation = 1.5\n")
    done = search(tmp_path / "search", extra=["--start", str(start)])
    assert done.returncode != 0 and "k_circulation" in done.stderr


def test_a_detouring_search_tunes_the_detour_reach_as_an_eleventh_gain(tmp_path):
    start = tmp_path / "start.toml"
    start.write_text("[baseline]\nk_circulation = 1.5\ndetour_range_m = 1.2\n")
    out = tmp_path / "search"
    done = search(out, extra=["--detouring", "--start", str(start)])
    assert done.returncode == 0, done.stderr[-2000:]
    rows = list(csv.DictReader(open(out / "search.csv")))
    names = list(gain_search.DETOURING_RANGES)
    assert len(names) == 11 and names[-1] == "detour_range_m" and all(name in rows[0] for name in names)
    first = {g: float(rows[0][g]) for g in names}
    assert first == {**gain_search.DETOURING_GAINS, "k_circulation": 1.5, "detour_range_m": 1.2}
    lo, hi = gain_search.DETOURING_RANGES["detour_range_m"]
    assert all(lo <= float(r["detour_range_m"]) <= hi for r in rows)
    tuned = tomllib.load(open(out / "tuned-forest.toml", "rb"))["baseline"]
    assert set(tuned) == set(names)
    # Without --detouring the reach is not searched: a start naming it is refused.
    refused = search(tmp_path / "plain", extra=["--circulating", "--start", str(start)])
    assert refused.returncode != 0 and "detour_range_m" in refused.stderr
