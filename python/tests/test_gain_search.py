"""scripts/gain_search.py as a user runs it: a small field search with local refinement, real
runs of scripts/run_swarm.sh (FORMATION_BIN_DIR as for every multi-process test)."""

import csv
import json
import math
import random
import subprocess
import sys
from pathlib import Path

from conftest import root_path, shm_leftovers

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"
sys.path.insert(0, str(SCRIPTS))
sys.dont_write_bytecode = True
import gain_search  # noqa: E402


def test_local_search_sets_stay_in_range_and_are_seeded():
    best = {name: hi for name, (lo, hi) in gain_search.RANGES.items()}
    assert gain_search.perturbed(best, random.Random(3)) == gain_search.perturbed(best, random.Random(3))
    rng = random.Random(5)
    for _ in range(200):
        gains = gain_search.perturbed(best, rng)
        for name, (lo, hi) in gain_search.RANGES.items():
            assert lo <= gains[name] <= hi
    # Not a copy: a perturbation moves every gain off an interior point.
    middle = {name: math.sqrt(lo * hi) for name, (lo, hi) in gain_search.RANGES.items()}
    moved = gain_search.perturbed(middle, random.Random(1))
    assert all(abs(moved[n] - middle[n]) > 1e-4 for n in middle)


def test_a_search_with_refinement_refines_around_its_best(tmp_path):
    out = tmp_path / "search"
    done = subprocess.run(
        [sys.executable, str(SCRIPTS / "gain_search.py"), "--row", "field", "--n", "3", "--episodes", "3",
         "--seed", "2000", "--sets", "3", "--refine", "2", "--no-learned", "--out", str(out)],
        capture_output=True, text=True, timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    rows = list(csv.DictReader(open(out / "search.csv")))
    assert [int(r["set"]) for r in rows] == [0, 1, 2, 3, 4]
    assert all(r["success"] != "" for r in rows), "every set ran"
    # The first local set is the best of the three coarse sets, perturbed by the local stream
    # (--search-seed 7 + 1).
    coarse = [r for r in rows if int(r["set"]) < 3]
    best = min(coarse, key=lambda r: (-float(r["success"]), float(r["steps_to_goal"] or math.inf)))
    expected = gain_search.perturbed({g: float(best[g]) for g in gain_search.rr.GAIN_NAMES}, random.Random(8))
    assert {g: float(rows[3][g]) for g in gain_search.rr.GAIN_NAMES} == expected
    assert "(local)" in done.stdout
    assert (out / "tuned-field.toml").is_file() and (out / "front.png").is_file()
    # The pace floor: one bound per episode, and no set's successful episodes beat it.
    search = json.load(open(out / "search.json"))
    floors = search["pace_floors"]["3"]
    assert len(floors) == 3 and all(isinstance(b, int) and b > 10 for b in floors)
    paced = [r["x_floor"] for r in search["results"] if r["x_floor"] is not None]
    assert paced and all(ratio >= 1.0 for ratio in paced)
    assert "Pace floor" in done.stdout
    for run in (out / "runs").glob("*/run.json"):
        run_id = json.loads(run.read_text())["run_id"]
        assert not shm_leftovers(run_id) and not root_path(run_id).exists()


def test_sets_from_an_earlier_search_plays_its_sets_on_other_episodes(tmp_path):
    def search(*extra):
        out = tmp_path / f"search-{len(list(tmp_path.iterdir()))}"
        done = subprocess.run(
            [sys.executable, str(SCRIPTS / "gain_search.py"), "--row", "field", "--n", "3", "--episodes", "2",
             "--no-learned", "--out", str(out), *extra],
            capture_output=True, text=True, timeout=600,
        )
        assert done.returncode == 0, done.stderr[-2000:]
        return json.load(open(out / "search.json")), out

    first, first_out = search("--seed", "2000", "--sets", "3", "--refine", "1")
    again, _ = search("--seed", "3000", "--sets-from", str(first_out))
    assert [r["gains"] for r in again["results"]] == [r["gains"] for r in first["results"]]
    assert [r["local"] for r in again["results"]] == [False, False, False, True]
    assert again["seed"] == 3000
