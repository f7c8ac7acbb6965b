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


def test_returns_are_paired_where_every_csv_holds_them(tmp_path):
    for side, returns in (("a", [10.0, 20.0, 30.0]), ("b", [12.0, 18.0, 36.0])):
        path = tmp_path / side / "n4.csv"
        path.parent.mkdir(parents=True)
        rows = ["episode,outcome,steps,episode_return"]
        rows += [f"{i},success,100,{r}" for i, r in enumerate(returns)]
        path.write_text("\n".join(rows) + "\n")
    row = dict(paired_compare.paired(tmp_path / "a", tmp_path / "b"))["all"]
    # Differences +2, -2, +6: mean 2, sample variance (0 + 16 + 16) / 2 = 16.
    assert (row["return_a"], row["return_b"]) == (20.0, 22.0)
    assert row["return_diff"] == pytest.approx(2.0)
    assert row["return_sd"] == pytest.approx(math.sqrt(16 / 3))
    write(tmp_path / "c/n4.csv", ["success"] * 3)
    assert "return_a" not in dict(paired_compare.paired(tmp_path / "a", tmp_path / "c"))["all"]


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
