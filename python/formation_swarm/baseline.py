"""The scripted baseline (``core/src/baseline.rs``) in Python: a distance-based formation
controller from the robot's own observation, tracked by a unicycle, with a potential field
among obstacles when the observation has a range sensor (``slot_proximity_scan``). An example
policy.

Where each quantity sits in the observation comes from ``layout.json`` (``wire.OBSERVATION_MODELS``),
never from indices written here."""

from __future__ import annotations

import functools
import math
from typing import NamedTuple, Optional, Sequence, Tuple

from . import wire


class _Indices(NamedTuple):
    """The floats the baseline reads, for one observation model."""

    neighbours: Tuple[Tuple[int, int, int], ...]  # each tracked neighbour's x, y, desired
    goal: Tuple[int, int]
    slot: Optional[Tuple[int, int]]
    proximity: Optional[Tuple[int, int]]
    scan: Optional[slice]


@functools.lru_cache(maxsize=None)
def _indices(dim: int) -> _Indices:
    layout = wire.observation_layout(dim)

    def point(block: str) -> Optional[Tuple[int, int]]:
        x = layout.index(block)
        return None if x is None else (x, layout.index(block, "y"))

    neighbours = tuple(
        (layout.index(f"neighbour_{k}"), layout.index(f"neighbour_{k}", "y"),
         layout.index(f"neighbour_{k}", "desired"))
        for k in range(wire.NEIGHBOURS)
    )
    return _Indices(neighbours, point("goal"), point("slot"), point("proximity"), layout.span("scan"))


#: How far from a tracked robot's centre a ray's hit still counts as that robot, beyond its
#: radius, metres (``TRACKED_HIT_SLACK_M``).
TRACKED_HIT_SLACK_M = 0.1
#: The gap a braking robot keeps to the hit ahead, metres, beyond its radius (``BRAKE_MARGIN_M``).
BRAKE_MARGIN_M = 0.05
#: How many directions a detouring robot tries (``DETOUR_DIRECTIONS``).
DETOUR_DIRECTIONS = 64
#: Neighbouring rays' hits closer than this are one surface to a detouring robot, metres
#: (``DETOUR_JOIN_M``).
DETOUR_JOIN_M = 1.0


