"""The ctypes mirrors match the Rust payloads: layout.json is what a Rust unit test
(core/src/layout.rs) keeps equal to the build; here every mirror is compared with it, and the
observation models it lists are checked as the Python side reads them."""

import ctypes
import json
import math
import re
import subprocess
from pathlib import Path

import pytest

import formation_swarm
import formation_swarm.run
from formation_swarm import wire


LAYOUT = json.loads((Path(wire.__file__).parent / "layout.json").read_text())

SCALARS = {"u8": ctypes.c_uint8, "u32": ctypes.c_uint32, "u64": ctypes.c_uint64, "f32": ctypes.c_float,
           "f64": ctypes.c_double}


def ctype_of(spelled: str):
    """``u32``, ``f32[16]``, ``f32[64][3]`` or a payload's type name, as a ctypes type."""
    match = re.fullmatch(r"(\w+)((?:\[\d+\])*)", spelled)
    if match is None:
        for cls in wire.PAYLOADS.values():
            if cls.type_name() == spelled:
                return cls
        raise AssertionError(f"no mirror has type name {spelled}")
    t = SCALARS[match.group(1)]
    for dim in reversed([int(d) for d in re.findall(r"\[(\d+)\]", match.group(2))]):
        t = t * dim
    return t


def test_every_rust_payload_has_a_mirror():
    assert sorted(p["rust"] for p in LAYOUT["payloads"]) == sorted(wire.PAYLOADS)


@pytest.mark.parametrize("payload", LAYOUT["payloads"], ids=lambda p: p["rust"])
def test_mirror_matches_the_rust_layout(payload):
    cls = wire.PAYLOADS[payload["rust"]]
    assert cls.type_name() == payload["type_name"]
    assert ctypes.sizeof(cls) == payload["size"], "size"
    assert ctypes.alignment(cls) == payload["align"], "alignment"
    assert [name for name, _ in cls._fields_] == [f["name"] for f in payload["fields"]], "field order"
    for name, ctype in cls._fields_:
        field = next(f for f in payload["fields"] if f["name"] == name)
        assert getattr(cls, name).offset == field["offset"], f"offset of {name}"
        assert getattr(cls, name).size == field["size"], f"size of {name}"
        expected = ctype_of(field["type"])
        assert ctypes.sizeof(ctype) == ctypes.sizeof(expected) and (
            ctype is expected or getattr(ctype, "_type_", None) == getattr(expected, "_type_", None)
            or ctype.__name__ == expected.__name__
        ), f"type of {name}: {ctype} vs {field['type']}"


def test_iceoryx2_declares_the_rust_type_names():
    """The bindings take the type name from ``type_name()``, as the service builder sends it."""
    import iceoryx2 as iox2

    for cls in wire.PAYLOADS.values():
        assert iox2.get_type_name(cls) == cls.type_name()


def test_constants_match():
    for name, value in LAYOUT["constants"].items():
        assert getattr(wire, name) == value, name
    assert formation_swarm.PROTOCOL_VERSION == LAYOUT["protocol_version"]


def test_layout_file_matches_the_binaries():
    """layout.json equals what this checkout's formation-layout binary prints (when built)."""
    from conftest import bin_dir

    binary = bin_dir() / "formation-layout"
    if not binary.is_file():
        pytest.skip(f"{binary} not built (cargo build --workspace --bins builds it)")
    printed = subprocess.run([str(binary)], check=True, capture_output=True, text=True).stdout
    assert json.loads(printed) == LAYOUT
    version = subprocess.run([str(binary), "--protocol-version"], check=True, capture_output=True, text=True)
    assert int(version.stdout) == wire.PROTOCOL_VERSION


def test_every_observation_model_is_laid_out_without_gaps():
    """layout.json's observation models: blocks one after another filling ``dim`` floats, a
    dimension of its own for each model (the baseline tells them apart by it), the wire's room."""
    models = LAYOUT["observation_models"]
    assert [m["name"] for m in models] == list(wire.OBSERVATION_MODELS)
    assert len({m["dim"] for m in models}) == len(models)
    for model in models:
        end = 0
        for block in model["blocks"]:
            assert block["offset"] == end, (model["name"], block["name"])
            end += len(block["fields"])
        assert end == model["dim"] <= wire.MAX_OBS_DIM, model["name"]
        assert wire.observation_layout(model["dim"]).name == model["name"]
    assert formation_swarm.run.OBSERVATION_DIMS == {m["name"]: m["dim"] for m in models}


