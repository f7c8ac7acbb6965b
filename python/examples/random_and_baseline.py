"""Drives a real 3-robot swarm through ``formation_swarm.FormationEnv`` (PettingZoo
``ParallelEnv``) with random actions, then with the scripted baseline (ported to Python), and
prints whole-env steps per second (one step = every robot's command for one tick) and the
mean reward of each.

    FORMATION_BIN_DIR=target/debug PYTHONPATH=python \\
        python3 python/examples/random_and_baseline.py --n 3 --steps 3000 --seed 1
"""

from __future__ import annotations

import argparse
import collections
import time

import numpy as np

import formation_swarm as fs


def play(env, steps, choose):
    """``steps`` env steps (episodes restart as they end); returns the figures."""
    rewards, returns, outcomes = [], [], collections.Counter()
    obs, _ = env.reset()
    episode_return = 0.0
    started = time.perf_counter()
    for _ in range(steps):
        if not env.agents:
            returns.append(episode_return)
            episode_return = 0.0
            obs, _ = env.reset()
        obs, reward, terminations, truncations, infos = env.step({a: choose(a, obs[a]) for a in env.agents})
        r = next(iter(reward.values()))  # the team's shared reward
        rewards.append(r)
        episode_return += r
        if not env.agents:
            outcomes[next(iter(infos.values()))["outcome"]] += 1
    elapsed = time.perf_counter() - started
    if not env.agents:
        returns.append(episode_return)
    return {
        "steps/s": steps / elapsed,
        "mean reward/step": float(np.mean(rewards)),
        "mean episode return": float(np.mean(returns)) if returns else float("nan"),
        "episodes": sum(outcomes.values()),
        "outcomes": dict(outcomes),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=3, help="robots (default 3)")
    parser.add_argument("--steps", type=int, default=3000, help="env steps per policy (default 3000)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--shape", default=None, help="run_swarm.sh --shape (default random)")
    args = parser.parse_args()

    with fs.FormationEnv(n=args.n, seed=args.seed, shape=args.shape) as env:
        print(f"run {env.run.run_id}: {env.n} robots, observation {env.run.observation} "
              f"({env.run.observation_dim} floats), actions normalised to v_max {env.run.v_max} m/s, "
              f"w_max {env.run.w_max} rad/s", flush=True)
        rng = np.random.default_rng(args.seed)
        baseline = fs.Baseline.for_run(env.run)
        policies = {
            "random": lambda agent, obs: rng.uniform(-1.0, 1.0, size=2).astype(np.float32),
            "baseline": lambda agent, obs: env.action_from_command(*baseline(obs)),
        }
        for name, choose in policies.items():
            figures = play(env, args.steps, choose)
            print(f"{name:8s} {figures['steps/s']:8.0f} steps/s  mean reward/step {figures['mean reward/step']:+.3f}  "
                  f"mean episode return {figures['mean episode return']:+8.2f}  over {figures['episodes']} episodes "
                  f"{figures['outcomes']}", flush=True)


if __name__ == "__main__":
    main()
