"""planner=policy: a saved policy plays through the planner interface and the main job."""

import json
import subprocess
import sys
import zipfile

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from overhang_framework.envs import ENV_ID
from overhang_framework.envs.policies import load_policy, save_policy
from overhang_framework.envs.wrappers import flat_env
from overhang_framework.geometry import Action
from overhang_framework.interfaces import Budget, Task
from overhang_framework.plugins import Registry
from overhang_framework.testing.contracts import PlannerContract


@pytest.fixture(scope="module")
def policy_file(tmp_path_factory):
    import torch
    from stable_baselines3 import PPO

    torch.set_num_threads(1)
    env = flat_env(physics="static", tasks="random", reward="shaped", resolution=0.1)
    model = PPO("MlpPolicy", env, n_steps=128, batch_size=64, seed=3, device="cpu",
                policy_kwargs={"log_std_init": -1.5})
    model.learn(256)
    return save_policy(model, tmp_path_factory.mktemp("agent") / "ppo", env)


class TestPolicyPlanner(PlannerContract):
    @pytest.fixture
    def world(self):
        return Registry().create("world", {"name": "overhang", "physics": "static"})

    @pytest.fixture
    def planner(self, world, policy_file):
        return Registry().create("planner", {"name": "policy", "path": str(policy_file)}, world=world)


def env_actions(path, task_set: str):
    """What the policy does in the environment on each task of ``task_set``: [(x, layer, legal), ...]."""
    model, spaces, _ = load_policy(path)
    env = gym.make(ENV_ID, tasks=task_set, physics="static", **spaces.spec())
    out = {}
    for task in env.unwrapped.tasks:
        obs, _ = env.reset(seed=0, options={"task": task.id})
        done, steps = False, []
        while not done:
            flat, _ = model.predict(gym.spaces.flatten(env.observation_space, obs), deterministic=True)
            action = spaces.unflatten(flat, env.unwrapped.state)
            obs, _, done, _, info = env.step(action)
            placed, _ = spaces.to_action(action)  # x on the policy's grid, as the environment placed it
            steps.append((placed.x, placed.layer, info["illegal"] is None))
        out[task.id] = steps
    return out


def episode_actions(run_dir):
    return [[(s["x"], s["layer"]) for s in json.loads(line)["steps"]]
            for line in (run_dir / "episodes.jsonl").read_text().splitlines()]