class Baseline:
    """``policy(obs) -> (v, w)``; the observation model follows from ``len(obs)`` (each model's
    dimension is its own, see ``wire.OBSERVATION_MODELS``). Gains are the Rust defaults.

    ``scan_range`` (``env.scan_range_m``) and ``robot_radius`` (half ``env.eps_coll_m``) are the
    range sensor's, read only with a scan: each ray whose range is below ``obstacle_range_m``
    pushes back along the ray by ``k_obstacle (obstacle_range_m - range)``, unless its hit lies
    within ``robot_radius`` + 0.1 m of a robot the observation tracks (a neighbour, the nearest
    other robot).

    The four obstacle options of ``[baseline]`` (0: off) are the Rust ones: ``k_circulation``
    (every push from a robot or a ray that blocks the aim also pushes a quarter turn to the left
    of it, by k_circulation x shortfall x how squarely it blocks), ``obstacle_yield`` (the
    formation pull divided by 1 + obstacle_yield x |obstacle push|), ``brake_range_m`` (the
    forward speed cut to v_max x (free distance ahead - 0.05 m) / brake_range_m) and
    ``detour_range_m`` (when the way to the slot is blocked that far, aim at the first of 64
    directions, turning left, whose way is clear, with the formation pull off; see
    :meth:`detour`)."""

    def __init__(self, v_max: float = 0.5, w_max: float = 1.0, proximity_range: float = 1.0,
                 k_form: float = 1.5, k_goal: float = 0.6, k_turn: float = 2.5,
                 repulsion_range: float = 0.5, k_repulsion: float = 3.0, k_obstacle: float = 1.0,
                 obstacle_range_m: float = 0.5, scan_range: float = 2.0, robot_radius: float = 0.1,
                 k_circulation: float = 0.0, obstacle_yield: float = 0.0, brake_range_m: float = 0.0,
                 detour_range_m: float = 0.0) -> None:
        self.v_max, self.w_max, self.proximity_range = v_max, w_max, proximity_range
        self.k_form, self.k_goal, self.k_turn = k_form, k_goal, k_turn
        self.repulsion_range, self.k_repulsion = repulsion_range, k_repulsion
        self.k_obstacle, self.obstacle_range_m = k_obstacle, obstacle_range_m
        self.scan_range, self.robot_radius = scan_range, robot_radius
        self.k_circulation, self.obstacle_yield, self.brake_range_m = k_circulation, obstacle_yield, brake_range_m
        self.detour_range_m = detour_range_m

    @classmethod
    def for_run(cls, run) -> "Baseline":
        """The baseline with the robot limits of a run (``formation_swarm.connect(...)``); the
        range sensor's are the defaults (run.json does not carry them)."""
        return cls(run.v_max, run.w_max, run.proximity_range_m)

    def desired_velocity(self, obs: Sequence[float]) -> Tuple[float, float]:
        """The desired planar velocity in the robot's frame."""
        at = _indices(len(obs))
        neighbours = [(float(obs[x]), float(obs[y]), float(obs[d])) for x, y, d in at.neighbours]
        if at.slot is not None:  # the robot's own slot in the goal formation
            tx, ty = float(obs[at.slot[0]]), float(obs[at.slot[1]])
        else:  # the goal minus the centroid of the robot's triangle (exact for N = 3)
            share = len(neighbours) + 1.0
            tx = float(obs[at.goal[0]]) - sum(q[0] for q in neighbours) / share
            ty = float(obs[at.goal[1]]) - sum(q[1] for q in neighbours) / share
        fx = fy = ux = uy = 0.0
        robots = list(neighbours)  # neighbours (i+1) and (i+2), then the nearest other robot
        if at.proximity is not None:  # nearest untracked robot as (1 - d/R) * unit vector
            nx, ny = float(obs[at.proximity[0]]), float(obs[at.proximity[1]])
            closeness = math.hypot(nx, ny)
            if closeness > 0.0:
                dist = (1.0 - closeness) * self.proximity_range
                robots.append((nx / closeness * dist, ny / closeness * dist, None))
        detour = None
        if at.scan is not None and self.detour_range_m > 0.0:
            detour = self.detour(obs[at.scan], [(q[0], q[1]) for q in robots], (tx, ty))
        aim = detour if detour is not None else _unit(tx, ty)
        for qx, qy, desired in robots:
            dist = max(math.hypot(qx, qy), 1e-6)
            towards = (qx / dist, qy / dist)
            if desired is not None:
                pull = self.k_form * (dist - desired)
                fx, fy = fx + pull * towards[0], fy + pull * towards[1]
            shortfall = max(self.repulsion_range - dist, 0.0)
            px, py = self._away(towards, self.k_repulsion * shortfall, shortfall, aim)
            ux, uy = ux + px, uy + py
        formation_share = 1.0
        if at.scan is not None:
            px, py = self.obstacle_push(obs[at.scan], [(q[0], q[1]) for q in robots], aim)
            ux, uy = ux + px, uy + py
            formation_share = 1.0 / (1.0 + self.obstacle_yield * math.hypot(px, py))
        if detour is not None:
            formation_share = 0.0
        speed = min(self.k_goal * math.hypot(tx, ty), self.v_max)
        gx, gy = speed * aim[0], speed * aim[1]
        return ux + formation_share * fx + gx, uy + formation_share * fy + gy

    def _away(self, towards, strength: float, shortfall: float, aim) -> Tuple[float, float]:
        """``strength`` straight away from the unit direction ``towards`` and, with circulation,
        sideways (a quarter turn to its left) by how squarely it blocks the unit ``aim``."""
        blocking = max(towards[0] * aim[0] + towards[1] * aim[1], 0.0)
        sideways = self.k_circulation * shortfall * blocking
        return (-strength * towards[0] - sideways * towards[1], -strength * towards[1] + sideways * towards[0])

    def obstacle_push(self, scan: Sequence[float], tracked: Sequence[Tuple[float, float]],
                      aim: Tuple[float, float] = (1.0, 0.0)) -> Tuple[float, float]:
        """The potential field's push from the rays of ``scan`` (normalised ranges, ray k at
        2 pi k / len(scan) from the heading) that read less than ``obstacle_range_m``, leaving
        out hits near a ``tracked`` robot's centre (robot frame); with circulation, also
        sideways around hits that block the unit ``aim``."""
        px = py = 0.0
        for (c, s), distance in _rays(scan, self.scan_range):
            if distance >= self.obstacle_range_m:
                continue
            if self._explained(distance * c, distance * s, tracked):
                continue
            shortfall = self.obstacle_range_m - distance
            rx, ry = self._away((c, s), self.k_obstacle * shortfall, shortfall, aim)
            px, py = px + rx, py + ry
        return px, py

    def _explained(self, hx: float, hy: float, tracked: Sequence[Tuple[float, float]]) -> bool:
        """Whether a ray's hit (robot frame) lies on a ``tracked`` robot (within its radius and
        some slack)."""
        return any(math.hypot(hx - qx, hy - qy) < self.robot_radius + TRACKED_HIT_SLACK_M for qx, qy in tracked)

    def detour(self, scan: Sequence[float], tracked: Sequence[Tuple[float, float]],
               target: Tuple[float, float]) -> Optional[Tuple[float, float]]:
        """Where a detouring robot aims instead of its ``target`` (robot frame): ``None`` when the
        way to it is clear for ``detour_range_m`` (or up to the target, if nearer), else the first
        of 64 directions, turning left from the target's, whose way is clear that far (``None``
        if none is). A way is blocked when it passes within ``robot_radius`` + 0.1 m of what the
        scan sees: each hit no ``tracked`` robot explains, as a surface across half the ray
        spacing either side at its range, and the segment joining two neighbouring rays' hits
        less than 1 m apart (the rays are sparse; a wall between them is not read)."""
        reach = min(self.detour_range_m, math.hypot(*target))
        half = math.pi / len(scan)
        hits = []
        for k, ((c, s), distance) in enumerate(_rays(scan, self.scan_range)):
            seen_here = distance < self.scan_range and not self._explained(distance * c, distance * s, tracked)
            hits.append((2.0 * half * k, distance) if seen_here else None)

        def at(angle, distance):
            return distance * math.cos(angle), distance * math.sin(angle)

        seen = [(at(angle - half, r), at(angle + half, r)) for angle, r in filter(None, hits)]
        for k, hit in enumerate(hits):
            after = hits[(k + 1) % len(hits)]
            if hit is not None and after is not None and math.dist(at(*hit), at(*after)) < DETOUR_JOIN_M:
                seen.append((at(*hit), at(*after)))
        clearance = self.robot_radius + TRACKED_HIT_SLACK_M

        def clear(bearing: float) -> bool:
            end = (reach * math.cos(bearing), reach * math.sin(bearing))
            return all(_segment_distance((0.0, 0.0), end, a, b) >= clearance for a, b in seen)

        bearing = math.atan2(target[1], target[0])
        if clear(bearing):
            return None
        for k in range(1, DETOUR_DIRECTIONS):
            way = bearing + 2.0 * math.pi * k / DETOUR_DIRECTIONS
            if clear(way):
                return math.cos(way), math.sin(way)
        return None

    def free_distance_ahead(self, scan: Sequence[float]) -> float:
        """How far the robot drives straight ahead before its disc reaches a ray's hit (robot or
        obstacle) within its radius + 0.1 m of its path, metres; the scan's reach without one."""
        free = self.scan_range
        for (c, s), distance in _rays(scan, self.scan_range):
            if c > 1e-9 and abs(distance * s) < self.robot_radius + TRACKED_HIT_SLACK_M:
                free = min(free, max(distance * c - self.robot_radius, 0.0))
        return free

    def __call__(self, obs: Sequence[float]) -> Tuple[float, float]:
        """The (v, w) command, clamped to the robot's limits; never drives backwards."""
        ux, uy = self.desired_velocity(obs)
        bearing = math.atan2(uy, ux)
        v = min(max(math.hypot(ux, uy) * math.cos(bearing), 0.0), self.v_max)
        scan = _indices(len(obs)).scan
        if self.brake_range_m > 0.0 and scan is not None:
            free = self.free_distance_ahead(obs[scan]) - BRAKE_MARGIN_M
            v = min(v, self.v_max * min(max(free / self.brake_range_m, 0.0), 1.0))
        w = min(max(self.k_turn * bearing, -self.w_max), self.w_max)
        return v, w


