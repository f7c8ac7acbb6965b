"""What scripts/reality_grid.py and scripts/gain_search.py share: the grid's conditions (rows),
writing a run's config (a TOML file with `[reality]` and `[baseline]` sections over an optional
base config), running one eval cell through scripts/run_swarm.sh and reading its summary.json.

Every cell is a real multi-process run: `scripts/run_swarm.sh N --mode eval --viewer off ...`.
FORMATION_BIN_DIR=DIR in the environment runs prebuilt binaries (e.g. target/debug).
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: The baseline's gains in `BaselineGains` order (core/src/baseline.rs), with its defaults.
GAIN_NAMES = ("k_form", "k_goal", "k_turn", "repulsion_range", "k_repulsion")
DEFAULT_GAINS = {"k_form": 1.5, "k_goal": 0.6, "k_turn": 2.5, "repulsion_range": 0.5, "k_repulsion": 3.0}

#: The grid's rows in order, each "alone" row keeping only these keys of the field preset.
EFFECT_KEYS = {
    "noise": ("position_noise_m", "heading_noise_rad"),
    "delay": ("actuation_delay_ticks",),
    "lag": ("max_linear_accel_mps2", "max_angular_accel_radps2"),
    "loss": ("command_loss", "observation_loss"),
}
ROW_NAMES = ("ideal", "noise", "delay", "lag", "loss", "delay-3-4", "lab", "field", "field-failure")
# Past the field preset's 1-3 ticks: the delay the shipped gain schedule does not hold (it picks
# its gains from the noise it sees), where a command actor does (docs/RESULTS.md).
LONG_DELAY = {"actuation_delay_ticks": [3, 4]}
ROW_TITLES = {
    "ideal": "ideal",
    "noise": "noise alone (field)",
    "delay": "delay alone (field)",
    "lag": "motor lag alone (field)",
    "loss": "loss alone (field)",
    "delay-3-4": "delay 3-4 ticks alone",
    "lab": "lab",
    "field": "field",
    "field-failure": "field + controller failure, stop",
}


def preset_path(name: str) -> Path:
    """configs/reality-NAME.toml, or configs/reality/NAME.toml where the presets lived first."""
    for candidate in (ROOT / "configs" / f"reality-{name}.toml", ROOT / "configs" / "reality" / f"{name}.toml"):
        if candidate.is_file():
            return candidate
    raise SystemExit(f"error: no reality preset '{name}' (configs/reality-{name}.toml)")


def read_reality(path: Path) -> dict:
    """The `[reality]` section of a TOML file."""
    with open(path, "rb") as f:
        section = tomllib.load(f).get("reality")
    if not isinstance(section, dict):
        raise SystemExit(f"error: {path} has no [reality] section")
    return section


def rows(field_preset: Path, lab_preset: Path) -> dict[str, dict]:
    """Every row's `[reality]` section ({} for the ideal world), in ROW_NAMES order."""
    fld, lab = read_reality(field_preset), read_reality(lab_preset)
    out: dict[str, dict] = {"ideal": {}}
    for effect, keys in EFFECT_KEYS.items():
        out[effect] = {key: fld[key] for key in keys if key in fld}
    out["delay-3-4"] = dict(LONG_DELAY)
    out["lab"] = dict(lab)
    out["field"] = dict(fld)
    out["field-failure"] = {**fld, "controller_failure": 1.0, "dead_robot": "stop"}
    return out


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")


def to_toml(config: dict) -> str:
    """A config of tables of plain values (what the run configs hold) as TOML text."""
    lines: list[str] = []
    for name, table in config.items():
        if not isinstance(table, dict):
            raise TypeError(f"top-level key {name!r} is not a table")
        lines.append(f"[{name}]")
        for key, value in table.items():
            if isinstance(value, dict):
                raise TypeError(f"nested table {name}.{key} is not supported")
            lines.append(f"{key} = {_toml_value(value)}")
        lines.append("")
    return "\n".join(lines)


def load_base(path: Path | None) -> dict:
    """The base config every cell starts from (--config), or {}."""
    if path is None:
        return {}
    with open(path, "rb") as f:
        return tomllib.load(f)


def cell_config(base: dict, reality: dict, gains: dict | None) -> dict:
    """The base config with `[reality]` (left out when empty: the ideal world) and `[baseline]`."""
    config = {name: dict(table) for name, table in base.items()}
    if reality:
        config["reality"] = {**config.get("reality", {}), **reality}
    if gains is not None:
        config["baseline"] = {**config.get("baseline", {}), **gains}
    return config


@dataclass
class Cell:
    """One eval run: N robots, a team, a config file, E episodes from a seed."""

    n: int
    team: str  # "scripted" (the baseline on every robot, with the config's [baseline]) or "learned"
    config: Path
    run_dir: Path
    episodes: int
    seed: int
    checkpoint: Path | None = None
    shape: str | None = None
    extra: list[str] = field(default_factory=list)

    def command(self) -> list[str]:
        """The scripts/run_swarm.sh command line of this cell."""
        cmd = [
            str(ROOT / "scripts" / "run_swarm.sh"), str(self.n), "--mode", "eval",
            "--episodes", str(self.episodes), "--seed", str(self.seed), "--viewer", "off",
            "--run-dir", str(self.run_dir), "--config", str(self.config),
        ]
        if self.team == "scripted":
            cmd += ["--scripted", "all"]
        elif self.checkpoint is not None:
            cmd += ["--checkpoint", str(self.checkpoint)]
        if self.shape:
            cmd += ["--shape", self.shape]
        return cmd + self.extra


