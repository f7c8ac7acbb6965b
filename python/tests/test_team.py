"""Removing and restoring robots through the live control service, from Python, beside a real
scripted run (real processes, paced in real time so that the episode is under way): the
state's presence mask and slot map change at the acknowledged ticks, the robots left re-form
the same formation for fewer robots, bad requests are refused, and once every robot is back
the swarm re-forms and reaches the goal within the episode."""

import csv
import math

import pytest

from formation_swarm import Control, ControlRefused, wire

from conftest import assert_clean, realtime_scripted_run

WATCHDOG_S = 240
N = 6


def neighbours_by_slot(state):
    """Checks that the robots present hold slots 0..M-1 and that each one's desired edges are the
    distances from its slot to the next two modulo M; returns the robots present."""
    present = [r for r in range(N) if state.present[r]]
    m = len(present)
    slot = {r: state.raw.slot[r] for r in present}
    assert sorted(slot.values()) == list(range(m)), slot
    robot_in = {s: r for r, s in slot.items()}
    for r in present:
        for k in range(2):
            other = state.slots[robot_in[(slot[r] + k + 1) % m]]
            want = math.dist(state.slots[r], other)
            assert abs(state.desired[r][k] - want) < 1e-4, (r, k, state.desired[r][k], want)
    for r in range(N):
        if not state.present[r]:
            assert state.raw.slot[r] == wire.SLOT_NONE and state.desired[r] == (0.0, 0.0), r
    return present


def test_robots_removed_and_restored_from_python_leave_and_rejoin_the_formation(tmp_path):
    config = "[env]\nmax_steps = 400  # room to re-form after the changes\n"
    with realtime_scripted_run(tmp_path, N, 5, config, WATCHDOG_S, until_tick=3) as live:
        with Control(live.run) as control:
            removed = control.remove_robot(2)
            control.remove_robot(0)
            control.remove_robot(1)
            for bad, why in [(lambda: control.remove_robot(3), "fewer than 3"),
                             (lambda: control.remove_robot(2), "already out"),
                             (lambda: control.remove_robot(9), "no robot 9"),
                             (lambda: control.restore_robot(4), "already in")]:
                with pytest.raises(ControlRefused, match=why):
                    bad()
            control.restore_robot(0)
            control.restore_robot(1)
            restored = control.restore_robot(2)
    swarm, world = live.swarm, live.world

    episode = [s for s in world if not s.run_end and s.episode == 0]
    by_tick = {s.tick: s for s in episode}
    assert removed.episode == 0 and restored.episode == 0
    assert removed.tick < restored.tick
    # Every robot in until the removal's tick; from it on robot 2 is out, the five left on a
    # formation of five (neighbours modulo 5).
    assert all(all(by_tick[t].present) for t in by_tick if t < removed.tick)
    assert neighbours_by_slot(by_tick[removed.tick - 1]) == list(range(N))
    assert neighbours_by_slot(by_tick[removed.tick]) == [0, 1, 3, 4, 5]
    # At most three out at once (three stay), and every tick's slot map is consistent.
    assert min(sum(s.present) for s in episode) == 3
    for s in episode:
        neighbours_by_slot(s)
    # From the last restoration on, all six are in again.
    assert all(all(by_tick[t].present) for t in by_tick if t >= restored.tick)
    assert not all(by_tick[restored.tick - 1].present)
    # Re-formed with every robot: the episode ends in success.
    assert episode[-1].outcome_name == "success", episode[-1]
    rows = list(csv.DictReader((swarm.run_dir / "episodes.csv").open()))
    assert rows[0]["outcome"] == "success"
    assert int(rows[0]["departures"]) == 3 and int(rows[0]["returns"]) == 3, rows[0]
    assert_clean(swarm)