def test_the_baseline_reads_where_the_layout_says():
    """Every model's observation of the same scene gives the same command when its slot is the
    goal minus the triangle's centroid (what the paper's model falls back to), whatever the
    blocks' offsets: the baseline takes them from layout.json."""
    paper = wire.OBSERVATION_MODELS["paper"]
    slot = wire.OBSERVATION_MODELS["slot"]
    scene = {("neighbour_0", "x"): -1.0, ("neighbour_0", "y"): 0.5, ("neighbour_0", "cos"): 1.0,
             ("neighbour_0", "desired"): 1.1, ("neighbour_1", "x"): -1.0, ("neighbour_1", "y"): -0.5,
             ("neighbour_1", "cos"): 1.0, ("neighbour_1", "desired"): 1.1, ("goal", "x"): 2.0,
             ("goal", "y"): 0.3}
    centroid = ((-1.0 - 1.0) / 3, (0.5 - 0.5) / 3)
    scene[("slot", "x")], scene[("slot", "y")] = 2.0 - centroid[0], 0.3 - centroid[1]

    def observation(layout):
        obs = [0.0] * layout.dim
        for (block, field), value in scene.items():
            at = layout.index(block, field)
            if at is not None:
                obs[at] = value
        return obs

    baseline = formation_swarm.Baseline()
    v, w = baseline(observation(paper))
    assert v > 0.0
    assert baseline(observation(slot)) == pytest.approx((v, w))


def test_baseline_matches_the_rust_unit_tests():
    """The hand-made observations of core/src/baseline.rs's tests, same answers."""
    paper = wire.OBSERVATION_MODELS["paper"]

    def obs_with(neighbours, desired, goal):
        obs = [0.0] * paper.dim
        for k in range(wire.NEIGHBOURS):
            block = f"neighbour_{k}"
            obs[paper.index(block, "x")], obs[paper.index(block, "y")] = neighbours[k]
            obs[paper.index(block, "cos")] = 1.0
            obs[paper.index(block, "desired")] = desired[k]
        obs[paper.index("goal", "x")], obs[paper.index("goal", "y")] = goal
        return obs

    baseline = formation_swarm.Baseline()
    v, w = baseline(obs_with([(-1.0, 0.5), (-1.0, -0.5)], [1.25 ** 0.5] * 2, (2.0, 0.0)))
    assert abs(v - 0.5) < 1e-9 and abs(w) < 1e-6
    v, w = baseline(obs_with([(0.0, 1.0), (0.0, -1.0)], [1.0, 1.0], (-2.0, 0.5)))
    assert v == 0.0 and abs(w - 1.0) < 1e-9
    ux, _ = baseline.desired_velocity(obs_with([(2.0, 0.0), (0.0, 1.0)], [1.0, 1.0], (2 / 3, 1 / 3)))
    assert ux > 1.0


def test_the_baseline_pushes_away_from_the_obstacles_it_scans():
    """slot_proximity_scan: rays reading under obstacle_range_m (0.5 m) push back along the ray
    by k_obstacle (0.5 m - range), except a hit on a tracked neighbour; a clear scan changes
    nothing against slot_proximity (the same floats without the scan)."""
    scan_model = wire.OBSERVATION_MODELS["slot_proximity_scan"]
    plain = wire.OBSERVATION_MODELS["slot_proximity"]
    scan = scan_model.span("scan")
    assert scan.stop - scan.start == 16

    def observation(layout, neighbour_0=(-1.0, 0.5)):
        obs = [0.0] * layout.dim
        for block, (x, y) in (("neighbour_0", neighbour_0), ("neighbour_1", (-1.0, -0.5)),
                              ("goal", (2.0, 0.0)), ("slot", (2.0, 0.0))):
            obs[layout.index(block, "x")], obs[layout.index(block, "y")] = x, y
        for block in ("neighbour_0", "neighbour_1"):
            obs[layout.index(block, "cos")] = 1.0
            obs[layout.index(block, "desired")] = 1.25 ** 0.5
        if layout.span("scan") is not None:
            obs[layout.span("scan")] = [1.0] * 16
        return obs

    baseline = formation_swarm.Baseline()  # scan range 2 m: a reading of 0.15 is 0.3 m
    clear = observation(scan_model)
    assert baseline(clear) == pytest.approx(baseline(observation(plain)))
    ux, uy = baseline.desired_velocity(clear)
    near = list(clear)
    near[scan.start + 0] = 0.15  # straight ahead at 0.3 m: pushed back by 0.2
    near[scan.start + 4] = 0.3  # to the left at 0.6 m: out of range
    near[scan.start + 12] = 0.2  # to the right at 0.4 m: pushed left by 0.1
    assert baseline.desired_velocity(near) == pytest.approx((ux - 0.2, uy + 0.1))
    # The same ray ahead, its hit on neighbour 0 (0.3 m ahead): a robot, not an obstacle.
    tracked = observation(scan_model, neighbour_0=(0.3, 0.0))
    hit = list(tracked)
    hit[scan.start + 0] = 0.15
    assert baseline.desired_velocity(hit) == pytest.approx(baseline.desired_velocity(tracked))


