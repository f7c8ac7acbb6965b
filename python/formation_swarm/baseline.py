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


class Baseline:
    """``policy(obs) -> (v, w)``; the observation model follows from ``len(obs)`` (each model's
    dimension is its own, see ``wire.OBSERVATION_MODELS``). Gains are the Rust defaults.

    ``scan_range`` (``env.scan_range_m``) and ``robot_radius`` (half ``env.eps_coll_m``) are the
    range sensor's, read only with a scan: each ray whose range is below ``obstacle_range_m``
    pushes back along the ray by ``k_obstacle (obstacle_range_m - range)``, unless its hit lies
    within ``robot_radius`` + 0.1 m of a robot the observation tracks (a neighbour, the nearest
    other robot)."""

    def __init__(self, v_max: float = 0.5, w_max: float = 1.0, proximity_range: float = 1.0,
                 k_form: float = 1.5, k_goal: float = 0.6, k_turn: float = 2.5,
                 repulsion_range: float = 0.5, k_repulsion: float = 3.0, k_obstacle: float = 1.0,
                 obstacle_range_m: float = 0.5, scan_range: float = 2.0, robot_radius: float = 0.1) -> None:
        self.v_max, self.w_max, self.proximity_range = v_max, w_max, proximity_range
        self.k_form, self.k_goal, self.k_turn = k_form, k_goal, k_turn
        self.repulsion_range, self.k_repulsion = repulsion_range, k_repulsion
        self.k_obstacle, self.obstacle_range_m = k_obstacle, obstacle_range_m
        self.scan_range, self.robot_radius = scan_range, robot_radius

    @classmethod
    def for_run(cls, run) -> "Baseline":
        """The baseline with the robot limits of a run (``formation_swarm.connect(...)``); the
        range sensor's are the defaults (run.json does not carry them)."""
        return cls(run.v_max, run.w_max, run.proximity_range_m)

    def desired_velocity(self, obs: Sequence[float]) -> Tuple[float, float]:
        """The desired planar velocity in the robot's frame."""
        at = _indices(len(obs))
        ux = uy = cx = cy = 0.0
        tracked = []
        for x, y, d in at.neighbours:  # neighbours (i+1) and (i+2)
            qx, qy, desired = float(obs[x]), float(obs[y]), float(obs[d])
            tracked.append((qx, qy))
            dist = max(math.hypot(qx, qy), 1e-6)
            pull = self.k_form * (dist - desired)
            push = self.k_repulsion * (self.repulsion_range - dist) if dist < self.repulsion_range else 0.0
            ux += (pull - push) * qx / dist
            uy += (pull - push) * qy / dist
            cx, cy = cx + qx / 3.0, cy + qy / 3.0
        if at.proximity is not None:  # nearest untracked robot as (1 - d/R) * unit vector
            nx, ny = float(obs[at.proximity[0]]), float(obs[at.proximity[1]])
            closeness = math.hypot(nx, ny)
            if closeness > 0.0:
                dist = (1.0 - closeness) * self.proximity_range
                push = self.k_repulsion * max(self.repulsion_range - dist, 0.0)
                ux, uy = ux - push * nx / closeness, uy - push * ny / closeness
                tracked.append((nx / closeness * dist, ny / closeness * dist))
        if at.scan is not None:
            px, py = self.obstacle_push(obs[at.scan], tracked)
            ux, uy = ux + px, uy + py
        if at.slot is not None:  # the robot's own slot in the goal formation
            tx, ty = float(obs[at.slot[0]]), float(obs[at.slot[1]])
        else:  # the goal minus the centroid of the robot's triangle (exact for N = 3)
            tx, ty = float(obs[at.goal[0]]) - cx, float(obs[at.goal[1]]) - cy
        gx, gy = self.k_goal * tx, self.k_goal * ty
        speed = math.hypot(gx, gy)
        if speed > self.v_max:
            gx, gy = gx * self.v_max / speed, gy * self.v_max / speed
        return ux + gx, uy + gy

    def obstacle_push(self, scan: Sequence[float], tracked: Sequence[Tuple[float, float]]) -> Tuple[float, float]:
        """The potential field's push from the rays of ``scan`` (normalised ranges, ray k at
        2 pi k / len(scan) from the heading) that read less than ``obstacle_range_m``, leaving
        out hits near a ``tracked`` robot's centre (robot frame)."""
        px = py = 0.0
        rays = len(scan)
        for k, reading in enumerate(scan):
            distance = float(reading) * self.scan_range
            if distance >= self.obstacle_range_m:
                continue
            c, s = math.cos(2.0 * math.pi * k / rays), math.sin(2.0 * math.pi * k / rays)
            hx, hy = distance * c, distance * s
            if any(math.hypot(hx - qx, hy - qy) < self.robot_radius + TRACKED_HIT_SLACK_M for qx, qy in tracked):
                continue
            strength = self.k_obstacle * (self.obstacle_range_m - distance)
            px, py = px - strength * c, py - strength * s
        return px, py

    def __call__(self, obs: Sequence[float]) -> Tuple[float, float]:
        """The (v, w) command, clamped to the robot's limits; never drives backwards."""
        ux, uy = self.desired_velocity(obs)
        bearing = math.atan2(uy, ux)
        v = min(max(math.hypot(ux, uy) * math.cos(bearing), 0.0), self.v_max)
        w = min(max(self.k_turn * bearing, -self.w_max), self.w_max)
        return v, w
