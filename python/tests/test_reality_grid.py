"""scripts/reality_grid.py as a user runs it: a small grid of real runs (FORMATION_BIN_DIR as for
every multi-process test), its table, grid.json and the pace of each cell against the floor."""

import json
import subprocess
import sys
from pathlib import Path

from conftest import root_path, shm_leftovers

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"


def test_a_small_grid_reports_every_cell_with_its_pace_over_the_floor(tmp_path):
    out = tmp_path / "grid"
    done = subprocess.run(
        [sys.executable, str(SCRIPTS / "reality_grid.py"), "--rows", "ideal,delay", "--columns", "scripted",
         "--n", "3", "--episodes", "3", "--out", str(out)],
        capture_output=True, text=True, timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    grid = json.loads((out / "grid.json").read_text())
    cells = {(c["row"], c["n"], c["team"]): c for c in grid["cells"]}
    assert set(cells) == {("ideal", 3, "scripted"), ("delay", 3, "scripted")}
    for cell in cells.values():
        assert cell["summary"]["episodes"] == 3
        # Every successful episode takes at least its floor; the default baseline is not at it.
        assert cell["summary"]["success_rate"] > 0 and 1.0 < cell["x_floor"] < 3.0, cell["x_floor"]
    table = (out / "table.md").read_text()
    assert "| x floor |" in table and f"{cells[('ideal', 3, 'scripted')]['x_floor']:.2f}" in table
    assert (out / "grid.png").is_file()
    for run in (out / "runs").glob("*/run.json"):
        run_id = json.loads(run.read_text())["run_id"]
        assert not shm_leftovers(run_id) and not root_path(run_id).exists()