def scan_observation(slot=(2.0, 0.0), hits=(), stretch=0.0):
    """The Rust tests' `scan_obs`: a `slot_proximity_scan` observation with neighbours behind left
    and right at their desired distances less `stretch`, the slot (and goal) at `slot`, every ray
    clear but `hits` (ray, metres; the scan reads 2 m)."""
    layout = wire.OBSERVATION_MODELS["slot_proximity_scan"]
    scan = layout.span("scan")
    obs = [0.0] * layout.dim
    for block, (x, y) in (("neighbour_0", (-1.0, 0.5)), ("neighbour_1", (-1.0, -0.5)),
                          ("goal", slot), ("slot", slot)):
        obs[layout.index(block, "x")], obs[layout.index(block, "y")] = x, y
    for block in ("neighbour_0", "neighbour_1"):
        obs[layout.index(block, "cos")] = 1.0
        obs[layout.index(block, "desired")] = 1.25 ** 0.5 - stretch
    obs[scan] = [1.0] * 16
    for ray, metres in hits:
        obs[scan.start + ray] = metres / 2.0
    return obs


def test_the_baseline_s_obstacle_options_match_the_rust_tests():
    """core/src/baseline.rs's tests of k_circulation, brake_range_m and obstacle_yield, on the
    same observations: the same answers."""
    observation = scan_observation
    plain = formation_swarm.Baseline()
    circulating = formation_swarm.Baseline(k_circulation=2.0)
    ux, uy = plain.desired_velocity(observation(hits=[(0, 0.3)]))
    assert circulating.desired_velocity(observation(hits=[(0, 0.3)])) == pytest.approx((ux, uy + 0.4))
    right = observation(hits=[(12, 0.3)])
    assert circulating.desired_velocity(right) == pytest.approx(plain.desired_velocity(right))
    px, py = plain.desired_velocity(observation(slot=(0.0, 2.0), hits=[(4, 0.3)]))
    assert circulating.desired_velocity(observation(slot=(0.0, 2.0), hits=[(4, 0.3)])) == pytest.approx((px - 0.4, py))

    braking = formation_swarm.Baseline(brake_range_m=0.3)
    assert braking(observation()) == pytest.approx(plain(observation()))
    assert plain(observation())[0] == pytest.approx(0.5)
    assert braking(observation(hits=[(0, 0.3)]))[0] == pytest.approx(0.25)
    assert braking(observation(hits=[(0, 0.15)]))[0] == pytest.approx(0.0, abs=1e-9)
    beside = observation(hits=[(4, 0.15), (2, 0.3)])
    assert braking(beside)[0] == pytest.approx(plain(beside)[0])

    yielding = formation_swarm.Baseline(obstacle_yield=5.0)
    rest_x, _ = formation_swarm.Baseline(k_form=0.0).desired_velocity(observation(hits=[(0, 0.3)], stretch=0.5))
    fx, _ = plain.desired_velocity(observation(hits=[(0, 0.3)], stretch=0.5))
    yx, _ = yielding.desired_velocity(observation(hits=[(0, 0.3)], stretch=0.5))
    assert yx - rest_x == pytest.approx((fx - rest_x) / 2.0)
    assert yielding.desired_velocity(observation(stretch=0.5)) == pytest.approx(plain.desired_velocity(observation(stretch=0.5)))


def test_the_baseline_s_detour_matches_the_rust_test():
    """core/src/baseline.rs's detouring test, on the same observations: the same aims."""
    observation = scan_observation

    def wall_ahead(x):
        rays = [(ray, x / math.cos(2.0 * math.pi * ray / 16)) for ray in (0, 1, 2, 14, 15)]
        return [(ray, r) for ray, r in rays if r < 2.0]

    def bearing(u):
        return math.degrees(math.atan2(u[1], u[0]))

    plain = formation_swarm.Baseline()
    detouring = formation_swarm.Baseline(detour_range_m=2.0)
    u = detouring.desired_velocity(observation((3.0, 0.0), wall_ahead(1.8)))
    assert bearing(u) == pytest.approx(45.0)
    assert math.hypot(*u) == pytest.approx(0.5)
    assert bearing(plain.desired_velocity(observation((3.0, 0.0), wall_ahead(1.8)))) == pytest.approx(0.0, abs=1e-9)
    assert bearing(detouring.desired_velocity(observation((3.0, 0.0), wall_ahead(1.0)))) == pytest.approx(67.5)
    for same in (observation((0.6, 0.0), wall_ahead(1.0)), observation((3.0, 0.0), [(4, 0.3)])):
        assert detouring.desired_velocity(same) == pytest.approx(plain.desired_velocity(same))
