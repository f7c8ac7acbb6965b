"""The Observer's slot map (``WorldState.slot``): read from the state payload, and from a real
run whose formation changes twice an episode (8 scripted robots, paced in real time so the
observer keeps up): at each tick the desired edges are those of the slots the map names, and
the mission planner's reassignments show in it."""

import math

from formation_swarm import wire
from formation_swarm.observer import WorldState

from conftest import assert_clean, realtime_scripted_run

WATCHDOG_S = 240
N = 8


def test_the_slot_map_and_its_inverse_come_from_the_payload():
    raw = wire.State()
    raw.n_agents = 4
    for robot, slot in enumerate([2, 0, 3, 1]):
        raw.slot[robot] = slot
    state = WorldState.from_payload(raw)
    assert state.slot == [2, 0, 3, 1]
    assert state.robot_in_slot == [1, 3, 0, 2]
    # Robot r observes the robots in slots s+1 and s+2: robot 0 (slot 2) sees slots 3 and 0.
    assert state.observed[0] == (2, 1)
    # A robot out of the formation (a slot past N) holds none; the others wrap around 3 slots.
    raw.n_agents = 4
    for robot, slot in enumerate([1, 0xFFFFFFFF, 2, 0]):
        raw.slot[robot] = slot
    state = WorldState.from_payload(raw)
    assert state.slot == [1, None, 2, 0]
    assert state.robot_in_slot == [3, 0, 2]
    assert state.observed == [(2, 3), (1, 1), (3, 0), (0, 2)]


def edges_follow_the_slot_map(state: WorldState) -> None:
    """Each robot's desired edges are the distances from its slot to its observed robots'."""
    for robot, pair in enumerate(state.observed):
        for k, other in enumerate(pair):
            want = math.dist(state.slots[robot], state.slots[other])
            assert abs(state.desired[robot][k] - want) < 1e-4, (state.tick, robot, k, state.slot)


def test_a_run_with_shape_changes_shows_its_reassignments_in_the_slot_map(tmp_path):
    with realtime_scripted_run(tmp_path, N, 1000, "[env]\nshape_changes = 2\n", WATCHDOG_S) as live:
        pass  # the observer reads the whole run as the block ends
    swarm, world = live.swarm, live.world
    episode = [s for s in world if s.episode == 0]
    assert episode, swarm.output
    maps = []
    for state in episode:
        assert sorted(state.slot) == list(range(N)), state.slot
        edges_follow_the_slot_map(state)
        if not maps or maps[-1] != state.slot:
            maps.append(state.slot)
    assert episode[0].tick > 0 or episode[0].slot == list(range(N)), "robot i starts in slot i"
    # Two changes: the map moved away from robot i in slot i at least once.
    assert any(m != list(range(N)) for m in maps), maps
    assert_clean(swarm)