def _segment_distance(p, q, a, b) -> float:
    """The distance between segments pq and ab (either may be a point)."""
    def cross(o, u, v):
        return (u[0] - o[0]) * (v[1] - o[1]) - (u[1] - o[1]) * (v[0] - o[0])

    def to_point(x, u, v):
        dx, dy = v[0] - u[0], v[1] - u[1]
        length2 = dx * dx + dy * dy
        t = 0.0 if length2 == 0.0 else min(max(((x[0] - u[0]) * dx + (x[1] - u[1]) * dy) / length2, 0.0), 1.0)
        return math.hypot(x[0] - u[0] - t * dx, x[1] - u[1] - t * dy)

    d1, d2, d3, d4 = cross(p, q, a), cross(p, q, b), cross(a, b, p), cross(a, b, q)
    if d1 * d2 < 0.0 and d3 * d4 < 0.0:
        return 0.0
    return min(to_point(p, a, b), to_point(q, a, b), to_point(a, p, q), to_point(b, p, q))


def _unit(x: float, y: float) -> Tuple[float, float]:
    length = math.hypot(x, y)
    return (x / length, y / length) if length > 0.0 else (0.0, 0.0)


def _rays(scan: Sequence[float], scan_range: float):
    """Each ray as its unit direction (ray k at 2 pi k / len(scan) from the heading) and its
    range in metres."""
    for k, reading in enumerate(scan):
        angle = 2.0 * math.pi * k / len(scan)
        yield (math.cos(angle), math.sin(angle)), float(reading) * scan_range
