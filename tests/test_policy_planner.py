"""planner=policy: a saved policy plays through the planner interface and the main job."""

import json
import subprocess
import sys
import zipfile

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from overhang_framework.envs import ENV_ID  # noqa: E402
from overhang_framework.envs.policies import load_policy, save_policy  # noqa: E402
from overhang_framework.envs.wrappers import flat_env  # noqa: E402
from overhang_framework.plugins import Registry  # noqa: E402
from overhang_framework.testing.contracts import PlannerContract  # noqa: E402


@pytest.fixture(scope="module")
def policy_file(tmp_path_factory):
    import torch
    from stable_baselines3 import PPO

    torch.set_num_threads(1)
    env = flat_env(physics="static", tasks="random", reward="shaped", resolution=0.1)
    model = PPO("MlpPolicy", env, n_steps=128, batch_size=64, seed=3, device="cpu")
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
    env = gym.make(ENV_ID, tasks=task_set, physics="static", resolution=spaces.resolution)
    out = {}
    for task in env.unwrapped.tasks:
        obs, _ = env.reset(seed=0, options={"task": task.id})
        done, steps = False, []
        while not done:
            flat, _ = model.predict(gym.spaces.flatten(env.observation_space, obs), deterministic=True)
            action = spaces.unflatten(flat, env.unwrapped.state)
            obs, _, done, _, info = env.step(action)
            steps.append((float(action["x"][0]), int(action["layer"]), info["illegal"] is None))
        out[task.id] = steps
    return out


def test_a_saved_policy_plays_through_the_main_job(policy_file, tmp_path):
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "overhang_framework", "planner=policy", f"planner.path={policy_file}",
           "world.physics=static", "tasks=paper20", "tasks.only=[paper00,paper03,paper07]",
           f"hydra.run.dir={run}", "progress=false"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    episodes = [json.loads(line) for line in (run / "episodes.jsonl").read_text().splitlines()]
    assert [e["task_id"] for e in episodes] == ["paper00", "paper03", "paper07"]
    in_env = env_actions(policy_file, "paper20")
    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    from overhang_framework.interfaces import Task
    from overhang_framework.geometry import Action

    compared = 0
    for e in episodes:
        state = world.initial_state(Task(e["task_id"], tuple(e["sequence"])))
        for step, (x, layer, legal) in zip(e["steps"], in_env[e["task_id"]]):
            played = Action(step["x"], step["layer"])
            assert world.illegal_reason(state, played) is None
            if legal:  # the planner plays what the policy chose
                assert (step["x"], step["layer"]) == pytest.approx((round(x, 1), layer), abs=1e-6)
                compared += 1
            else:  # the nearest legal action instead
                break
            state = world.successor(state, played)
    assert compared >= 1 or all(not legal for steps in in_env.values() for *_, legal in steps[:1])
    again = subprocess.run(cmd[:-2] + [f"hydra.run.dir={tmp_path / 'again'}", "progress=false"],
                           capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert (tmp_path / "again" / "episodes.jsonl").read_text().splitlines() == \
        (run / "episodes.jsonl").read_text().splitlines() or _same_actions(run, tmp_path / "again")


def _same_actions(a, b):
    read = lambda d: [[(s["x"], s["layer"]) for s in json.loads(line)["steps"]]  # noqa: E731
                      for line in (d / "episodes.jsonl").read_text().splitlines()]
    return read(a) == read(b)


def test_an_illegal_choice_becomes_the_nearest_legal_action(policy_file):
    from overhang_framework.geometry import Action
    from overhang_framework.interfaces import Budget

    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    planner = Registry().create("planner", {"name": "policy", "path": str(policy_file)}, world=world)
    state = world.initial_state(__import__("overhang_framework.interfaces", fromlist=["Task"]).Task("t", (1.2, 0.6)))

    class Fixed:  # a policy that always asks for x = 3.0 on layer 2
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