def run_cell(cell: Cell) -> dict | None:
    """Runs the cell; its summary.json, or None (the log says why) when the run failed."""
    cell.run_dir.parent.mkdir(parents=True, exist_ok=True)
    log = cell.run_dir.with_suffix(".log")
    with open(log, "w") as out:
        out.write(" ".join(cell.command()) + "\n")
        out.flush()
        done = subprocess.run(cell.command(), stdout=out, stderr=subprocess.STDOUT, cwd=ROOT)
    summary = cell.run_dir / "summary.json"
    if done.returncode != 0 or not summary.is_file():
        return None
    with open(summary) as f:
        return json.load(f)


class Progress:
    """One line per finished cell on stderr: count, elapsed time, an estimate of what is left."""

    def __init__(self, total: int):
        self.total, self.done, self.start = total, 0, time.monotonic()

    def step(self, label: str, summary: dict | None, seconds: float) -> None:
        self.done += 1
        elapsed = time.monotonic() - self.start
        left = elapsed / self.done * (self.total - self.done)
        result = "FAILED (see its .log)" if summary is None else (
            f"success {summary['success_rate']:.2f}, steps {fmt_steps(summary.get('mean_steps_to_goal'))}"
        )
        print(
            f"[{self.done:>{len(str(self.total))}}/{self.total}] {label}: {result} ({seconds:.1f} s; "
            f"{elapsed / 60:.1f} min elapsed, ~{left / 60:.1f} min left)",
            file=sys.stderr, flush=True,
        )


def timed_run(cell: Cell, progress: Progress, label: str) -> dict | None:
    """run_cell with a progress line."""
    start = time.monotonic()
    summary = run_cell(cell)
    progress.step(label, summary, time.monotonic() - start)
    return summary


def fmt_steps(steps) -> str:
    """Steps to goal, or '-' when no episode succeeded."""
    return "-" if steps is None else f"{steps:.1f}"


def steps_or_inf(summary: dict) -> float:
    """Mean steps to goal, infinity when nothing succeeded (ranks last)."""
    steps = summary.get("mean_steps_to_goal")
    return math.inf if steps is None else float(steps)


def bin_dir() -> Path:
    """Where the binaries are: FORMATION_BIN_DIR, or the release build scripts/run_swarm.sh makes."""
    if os.environ.get("FORMATION_BIN_DIR"):
        return Path(os.environ["FORMATION_BIN_DIR"])
    return Path(os.environ.get("CARGO_TARGET_DIR") or ROOT / "target") / "release"


def pace_floors(config: Path, ns: list[int], episodes: int, seed: int, shape: str | None) -> dict[int, list] | None:
    """formation-pace-floor's lower bound on the steps to the goal of each episode the cells of
    `config` play ({n: [steps or None (out of time)]}); None, with a warning, if it cannot run."""
    cmd = [str(bin_dir() / "formation-pace-floor"), "--n", ",".join(map(str, ns)), "--episodes", str(episodes),
           "--seed", str(seed), "--config", str(config)] + (["--shape", shape] if shape else [])
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, check=True)
    except (OSError, subprocess.CalledProcessError) as err:
        print(f"warning: no pace floor ({' '.join(cmd)}: {err})", file=sys.stderr)
        return None
    return {d["n_agents"]: d["floor_steps"] for d in map(json.loads, done.stdout.splitlines())}


def pace_over_floor(run_dir: Path, floors: list) -> tuple[int, int]:
    """(steps, floor steps) summed over the run's successful episodes (episodes.csv)."""
    steps = floor = 0
    with open(run_dir / "episodes.csv") as f:
        for row in csv.DictReader(f):
            bound = floors[int(row["episode"])]
            if row["outcome"] == "success" and bound is not None:
                steps, floor = steps + int(row["steps"]), floor + bound
    return steps, floor


def bin_dir_note() -> str:
    """Which binaries the cells run (FORMATION_BIN_DIR or run_swarm.sh's release build)."""
    return os.environ.get("FORMATION_BIN_DIR") or "release (built by scripts/run_swarm.sh)"


def add_cell_options(ap) -> None:
    """The options every cell of the grid and the gain search shares: the learned model, the
    base config, the presets and the shape."""
    ap.add_argument("--checkpoint", type=Path, help="learned model (default: the launcher's shipped model)")
    ap.add_argument("--config", type=Path, help="base config under every run")
    ap.add_argument("--field", type=Path, help="field preset (default configs/reality-field.toml)")
    ap.add_argument("--lab", type=Path, help="lab preset (default configs/reality-lab.toml)")
    ap.add_argument("--shape", help="formation shape of every episode (default: the config's)")


def parse_list(text: str, kind=int) -> list:
    """'3,12,32' -> [3, 12, 32]."""
    return [kind(part) for part in text.split(",") if part.strip()]
