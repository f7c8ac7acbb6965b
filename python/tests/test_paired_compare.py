"""scripts/paired_compare.py: two controllers' formation-play rows paired episode by episode."""

import math
import sys
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"
sys.path.insert(0, str(SCRIPTS))
sys.dont_write_bytecode = True
import paired_compare  # noqa: E402


def write(path: Path, outcomes: list[str]) -> None:
    """A formation-play CSV with these outcomes, episodes numbered from 0."""
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = ["episode,outcome,steps"] + [f"{i},{o},100" for i, o in enumerate(outcomes)]
    path.write_text("\n".join(rows) + "\n")


def test_gains_losses_and_the_paired_sd_are_counted_episode_by_episode(tmp_path):
    s, t = "success", "timeout"
    write(tmp_path / "a/forest/n4.csv", [s, s, t, t, s])
    write(tmp_path / "b/forest/n4.csv", [s, t, s, s, s])
    write(tmp_path / "a/forest/n16.csv", [s, t])
    write(tmp_path / "b/forest/n16.csv", [s, t])
    rows = dict(paired_compare.paired(tmp_path / "a", tmp_path / "b"))
    assert list(rows) == ["forest/n4.csv", "forest/n16.csv", "all"]
    n4 = rows["forest/n4.csv"]
    assert (n4["a"], n4["b"], n4["gained"], n4["lost"]) == (0.6, 0.8, 2, 1)
    # Differences 0, -1, +1, +1, 0: mean 0.2, sample variance (3 - 5 * 0.04) / 4 = 0.7.
    assert n4["diff"] == pytest.approx(0.2)
    assert n4["sd"] == pytest.approx(math.sqrt(0.7 / 5))
    total = rows["all"]
    assert (total["episodes"], total["gained"], total["lost"]) == (7, 2, 1)
    assert total["diff"] == pytest.approx(1 / 7)


def test_other_episodes_or_a_missing_size_are_refused_with_the_reason(tmp_path):
    write(tmp_path / "a/n4.csv", ["success", "success"])
    write(tmp_path / "b/n4.csv", ["success", "success", "success"])
    with pytest.raises(SystemExit, match="different episodes"):
        paired_compare.paired(tmp_path / "a", tmp_path / "b")
    write(tmp_path / "a/n8.csv", ["success"])
    write(tmp_path / "b/n4.csv", ["success", "success"])
    with pytest.raises(SystemExit, match="missing"):
        paired_compare.paired(tmp_path / "a", tmp_path / "b")
    with pytest.raises(SystemExit, match="no formation-play CSV"):
        paired_compare.paired(tmp_path / "b" / "none", tmp_path / "a")
