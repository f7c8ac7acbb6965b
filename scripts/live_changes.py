#!/usr/bin/env python3
"""Live changes at scale: beside a real-time eval run, one control-service change per episode,
sent once the episode reaches --at-tick: a new formation (a shape drawn from --shapes, a random
orientation) or a robot removed (a random one; it is back in the next episode). Prints the
run's outcomes: success, collisions, timeouts, changes acknowledged and refused, mean ticks to
re-form.

  scripts/live_changes.py 32 --episodes 20 --seed 1000 --out runs/live-32
  scripts/live_changes.py 16 --kind remove --scripted --episodes 20 --out runs/live-remove-16

The run is `scripts/run_swarm.sh N --mode eval --realtime --viewer off` with an [env] of
--max-steps ticks (room to re-form after the change). FORMATION_BIN_DIR=DIR runs prebuilt
binaries (e.g. target/debug).
"""

from __future__ import annotations

import argparse
import json
import math
import random
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "python"))
sys.dont_write_bytecode = True
import formation_swarm as fs  # noqa: E402
import reality_runs as rr  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("n", type=int, help="robots in the swarm")
    ap.add_argument("--episodes", type=int, default=20, help="episodes (default 20)")
    ap.add_argument("--seed", type=int, default=1000, help="episode seed (default 1000)")
    ap.add_argument("--kind", choices=("formation", "remove"), default="formation",
                    help="the change: a new formation (default) or a robot removed")
    ap.add_argument("--shapes", default="ring,line,wedge,grid,random", help="shapes a new formation is drawn from")
    ap.add_argument("--at-tick", type=int, default=20, help="the change is sent at this tick of each episode (default 20)")
    ap.add_argument("--max-steps", type=int, default=400, help="env.max_steps of the run (default 400)")
    ap.add_argument("--scripted", action="store_true", help="the baseline on every robot (default: the shipped model)")
    ap.add_argument("--out", type=Path, required=True, help="the run directory")
    args = ap.parse_args()
    if args.n < 3 or args.episodes < 1 or args.at_tick < 1:
        ap.error("N must be at least 3, --episodes and --at-tick at least 1")

    args.out.parent.mkdir(parents=True, exist_ok=True)
    config = args.out.with_suffix(".toml")
    config.write_text(rr.to_toml({"env": {"max_steps": args.max_steps}}))
    cmd = rr.Cell(args.n, "scripted" if args.scripted else "learned", config, args.out, args.episodes, args.seed,
                  extra=["--realtime"]).command()
    log = args.out.with_suffix(".log")
    rng = random.Random(args.seed)
    shapes = [s for s in args.shapes.split(",") if s]
    acks = refused = 0
    with open(log, "w") as out:
        run = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT)
        try:
            with fs.Observer(args.out, connect_timeout=600) as observer, fs.Control(args.out) as control:
                changed = None
                for state in observer.states(timeout=120.0):
                    if state.run_end or run.poll() is not None:
                        break
                    if state.episode == changed or state.tick < args.at_tick or state.outcome_name != "running":
                        continue
                    changed = state.episode
                    try:
                        if args.kind == "formation":
                            control.set_formation(rng.choice(shapes), orientation=rng.uniform(-math.pi, math.pi))
                        else:
                            control.remove_robot(rng.randrange(args.n))
                        acks += 1
                    except fs.ControlRefused as why:
                        refused += 1
                        print(f"episode {state.episode}: refused: {why.reason}", file=sys.stderr)
                    print(f"episode {state.episode}: change sent at tick {state.tick}", file=sys.stderr, flush=True)
        finally:
            status = run.wait(timeout=600) if run.poll() is None else run.returncode
    if status != 0:
        print(f"live_changes.py: error: the run failed (status {status}); see {log}", file=sys.stderr)
        return 2
    summary = json.loads((args.out / "summary.json").read_text())
    result = {
        "n": args.n, "kind": args.kind, "team": "scripted" if args.scripted else "learned",
        "episodes": summary["episodes"], "changes_acknowledged": acks, "changes_refused": refused,
        "success": summary["success_rate"], "collisions": summary["collision_rate"], "timeouts": summary["timeout_rate"],
        "reconfigurations": summary["reconfigurations"], "mean_reform_ticks": summary["mean_reform_ticks"],
    }
    (args.out / "live_changes.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
