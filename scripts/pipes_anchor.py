#!/usr/bin/env python3
"""A same-machine anchor for the lockstep benchmark: the swarm's tick shape in plain Python.

One "sim" process and N "robot" processes joined by multiprocessing pipes. Each tick the sim
sends every robot its observation (the wire's 16 floats), each robot answers a command (v, w)
computed from it, the sim waits for every answer and steps unicycle physics. This is what a
Python user would write first; `scripts/bench.sh` prints the swarm's ticks/s against it, so the
ratio holds on any machine.

    scripts/pipes_anchor.py --agents 3 --seconds 5 [--placement auto|off]

Prints one JSON line: ticks, seconds, ticks_per_s, p50_us, p99_us.
"""

import argparse
import json
import math
import os
import time
from multiprocessing import Pipe, Process
from multiprocessing.connection import wait

OBS_FLOATS = 16
DT = 0.1


def robot(conn, cpus):
    """Answers each observation with a proportional command towards the goal it names."""
    if cpus:
        os.sched_setaffinity(0, cpus)
    while True:
        obs = conn.recv()
        if obs is None:
            return
        gx, gy = obs[10], obs[11]
        conn.send((min(0.5, math.hypot(gx, gy)), math.atan2(gy, gx)))


def observation(poses, agent, n):
    """Neighbour offsets and the goal in the robot's frame, padded to the wire's size."""
    x, y, th = poses[agent]
    c, s = math.cos(th), math.sin(th)
    obs = []
    for k in (1, 2):
        nx, ny, nth = poses[(agent + k) % n]
        dx, dy = nx - x, ny - y
        obs += [c * dx + s * dy, -s * dx + c * dy, math.cos(nth - th), math.sin(nth - th), 1.0]
    gx, gy = 5.0 - x, 5.0 - y
    obs += [c * gx + s * gy, -s * gx + c * gy]
    return obs + [0.0] * (OBS_FLOATS - len(obs))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--agents", type=int, default=3, help="robot processes (default 3)")
    parser.add_argument("--seconds", type=float, default=5.0, help="how long to tick (default 5)")
    parser.add_argument(
        "--placement",
        choices=["auto", "off"],
        default="auto",
        help="auto: every process on the last allowed CPU, as the swarm's lockstep; off: the OS places them",
    )
    args = parser.parse_args()
    if args.agents < 1:
        parser.error("--agents must be at least 1")
    cpus = None
    if args.placement == "auto":
        cpus = {max(os.sched_getaffinity(0))}
        os.sched_setaffinity(0, cpus)
    n = args.agents
    links = [Pipe() for _ in range(n)]
    robots = [Process(target=robot, args=(child, cpus), daemon=True) for _, child in links]
    for proc in robots:
        proc.start()
    sim_ends = [parent for parent, _ in links]
    poses = [[float(i), 0.0, 0.0] for i in range(n)]
    durations = []
    started = time.perf_counter()
    while time.perf_counter() - started < args.seconds:
        tick = time.perf_counter()
        for agent, conn in enumerate(sim_ends):
            conn.send(observation(poses, agent, n))
        commands = [None] * n
        pending = dict(zip(sim_ends, range(n)))
        while pending:
            for conn in wait(list(pending)):
                commands[pending.pop(conn)] = conn.recv()
        for pose, (v, w) in zip(poses, commands):
            pose[0] += v * math.cos(pose[2]) * DT
            pose[1] += v * math.sin(pose[2]) * DT
            pose[2] += w * DT
        durations.append(time.perf_counter() - tick)
    elapsed = sum(durations)
    for conn in sim_ends:
        conn.send(None)
    for proc in robots:
        proc.join(timeout=5)
    durations.sort()
    print(
        json.dumps(
            {
                "kind": "python_pipes",
                "n": n,
                "placement": args.placement,
                "ticks": len(durations),
                "seconds": round(elapsed, 3),
                "ticks_per_s": round(len(durations) / elapsed),
                "p50_us": round(durations[len(durations) // 2] * 1e6, 1),
                "p99_us": round(durations[int(len(durations) * 0.99)] * 1e6, 1),
            }
        )
    )


if __name__ == "__main__":
    main()
