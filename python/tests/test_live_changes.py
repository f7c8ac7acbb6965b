"""scripts/live_changes.py as a user runs it: one live formation change per episode beside a
real-time run (FORMATION_BIN_DIR as for every multi-process test)."""

import csv
import json
import subprocess
import sys
from pathlib import Path

from conftest import root_path, shm_leftovers

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"


def test_one_live_change_per_episode_is_sent_obeyed_and_counted(tmp_path):
    out = tmp_path / "live"
    done = subprocess.run(
        [sys.executable, str(SCRIPTS / "live_changes.py"), "6", "--episodes", "2", "--scripted", "--at-tick", "10",
         "--out", str(out)],
        capture_output=True, text=True, timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result == json.loads((out / "live_changes.json").read_text())
    rows = list(csv.DictReader(open(out / "episodes.csv")))
    assert len(rows) == result["episodes"] == 2
    # One change per episode, each acknowledged and in the run's own count.
    assert result["changes_acknowledged"] == 2 and result["changes_refused"] == 0
    assert [int(r["reconfigurations"]) for r in rows] == [1, 1]
    assert result["success"] + result["collisions"] + result["timeouts"] == 1.0
    assert done.stderr.count("change sent at tick") == 2
    run_id = json.loads((out / "run.json").read_text())["run_id"]
    assert not shm_leftovers(run_id) and not root_path(run_id).exists()
