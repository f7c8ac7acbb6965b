"""The live control service from Python: a scripted eval run started here (real processes,
paced in real time so that the episode is still under way), the README's example run as it
stands, then the states checked: the desired edges and the slot map change at the tick the
acknowledgement names, the new formation is re-formed and held at the goal within the
episode, and bad requests get a refusal while the run goes on."""

import csv
import math
import re
from pathlib import Path

import pytest

from formation_swarm import Control, ControlRefused

from conftest import REPO, assert_clean, realtime_scripted_run

WATCHDOG_S = 240
N = 6


def readme_example(run_dir: Path) -> str:
    """The README's live-control example, pointed at ``run_dir``."""
    text = (REPO / "README.md").read_text()
    section = text.split("### Live control", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert 'fs.Control("runs/live")' in code
    return code.replace('"runs/live"', repr(str(run_dir)))


def consistent(state):
    """Each robot's desired edges are the distances between its slot and the slots after it."""
    slot = [state.raw.slot[r] for r in range(N)]
    robot_in = {s: r for r, s in enumerate(slot)}
    for r in range(N):
        for k in range(2):
            other = state.slots[robot_in[(slot[r] + k + 1) % N]]
            want = math.dist(state.slots[r], other)
            assert abs(state.desired[r][k] - want) < 1e-4, (r, k, state.desired[r][k], want)
    return slot


def test_a_formation_change_sent_from_python_is_obeyed(tmp_path, capsys):
    config = "[env]\nmax_steps = 400  # room to re-form after the change\n"
    with realtime_scripted_run(tmp_path, N, 5, config, WATCHDOG_S, until_tick=3) as live:
        namespace = {}
        exec(compile(readme_example(live.swarm.run_dir), "README.md", "exec"), namespace)
        ack = namespace["ack"]
        printed = capsys.readouterr().out
        assert f"a line from tick {ack.tick} of episode 0" in printed
        assert 'refused: unknown shape "hexagon"' in printed
        namespace["control"].close()

        with Control(live.run) as control:
            for bad, why in [(lambda: control.set_formation("ring", scale=20.0), "an edge leaves"),
                             (lambda: control.set_formation("mixed"), "mixed is not a shape"),
                             (lambda: control.set_formation("ring", scale=-1.0), "not a positive number"),
                             (lambda: control.set_goal(-100.0, 3.0), "leaves the arena")]:
                with pytest.raises(ControlRefused, match=why):
                    bad()
    swarm, world = live.swarm, live.world

    episode = [s for s in world if not s.run_end and s.episode == 0]
    by_tick = {s.tick: s for s in episode}
    assert ack.episode == 0 and ack.tick >= 4, ack
    before, after = by_tick[ack.tick - 1], by_tick[ack.tick]
    # Until the change every tick seen has the first formation; from its tick on a new one.
    seen_first = min(by_tick)
    first = by_tick[seen_first]
    assert all(by_tick[t].desired == first.desired and by_tick[t].slots == first.slots
               for t in range(seen_first, ack.tick))
    assert after.desired != before.desired, "the desired edges changed at the acknowledged tick"
    consistent(before)
    slot_map = consistent(after)
    assert sorted(slot_map) == list(range(N))
    # It morphs (core's mission planner): the first tick asks for about the geometry the robots
    # stand in, no edge jumps, then the edges move tick by tick to the line's and stay there.
    final = episode[-1]
    jump = lambda a, b: max(abs(x - y) for ra, rb in zip(a.desired, b.desired) for x, y in zip(ra, rb))  # noqa: E731
    assert jump(after, before) < 0.1 < jump(final, before), (jump(after, before), jump(final, before))
    morph_end = min(s.tick for s in episode if s.tick >= ack.tick and s.desired == final.desired)
    assert morph_end > ack.tick + 1, "more than one tick of morph"
    consistent(final)
    # The line: its slots' spread along its main axis is well over its width (two files).
    xs = [p[0] for p in final.slots]
    ys = [p[1] for p in final.slots]
    assert max(xs) - min(xs) > 2.0 * (max(ys) - min(ys)), final.slots
    # The refused requests changed nothing after it.
    assert all(s.desired == final.desired for s in episode if s.tick >= morph_end)
    # Re-formed within the episode: it ends in success, holding the line at the goal.
    assert episode[-1].outcome_name == "success", episode[-1]
    rows = list(csv.DictReader((swarm.run_dir / "episodes.csv").open()))
    assert rows[0]["outcome"] == "success"
    assert int(rows[0]["reconfigurations"]) == 1 and int(rows[0]["reforms"]) == 1, rows[0]
    assert_clean(swarm)
