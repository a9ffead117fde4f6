"""Environment steps per second of ``OverhangTower-v0``, on the default physics and the static physics.

Two agents, or three, play paper20 tasks (drawn by the environment's generator):

* ``legal`` draws one of the world's legal actions at x resolution 0.1 (whole episodes; the towers
  a learner meets once it has learned the rules);
* ``sample`` draws from the action space (mostly illegal, so mostly one-step episodes: the
  environment's own overhead);
* with ``--policy PATH``, ``policy`` samples a saved policy's actions (``planner=policy``'s files):
  the towers a trained agent builds, near the edge of stability, where the default physics runs the
  reference most.

Both physics are timed side by side in one run, each from a fresh world (a cold physics cache);
the verdicts of the default ``tiered`` physics near a tipping point cost a full-window PyBullet
run, so it is timed on fewer steps. The last line is one JSON object.

    python -m overhang_framework.bench.env
    python -m overhang_framework.bench.env --steps 2000 --tiered-steps 1000 --policy runs/ppo/policy.zip
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence

import numpy as np


def measure(physics: str, agent: str, steps: int, seed: int = 0, policy: str | None = None) -> dict:
    """Play ``steps`` environment steps with ``agent``; the figures."""
    import gymnasium as gym

    from overhang_framework.envs import ENV_ID
    from overhang_framework.rules import random_legal_action

    model = spaces = None
    if agent == "policy":
        import torch

        from overhang_framework.envs.policies import load_policy, policy_action

        torch.set_num_threads(1)
        torch.manual_seed(seed)
        model, spaces, _ = load_policy(policy)
    env = gym.make(ENV_ID, tasks="paper20", physics=physics, **(spaces.spec() if spaces else {}))
    world = env.unwrapped.world
    rng = np.random.default_rng(seed)
    env.action_space.seed(seed)
    obs, _ = env.reset(seed=seed)
    episodes = falls = illegal = 0
    started = time.perf_counter()
    for _ in range(steps):
        if agent == "legal":
            state = env.unwrapped.state
            a = random_legal_action(state.geometry, state.next_width, 0.1, rng)
            action = {"x": np.array([a.x], np.float32), "layer": a.layer}
        elif agent == "policy":
            action = policy_action(model, spaces, env.observation_space, obs, env.unwrapped.state,
                                   deterministic=False)
        else:
            action = env.action_space.sample()
        obs, _, done, _, info = env.step(action)
        if done:
            episodes += 1
            falls += not info["stable"]
            illegal += info["illegal"] is not None
            obs, _ = env.reset()
    seconds = time.perf_counter() - started
    stages = (world.stats().get("cache") or {}).get("backend") or {}
    env.close()
    return {"physics": physics, "agent": agent, "steps": steps, "seconds": round(seconds, 3),
            "steps_per_second": round(steps / seconds, 1), "episodes": episodes, "collapses": falls,
            "illegal": illegal, "reference_runs": int(stages.get("reference", 0))}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m overhang_framework.bench.env", description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=2000, help="steps per static-physics measurement (default 2000)")
    parser.add_argument("--tiered-steps", type=int, default=1000,
                        help="steps per default-physics measurement (default 1000)")
    parser.add_argument("--policy", help="a saved policy (.zip) to time as a third agent")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quiet", action="store_true", help="print only the JSON line")
    args = parser.parse_args(argv)
    for name in ("steps", "tiered_steps"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1, got {getattr(args, name)}")
    agents = ("legal", "sample") + (("policy",) if args.policy else ())
    if args.policy:
        from overhang_framework.envs.policies import PolicyFileError, policy_info

        try:
            policy_info(args.policy)
        except PolicyFileError as err:
            parser.error(str(err))
    rows = []
    for agent in agents:
        for physics, steps in (("tiered", args.tiered_steps), ("static", args.steps)):
            rows.append(measure(physics, agent, steps, args.seed, args.policy))
            if not args.quiet:
                r = rows[-1]
                print(f"{agent:<7} {physics:<7} {r['steps_per_second']:>9.1f} steps/s  ({r['steps']} steps in "
                      f"{r['seconds']:.1f} s; {r['episodes']} episodes, {r['collapses']} collapses, "
                      f"{r['illegal']} illegal; {r['reference_runs']} reference runs)", flush=True)
    by = {(r["agent"], r["physics"]): r["steps_per_second"] for r in rows}
    if not args.quiet:
        for agent in agents:
            print(f"{agent}: static / default = {by[(agent, 'static')] / by[(agent, 'tiered')]:.1f}x")
    print(json.dumps({"rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
