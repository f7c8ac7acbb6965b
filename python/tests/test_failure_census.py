"""scripts/failure_census.py: each failed episode sorted into one cause, from formation-play's
rows and traces (FORMATION_BIN_DIR, default target/debug)."""

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"
sys.path.insert(0, str(SCRIPTS))
sys.dont_write_bytecode = True
import failure_census  # noqa: E402

DISC = {"disc": {"centre": [2.0, 0.0], "radius": 0.3}}


def trace(paths, slots, goal=(10.0, 0.0)):
    """A trace whose robot i follows paths[i] (one (x, y) a tick)."""
    ticks = len(paths[0])
    return {"poses": [[[*path[t], 0.0] for path in paths] for t in range(ticks)], "goal": list(goal),
            "slots": slots, "obstacles": [DISC]}


def timeout():
    return {"outcome": "timeout", "obstacle_collisions": "0"}


def test_a_robot_standing_by_a_disc_far_from_its_slot_has_stalled_and_one_moving_is_on_its_way():
    slots = [[0.0, 0.0], [0.0, 1.0]]
    arrived = [(10.0, 1.0)] * 300
    by_the_disc = [(1.5, 0.0)] * 300
    assert failure_census.cause_of(timeout(), trace([by_the_disc, arrived], slots), 1.0, 0.5, 200) == "stalled"
    # The same robot standing in the open is slow, not stalled.
    in_the_open = [(1.5, 5.0)] * 300
    assert failure_census.cause_of(timeout(), trace([in_the_open, arrived], slots), 1.0, 0.5, 200) == "on its way"
    # Moving past the disc in its last ticks: on its way.
    moving = [(1.5 + 0.01 * t, 0.0) for t in range(300)]
    assert failure_census.cause_of(timeout(), trace([moving, arrived], slots), 1.0, 0.5, 200) == "on its way"
    near_slots = [[(9.5, 0.0)] * 300, arrived]
    assert failure_census.cause_of(timeout(), trace(near_slots, slots), 1.0, 0.5, 200) == "at the goal"
    hit = {"outcome": "collision", "obstacle_collisions": "1"}
    assert failure_census.cause_of(hit, trace(near_slots, slots), 1.0, 0.5, 200) == "hit an obstacle"
    bumped = {"outcome": "collision", "obstacle_collisions": "0"}
    assert failure_census.cause_of(bumped, trace(near_slots, slots), 1.0, 0.5, 200) == "robots collided"


def test_a_wall_s_surface_is_its_distance_less_half_its_thickness():
    wall = {"wall": {"a": [0.0, 0.0], "b": [4.0, 0.0], "thickness": 0.2}}
    assert abs(failure_census.surface_distance((2.0, 1.0), wall) - 0.9) < 1e-12
    assert abs(failure_census.surface_distance((5.0, 0.0), wall) - 0.9) < 1e-12


def test_the_census_sorts_every_failed_episode_formation_play_reports(tmp_path):
    common = ["--team", "scripted", "--obstacles", "forest", "--n", "4", "--episodes", "8", "--seed", "7"]
    causes = tmp_path / "causes.json"
    done = subprocess.run([sys.executable, str(SCRIPTS / "failure_census.py"), *common, "--json", str(causes)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    row = done.stdout.strip().splitlines()[-1].strip("|").split("|")
    successes, counts = int(row[1]), [int(c) for c in row[2:]]
    assert successes + sum(counts) == 8
    binary = Path(os.environ.get("FORMATION_BIN_DIR") or SCRIPTS.parent / "target" / "debug") / "formation-play"
    config = SCRIPTS.parent / "configs" / "obstacles-detouring.toml"  # the census's default
    subprocess.run([str(binary), *common, "--config", str(config), "--out", str(tmp_path / "rows")], check=True,
                   capture_output=True)
    rows = list(csv.DictReader(open(tmp_path / "rows" / "n4.csv")))
    failed = {str(k) for k, r in enumerate(rows) if r["outcome"] != "success"}
    sorted_out = json.loads(causes.read_text())["4"]
    assert set(sorted_out) == failed
    assert all(cause in failure_census.CAUSES for cause in sorted_out.values())
    assert sum(counts) == len(failed)