@pytest.mark.slow
def test_a_saved_policy_plays_through_the_main_job(policy_file, tmp_path):
    cmd = [sys.executable, "-m", "overhang_framework", "planner=policy", f"planner.path={policy_file}",
           "world.physics=static", "tasks=paper20", "tasks.only=[paper00,paper03,paper07]", "progress=false"]
    done = subprocess.run(cmd + [f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    episodes = [json.loads(line) for line in (tmp_path / "run" / "episodes.jsonl").read_text().splitlines()]
    assert [e["task_id"] for e in episodes] == ["paper00", "paper03", "paper07"]
    in_env = env_actions(policy_file, "paper20")
    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    compared = 0
    for e in episodes:
        state = world.initial_state(Task(e["task_id"], tuple(e["sequence"])))
        for step, (x, layer, legal) in zip(e["steps"], in_env[e["task_id"]]):
            played = Action(step["x"], step["layer"])
            assert world.illegal_reason(state, played) is None
            if not legal:  # the planner played the nearest legal action instead; the env episode ended
                break
            assert (step["x"], step["layer"]) == pytest.approx((x, layer), abs=1e-6)  # what the policy chose
            compared += 1
            state = world.successor(state, played)
    assert compared >= 3
    again = subprocess.run(cmd + [f"hydra.run.dir={tmp_path / 'again'}"], capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert episode_actions(tmp_path / "again") == episode_actions(tmp_path / "run")


def test_an_illegal_choice_becomes_the_nearest_legal_action(policy_file):
    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    planner = Registry().create("planner", {"name": "policy", "path": str(policy_file)}, world=world)
    state = world.initial_state(Task("t", (1.2, 0.6)))

    class Fixed:  # a policy that always asks for x = 3.0 on the top reachable layer
        def predict(self, obs, deterministic=True):
            return np.array([0.75, 0.9], np.float32), None  # x = 3.0, the top reachable layer

    planner.model = Fixed()
    decision = planner.plan(state, Registry().create("predictor", {"name": "veridical"}, world=world),
                            None, Budget(), np.random.default_rng(0))
    assert decision.action == Action(0.8, 1)  # layer 1 is the only legal one; 0.8 is its rightmost x
    assert planner.replaced == 1


@pytest.mark.parametrize("content, message", [
    (None, "no policy file at"),
    (b"not a zip", "is not a Stable-Baselines3 policy file"),
    ("zip-without-metadata", "was not saved with overhang_framework.envs.save_policy"),
])
def test_unreadable_policy_files_are_refused_in_one_line(tmp_path, content, message):
    path = tmp_path / "p.zip"
    if content == "zip-without-metadata":
        with zipfile.ZipFile(path, "w") as z:
            z.writestr("data", json.dumps({"policy_class": "x"}))
    elif content is not None:
        path.write_bytes(content)
    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    from overhang_framework.errors import ConfigError

    with pytest.raises(ConfigError, match=message) as err:
        Registry().create("planner", {"name": "policy", "path": str(path)}, world=world)
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="planner.path must name a policy file"):
        Registry().create("planner", {"name": "policy"}, world=world)


@pytest.mark.slow
def test_the_ppo_example_trains_saves_and_compares(tmp_path):
    out = tmp_path / "ppo"
    done = subprocess.run([sys.executable, "-m", "overhang_framework.envs.ppo", "--steps", "2048", "--envs", "2",
                           "--n-steps", "256", "--compare", "myopic", "--test", "example", "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["models"]) == {"ppo", "myopic"}
    assert summary["training"]["steps"] >= 2048 and summary["training"]["curve"]
    myopic = json.loads((out / "test" / "myopic" / "metrics.json").read_text())
    assert summary["models"]["myopic"]["reward_mean"] == myopic["reward_mean"]
    model, spaces, info = load_policy(out / "policy.zip")
    assert info["training"]["tasks"] == "random" and spaces.resolution == 0.1
    assert "ppo (policy planner)" in done.stdout and (out / "comparison.csv").read_text().startswith("model,")


def test_a_sampling_policy_is_reproducible_by_seed_and_long_tasks_are_refused(policy_file):
    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    planner = Registry().create("planner", {"name": "policy", "path": str(policy_file), "deterministic": False},
                                world=world)
    predictor = Registry().create("predictor", {"name": "veridical"}, world=world)
    state = world.initial_state(Task("t", (1.8, 1.2, 0.6)))
    draws = [planner.plan(state, predictor, None, Budget(), np.random.default_rng(s)).action for s in (1, 1, 2, 3, 4)]
    assert draws[0] == draws[1] and len(set(draws[1:])) > 1
    with pytest.raises(ValueError, match="at most 6 blocks; this task has 7"):
        planner.plan(world.initial_state(Task("long", (1.8,) * 7)), predictor, None, Budget(),
                     np.random.default_rng(0))


def test_a_shipped_policy_is_named_without_a_path_and_a_missing_name_lists_the_shipped_ones(tmp_path):
    from overhang_framework.envs.policies import SHIPPED, policy_path, shipped_policies
    from overhang_framework.errors import ConfigError

    assert "ppo-train-3m" in shipped_policies()
    assert policy_path("ppo-train-3m") == policy_path("ppo-train-3m.zip") == SHIPPED / "ppo-train-3m.zip"
    own = tmp_path / "ppo-train-3m.zip"  # a file of the same name where it is named wins
    own.write_bytes(b"x")
    assert policy_path(own) == own
    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    planner = Registry().create("planner", {"name": "policy", "path": "ppo-train-3m"}, world=world)
    state = world.initial_state(Task("t", (1.2, 0.6, 1.8, 0.6, 1.2, 0.6, 1.8)))  # the cross split's seven blocks
    decision = planner.plan(state, Registry().create("predictor", {"name": "veridical"}, world=world), None, Budget(),
                            np.random.default_rng(0))
    assert decision.action in set(world.legal_actions(state))
    with pytest.raises(ConfigError, match="no policy file at nonesuch; .*name a shipped one: .*ppo-train-3m"):
        Registry().create("planner", {"name": "policy", "path": "nonesuch"}, world=world)
