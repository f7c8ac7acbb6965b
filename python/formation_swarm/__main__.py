"""``python -m formation_swarm``: play a robot slot or watch a running swarm.

    python -m formation_swarm robot RUN_DIR INDEX [--policy baseline|MODULE:CALLABLE|FILE.safetensors]
    python -m formation_swarm observe RUN_DIR [--count K]
    python -m formation_swarm ros2-node INDEX [--endpoint tcp/127.0.0.1:7447] [--namespace formation] [--domain 0]
                                              [--policy CHECKPOINT.safetensors]
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys

from . import Baseline, FormationError, Observer, connect, run_robot


def _load_policy(spec: str, run, index: int = 0):
    if spec == "baseline":
        return Baseline.for_run(run)
    if spec.endswith(".safetensors"):
        from .policy import NumpyActor

        actor = NumpyActor.from_file(spec, agent=index, v_max=run.v_max, w_max=run.w_max,
                                     proximity_range=run.proximity_range_m)
        actor.check_observation(run.observation, run.observation_dim)
        return actor
    module, _, attr = spec.partition(":")
    if not attr:
        raise FormationError(f"--policy must be 'baseline', MODULE:CALLABLE or FILE.safetensors, got {spec!r}")
    policy = getattr(importlib.import_module(module), attr)
    # A class or factory taking no argument yields the policy; a plain function is the policy.
    return policy() if isinstance(policy, type) else policy


def _ros2_node(args) -> int:
    from .ros2 import Ros2Node

    try:
        policy = None
        if args.policy is not None:
            from .policy import NumpyActor

            policy = NumpyActor.from_file(args.policy, agent=args.index, v_max=args.v_max, w_max=args.w_max)
        node = Ros2Node(args.index, args.endpoint, args.namespace, args.domain, policy=policy)
    except FormationError as err:
        print(f"formation_swarm: error: {err}", file=sys.stderr)
        return 1
    print(f"robot {args.index}: ROS 2 node /{node.namespace}/{node.node_name} on domain {args.domain}, "
          f"zenoh {node.zid} dialling {args.endpoint}, policy {policy if policy is not None else 'baseline'}",
          flush=True)
    status = 0
    try:
        node.spin(args.idle_exit)
    except KeyboardInterrupt:
        pass
    except FormationError as err:
        print(f"formation_swarm: error: {err}", file=sys.stderr, flush=True)
        status = 1
    finally:
        print(f"robot {args.index}: sent {node.twists} twists, received {node.odometry_count} odometry messages, "
              f"{node.episodes} episodes", flush=True)
        node.close()
    return status


def _terminate(signum, frame):
    raise KeyboardInterrupt


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m formation_swarm", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    robot = sub.add_parser("robot", help="play one robot slot until the run ends")
    robot.add_argument("run_dir")
    robot.add_argument("index", type=int)
    robot.add_argument("--policy", default="baseline",
                       help="baseline (default), MODULE:CALLABLE, or a checkpoint FILE.safetensors (numpy)")
    robot.add_argument("--connect-timeout", type=float, default=60.0,
                       help="seconds to wait for the launcher's run.json (default 60)")
    observe = sub.add_parser("observe", help="print the live true state")
    observe.add_argument("run_dir")
    observe.add_argument("--count", type=int, default=0, help="stop after K states (default: run end)")
    ros2 = sub.add_parser("ros2-node", help="play a --ros2 robot as a ROS 2 node over rmw_zenoh's wire format "
                                            "(eclipse-zenoh and rosbags, no ROS 2 install), driven by the baseline "
                                            "or by a learned actor (--policy FILE)")
    ros2.add_argument("index", type=int)
    ros2.add_argument("--endpoint", default="tcp/127.0.0.1:7447",
                      help="the Zenoh endpoint of the swarm's ROS 2 side or of a router (default tcp/127.0.0.1:7447)")
    ros2.add_argument("--namespace", default="formation", help="the topics' namespace (default formation)")
    ros2.add_argument("--domain", type=int, default=0, help="ROS_DOMAIN_ID (default 0)")
    ros2.add_argument("--policy", default=None, metavar="FILE",
                      help="a learned actor's safetensors checkpoint (models/formation.safetensors), played in "
                           "numpy; refused if the run observes another model (default: the scripted baseline)")
    ros2.add_argument("--v-max", type=float, default=0.5, help="the run's env.v_max, for --policy (default 0.5)")
    ros2.add_argument("--w-max", type=float, default=1.0, help="the run's env.w_max, for --policy (default 1.0)")
    ros2.add_argument("--idle-exit", type=float, default=None,
                      help="leave after this many seconds without an observation (default: run until stopped)")
    args = parser.parse_args(argv)

    # SIGTERM ends the loop like Ctrl-C: ports and node are released on the way out.
    signal.signal(signal.SIGTERM, _terminate)
    if args.command == "ros2-node":
        return _ros2_node(args)
    try:
        run = connect(args.run_dir, args.connect_timeout if args.command == "robot" else 60.0)
        if args.command == "robot":
            print(f"robot {args.index}: attached to run {run.run_id} ({run.n_agents} robots, "
                  f"{run.observation} observations)", flush=True)
            stats = run_robot(run, args.index, _load_policy(args.policy, run, args.index))
            print(f"robot {args.index}: run ended after {stats.commands} commands in {stats.episodes} episodes",
                  flush=True)
        else:
            with Observer(run) as observer:
                seen = 0
                for state in observer.states(timeout=run.startup_timeout_s):
                    centroid = [sum(p[k] for p in state.poses) / state.n_agents for k in (0, 1)]
                    print(f"episode {state.episode} tick {state.tick} seq {state.sequence} "
                          f"{state.outcome_name} centroid ({centroid[0]:+.2f}, {centroid[1]:+.2f}) "
                          f"goal ({state.goal[0]:+.2f}, {state.goal[1]:+.2f})", flush=True)
                    seen += 1
                    if args.count and seen >= args.count:
                        break
    except FormationError as err:
        print(f"formation_swarm: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("formation_swarm: stopped", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
