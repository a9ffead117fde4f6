"""Train a PPO agent on the Overhang Tower environment and compare it with the paper's models.

    python -m overhang_framework.envs.ppo --steps 200000 --out runs/ppo

Needs the ``[rl]`` extra (Stable-Baselines3). Trains on CPU (``--threads``
torch threads, 1 by default: fair on a shared machine) on ``--tasks``
(``random``: a new six-block sequence each episode, so the test set stays
unseen), saves the policy with :func:`~overhang_framework.envs.policies.save_policy`,
then plays ``--test`` (paper20) through the main job with ``planner=policy``
beside the myopic and depth-2 and depth-3 lookahead models (veridical predictor, the same
physics), and writes ``comparison.csv``, ``training.json`` and ``summary.json`` (every figure) to
``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

MODELS = {
    "myopic": ["planner=myopic"],
    "lookahead_d2": ["planner=lookahead", "planner.depth=2"],
    "lookahead_d3": ["planner=lookahead", "planner.depth=3"],
}


def _write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


BENCHMARK = "benchmark:"


def task_kwargs(tasks: str) -> dict:
    """The environment's task arguments for ``--tasks``: a task set, ``random``, or ``benchmark:SPLIT``
    (a split of the benchmark, e.g. ``benchmark:train``: its sequences)."""
    if tasks.startswith(BENCHMARK):
        from overhang_framework.benchmark.splits import sequence_of, split_ids

        return {"sequences": [list(sequence_of(t)) for t in split_ids(tasks[len(BENCHMARK):])]}
    return {"tasks": tasks}


def make_env(tasks: str, physics: str, reward: str, resolution: float, seed: int, n_envs: int,
             max_blocks: int | None = None):
    """The vectorised flat environment PPO trains on."""
    from stable_baselines3.common.env_util import make_vec_env

    from overhang_framework.envs.wrappers import flat_env

    kwargs = {**task_kwargs(tasks), "physics": physics, "reward": reward, "resolution": resolution,
              "max_blocks": max_blocks}
    return make_vec_env(lambda: flat_env(**kwargs), n_envs=n_envs, seed=seed)


def train(args) -> tuple[Path, dict]:
    import numpy as np
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback

    from overhang_framework.envs.policies import save_policy
    from overhang_framework.progress import progress_bar

    torch.set_num_threads(args.threads)
    env = make_env(args.tasks, args.physics, args.reward, args.resolution, args.seed, args.envs, args.max_blocks)

    class Progress(BaseCallback):
        def _on_training_start(self):
            self.curve = []
            # a bar on a terminal, a line now and then in a log file or a pipe
            self.bar = progress_bar(total=args.steps, unit="step", desc="training", file=sys.stderr)

        def _on_step(self):
            self.bar.update(min(self.training_env.num_envs, args.steps - self.bar.n))
            return True

        def _on_rollout_end(self):
            recent = list(self.model.ep_info_buffer)
            if recent:
                self.bar.set_postfix_str(f"return {np.mean([e['r'] for e in recent]):.2f}, "
                                         f"length {np.mean([e['l'] for e in recent]):.2f}")
                self.curve.append((int(self.model.num_timesteps), round(float(np.mean([e['r'] for e in recent])), 3),
                                   round(float(np.mean([e['l'] for e in recent])), 2)))

        def _on_training_end(self):
            self.bar.close()

    model = PPO("MlpPolicy", env, n_steps=args.n_steps, batch_size=256, gamma=1.0, gae_lambda=0.95,
                learning_rate=3e-4, ent_coef=0.0, seed=args.seed, device="cpu", verbose=0,
                policy_kwargs={"log_std_init": args.log_std_init})
    started = time.perf_counter()
    progress = Progress()
    model.learn(total_timesteps=args.steps, callback=progress)
    seconds = time.perf_counter() - started
    figures = {"steps": int(model.num_timesteps), "seconds": round(seconds, 1),
               "steps_per_second": round(model.num_timesteps / seconds, 1), "threads": args.threads,
               "envs": args.envs, "tasks": args.tasks, "max_blocks": args.max_blocks, "physics": args.physics, "reward": args.reward,
               "resolution": args.resolution, "seed": args.seed, "log_std_init": args.log_std_init,
               "curve": [{"steps": n, "return": r, "length": ln} for n, r, ln in progress.curve[:: max(1, len(progress.curve) // 50)]]}
    path = save_policy(model, args.out / "policy.zip", env, training=figures)
    env.close()
    return path, figures


def env_reward(policy: Path, tasks: str, physics: str) -> tuple[float, int]:
    """Mean paper reward of ``policy`` played in the environment on ``tasks`` (an illegal action is a
    failure there), and the number of illegal actions."""
    import gymnasium as gym

    from overhang_framework.envs import ENV_ID
    from overhang_framework.envs.policies import load_policy, policy_action

    model, spaces, _ = load_policy(policy)
    env = gym.make(ENV_ID, tasks=tasks, physics=physics, **spaces.spec())
    total, illegal = 0.0, 0
    for k in range(len(env.unwrapped.tasks)):
        obs, _ = env.reset(seed=k, options={"task": k})
        done = False
        while not done:
            action = policy_action(model, spaces, env.observation_space, obs, env.unwrapped.state)
            obs, reward, done, _, info = env.step(action)
            total += reward
            illegal += info["illegal"] is not None
    env.close()
    return total / len(env.unwrapped.tasks), illegal


def main_job(overrides: list[str], out_dir: Path) -> dict:
    """Run the main job for ``overrides`` into ``out_dir``; its summary."""
    from overhang_framework.app import run
    from overhang_framework.preflight import compose_checked

    cfg = compose_checked(overrides + ["progress=false", "overwrite=true"])
    return run(cfg, out_dir)


def check_settings(args) -> None:
    """The training environment, the physics and the test task set, checked before the training starts
    (:class:`~overhang_framework.errors.OverhangError`, one line, otherwise)."""
    from omegaconf import OmegaConf

    from overhang_framework.envs.wrappers import flat_env
    from overhang_framework.errors import ConfigError
    from overhang_framework.plugins import Registry
    from overhang_framework.preflight import compose_checked
    from overhang_framework.tasks import tasks_from_config

    cfg = compose_checked([f"world.physics={args.physics}", f"tasks={args.test}"])
    Registry().create("world", OmegaConf.to_container(cfg.world, resolve=True))
    tasks_from_config(cfg.tasks)
    try:
        flat_env(**task_kwargs(args.tasks), physics=args.physics, reward=args.reward, resolution=args.resolution,
                 max_blocks=args.max_blocks).close()
    except ValueError as err:  # the environment's own refusal of --tasks or --resolution
        raise ConfigError(f"the training environment: {err}") from None


def parse(argv=None):
    parser = argparse.ArgumentParser(prog="python -m overhang_framework.envs.ppo", description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=200_000, help="environment steps of training (default 200000)")
    parser.add_argument("--out", type=Path, default=Path("runs/ppo"), help="output directory (default runs/ppo)")
    parser.add_argument("--tasks", default="random",
                        help="training tasks: random, a task set, or benchmark:SPLIT (e.g. benchmark:train, the "
                             "benchmark's training split) (default random)")
    parser.add_argument("--max-blocks", type=int, default=None,
                        help="the longest task the policy can play (default: the training tasks' length); "
                             "7 lets a policy trained on 6-block tasks play the benchmark's cross split")
    parser.add_argument("--test", default="paper20", help="task set the agent and the models are compared on")
    parser.add_argument("--physics", default="static", help="world physics for training and test (default static)")
    parser.add_argument("--reward", default="shaped", choices=("paper", "shaped"), help="training reward")
    parser.add_argument("--resolution", type=float, default=0.1, help="x grid of the actions (default 0.1)")
    parser.add_argument("--envs", type=int, default=4, help="environments stepped together (default 4)")
    parser.add_argument("--n-steps", type=int, default=512, help="PPO rollout length per environment")
    parser.add_argument("--log-std-init", type=float, default=-1.5,
                        help="initial log standard deviation of the actions (default -1.5: x spread about 0.9 m)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--compare", default="myopic,lookahead_d2,lookahead_d3",
                        help=f"models run beside the agent, comma-separated from {', '.join(MODELS)}")
    parser.add_argument("--skip-training", action="store_true", help="compare the policy already in --out")
    args = parser.parse_args(argv)
    for name in ("steps", "envs", "n_steps", "threads"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1, got {getattr(args, name)}")
    compare = [m for m in args.compare.split(",") if m]
    unknown = [m for m in compare if m not in MODELS]
    if unknown:
        parser.error(f"unknown model(s) {', '.join(unknown)} in --compare; allowed: {', '.join(MODELS)}")
    args.compare = compare
    return args


def main(argv=None) -> int:
    from overhang_framework.envs.policies import PolicyFileError, policy_info, stable_baselines3
    from overhang_framework.errors import OverhangError

    args = parse(argv)
    try:
        stable_baselines3()
        check_settings(args)
        args.out.mkdir(parents=True, exist_ok=True)
        if args.skip_training:
            path = args.out / "policy.zip"
            figures = policy_info(path).get("training", {})
        else:
            path, figures = train(args)
            print(f"trained {figures['steps']} steps in {figures['seconds']} s "
                  f"({figures['steps_per_second']} steps/s); policy: {path}")
    except (PolicyFileError, OverhangError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    _write(args.out / "training.json", json.dumps(figures, indent=2) + "\n")
    rows = []
    world = [f"world.physics={args.physics}", f"tasks={args.test}"]
    started = time.perf_counter()
    summary = main_job(world + ["planner=policy", f"planner.path={path.resolve()}"], args.out / "test" / "policy")
    reward_env, illegal = env_reward(path, args.test, args.physics)
    rows.append(("ppo (policy planner)", summary["reward_mean"], summary["reward_sem"],
                 time.perf_counter() - started))
    for name in args.compare:
        started = time.perf_counter()
        summary = main_job(world + MODELS[name], args.out / "test" / name)
        rows.append((name, summary["reward_mean"], summary["reward_sem"], time.perf_counter() - started))
    lines = ["model,reward_mean,reward_sem,seconds"] + [f"{n},{m:.4f},{s:.4f},{t:.1f}" for n, m, s, t in rows]
    _write(args.out / "comparison.csv", "\n".join(lines) + "\n")
    models = {("ppo" if i == 0 else n): {"reward_mean": m, "reward_sem": s, "seconds": round(t, 1)}
              for i, (n, m, s, t) in enumerate(rows)}
    _write(args.out / "summary.json", json.dumps({"training": figures, "test": args.test, "physics": args.physics,
                                                  "models": models, "env_reward": reward_env,
                                                  "env_illegal": illegal}, indent=2) + "\n")
    print(f"\n{args.test} under physics={args.physics} (reward: mean +- sem over tasks)")
    for n, m, s, t in rows:
        print(f"  {n:<22} {m:.3f} +- {s:.3f}   ({t:.0f} s)")
    print(f"  ppo in the environment {reward_env:.3f}   ({illegal} illegal actions, each a failure there; "
          f"the planner plays the nearest legal one instead)")
    print(f"written: {args.out / 'comparison.csv'}, {args.out / 'training.json'}, {args.out / 'summary.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
