"""OverhangTower-v0: Gymnasium's checker, the paper's reward, illegal actions, seeding, rendering, vectors."""

import json
import math
from importlib import resources

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import overhang_framework  # noqa: F401  (registers the environment)
from overhang_framework.envs import ENV_ID
from overhang_framework.envs.spaces import TowerSpaces
from overhang_framework.envs.tower import OverhangTowerEnv
from overhang_framework.envs.wrappers import FlattenAction, flat_env
from overhang_framework.geometry import Action


def make(**kwargs):
    kwargs.setdefault("physics", "static")
    return gym.make(ENV_ID, **kwargs)


def stored_optimum(task_id: str, physics: str = "static") -> dict:
    data = json.loads(resources.files("overhang_framework.data").joinpath("optima.json").read_text())
    for entry in data["optima"].values():
        if entry["task_id"] == task_id and entry["physics"] == physics and entry["resolution"] == 0.1:
            return entry
    raise LookupError(task_id)


def test_registered_when_the_package_is_imported():
    assert ENV_ID in gym.registry
    env = gym.make(ENV_ID, tasks="example", physics="static")
    assert env.unwrapped.tasks[0].sequence == (0.6, 1.8, 1.2, 1.8, 0.6, 1.8)


@pytest.mark.parametrize("observation, physics", [("arrays", "static"), ("image", "static"), ("arrays", "tiered")])
def test_passes_gymnasiums_checker(observation, physics):
    check_env(make(observation=observation, physics=physics, render_mode="rgb_array").unwrapped,
              skip_render_check=False)


def test_flat_env_passes_the_checker_and_has_box_spaces():
    env = flat_env(physics="static")
    assert isinstance(env.action_space, gym.spaces.Box) and env.action_space.shape == (2,)
    assert isinstance(env.observation_space, gym.spaces.Box)
    check_env(env)


def test_paper_reward_along_a_stored_optimal_path():
    entry = stored_optimum("paper03")
    env = make(tasks="paper20")
    obs, info = env.reset(seed=0, options={"task": "paper03"})
    assert tuple(env.unwrapped.task.sequence) == tuple(entry["sequence"])
    rewards = []
    for x, layer in entry["actions"]:
        obs, reward, terminated, truncated, info = env.step({"x": np.array([x], np.float32), "layer": layer})
        rewards.append(reward)
        assert info["illegal"] is None and info["stable"]
    assert terminated and not truncated
    assert rewards[:-1] == [0.0] * (len(rewards) - 1)
    assert rewards[-1] == pytest.approx(entry["optimum"], abs=1e-6)


def test_shaped_return_of_a_success_is_the_paper_reward_minus_the_first_half_width():
    entry = stored_optimum("paper03")
    env = make(tasks="paper20", reward="shaped")
    env.reset(seed=0, options={"task": "paper03"})
    total = 0.0
    for x, layer in entry["actions"]:
        _, reward, terminated, _, _ = env.step({"x": [x], "layer": layer})
        total += reward
    assert terminated
    assert total == pytest.approx(entry["optimum"] - entry["sequence"][0] / 2, abs=1e-6)


@pytest.mark.parametrize("reward", ["paper", "shaped"])
def test_a_collapse_ends_the_episode_with_nothing(reward):
    env = make(sequences=[1.8, 1.8, 1.8], reward=reward, failure_penalty=1.0)
    env.reset(seed=0)
    _, r1, done1, _, _ = env.step({"x": [0.6], "layer": 1})   # stands, overhang 1.5
    _, r2, done2, _, info = env.step({"x": [1.8], "layer": 2})  # its centre of mass is off the block below
    assert not done1 and done2 and not info["stable"]
    if reward == "paper":
        assert r1 == 0.0 and r2 == 0.0
    else:
        assert r1 == pytest.approx(0.6) and r2 == pytest.approx(-1.0)


@pytest.mark.parametrize("action, why", [
    ({"x": [3.9], "layer": 1}, "outside the grid"),
    ({"x": [2.5], "layer": 1}, "supports"),
    ({"x": [0.0], "layer": 3}, "supports"),
    ({"x": [0.0], "layer": 0}, "ground"),
    ({"x": [0.0], "layer": 40}, "outside the grid"),
    ({"x": [float("nan")], "layer": 1}, "finite"),
    ({"x": [0.0], "layer": 1.5}, "whole number"),
    ({"x": [0.0], "layer": "1"}, "whole number"),
    ({"x": ["0.3"], "layer": 1}, "x must be a number"),
    ({"x": [1e308], "layer": 1}, "far outside the grid"),
    ({"x": [12.0], "layer": 1}, "outside the grid"),
    ({"x": [0.0, 1.0], "layer": 1}, "single values"),
    ({"layer": 1}, "keys 'x' and 'layer'"),
    ("left", "keys 'x' and 'layer'"),
    (None, "keys 'x' and 'layer'"),
])
@pytest.mark.parametrize("reward, resolution", [("paper", None), ("shaped", 0.1)])
def test_an_illegal_action_ends_the_episode_as_a_failure(action, why, reward, resolution):
    env = make(sequences=[1.8, 1.2, 0.6], reward=reward, resolution=resolution, failure_penalty=0.7).unwrapped
    obs0, _ = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(action)
    assert terminated and not truncated and reward == (0.0 if env.reward_mode == "paper" else -0.7)
    assert why in info["illegal"]
    np.testing.assert_array_equal(obs["blocks"], obs0["blocks"])  # nothing was placed


def test_overlap_is_illegal_and_a_finished_episode_asks_for_reset():
    env = make(sequences=[1.8, 0.6, 0.6]).unwrapped
    env.reset(seed=0)
    env.step({"x": [0.0], "layer": 1})
    _, reward, terminated, _, info = env.step({"x": [0.3], "layer": 1})
    assert terminated and reward == 0.0 and "overlaps" in info["illegal"]
    with pytest.raises(RuntimeError, match="reset"):
        env.step({"x": [0.0], "layer": 2})


def test_reset_with_a_seed_is_reproducible():
    env = make(tasks="paper20")
    a = [env.reset(seed=s)[1]["task_id"] for s in range(8)]
    b = [env.reset(seed=s)[1]["task_id"] for s in range(8)]
    assert a == b and len(set(a)) > 1

    def rollout(seed):
        obs, _ = env.reset(seed=seed)
        seen = [obs["remaining"].tolist()]
        for x in (0.1, 0.2, 0.3):
            obs, reward, done, _, _ = env.step({"x": [x], "layer": len(seen)})
            seen.append((obs["blocks"].tolist(), reward, done))
            if done:
                break
        return seen

    assert rollout(4) == rollout(4)
    rnd = make(tasks="random")
    seqs = [rnd.unwrapped.task.sequence for s in (1, 1, 2) if rnd.reset(seed=s)]
    assert seqs[0] == seqs[1] != seqs[2]


def test_resolution_rounds_x_to_the_grid():
    env = make(sequences=[1.8, 0.6], resolution=0.1)
    env.reset(seed=0)
    env.step({"x": [0.3337], "layer": 1})
    assert env.unwrapped.state.geometry.blocks[-1].x == pytest.approx(0.3)
    free = make(sequences=[1.8, 0.6, 0.6])
    free.reset(seed=0)
    free.step({"x": np.array([0.3], np.float32), "layer": 1})
    assert free.unwrapped.state.geometry.blocks[-1].x == 0.3  # the float32 0.3, to the micrometre
    _, _, _, _, info = free.step({"x": np.array([-0.3], np.float32), "layer": 1})  # touching it exactly
    assert info["illegal"] is None and free.unwrapped.state.geometry.blocks[-1].x == -0.3
    fine = make(sequences=[1.8, 0.6])
    fine.reset(seed=0)
    fine.step({"x": [0.3337], "layer": 1})
    assert fine.unwrapped.state.geometry.blocks[-1].x == 0.3337


def test_numpy_sequences_are_tasks_like_lists():
    for given in (np.array([1.2, 0.6, 1.8], np.float32), [np.float64(1.2), 0.6, 1.8], np.array([[1.2, 0.6, 1.8]])):
        assert make(sequences=given).unwrapped.tasks[0].sequence == (1.2, 0.6, 1.8)


def test_observation_holds_the_tower_and_the_remaining_blocks():
    env = make(sequences=[1.2, 0.6, 1.8])
    obs, _ = env.reset(seed=0)
    np.testing.assert_allclose(obs["remaining"], [0.6, 1.8, 0.0])
    obs, *_ = env.step({"x": [0.2], "layer": 1})
    np.testing.assert_allclose(obs["blocks"], [[1.2, 0.0, 0.0], [0.6, 0.2, 1.0], [0.0, 0.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(obs["remaining"], [1.8, 0.0, 0.0])


def test_image_observation_and_render_draw_the_tower():
    env = make(sequences=[1.2, 0.6, 1.8], observation="image", render_mode="rgb_array")
    obs, _ = env.reset(seed=0)
    frame = env.render()
    assert obs["image"].shape == (3, 32, 160) and obs["image"].dtype == np.uint8
    assert frame.shape == (240, 400, 3) and frame.dtype == np.uint8
    obs2, *_ = env.step({"x": [0.2], "layer": 1})
    assert (obs2["image"] != obs["image"]).any() and (env.render() != frame).any()


def test_bad_arguments_are_refused_in_one_line():
    for kwargs, message in [({"reward": "dense"}, "unknown reward 'dense'; allowed: paper, shaped"),
                            ({"observation": "pixels"}, "unknown observation 'pixels'"),
                            ({"sequences": [1.8, 1.0]}, "illegal block width 1.0"),
                            ({"tasks": "paper20", "max_blocks": 4}, "max_blocks >= 6"),
                            ({"render_mode": "human"}, "unknown render_mode 'human'"),
                            ({"tasks": "bogus"}, "unknown task set 'bogus'; allowed: draw, example, paper20, random"),
                            ({"sequences": [0.6] * 14}, "has 14 blocks; at most 13 fit the grid"),
                            ({"world": {"physics": "tiered"}}, "not inside world"),
                            ({"reward": "shaped", "failure_penalty": -1}, "failure_penalty must be a finite number >= 0"),
                            ({"world": {"resolution": -1}}, "resolution must be a positive number")]:
        with pytest.raises(ValueError, match=message.replace("(", r"\(")) as err:
            OverhangTowerEnv(physics="static", **kwargs)
        assert "\n" not in str(err.value)


def test_flat_actions_reach_every_layer_and_x():
    from overhang_framework.geometry import Block, Geometry
    from overhang_framework.interfaces import State

    spaces = TowerSpaces(max_blocks=6)
    tower = State(Geometry((Block(1.2, 0.0, 0), Block(0.6, 0.3, 1), Block(0.6, 0.3, 2), Block(1.2, 0.0, 3))), (0.6,))
    for layer in range(1, 5):
        for x in (-3.1, 0.0, 0.45, 3.3):
            back, why = spaces.to_action(spaces.unflatten(spaces.flatten_action(Action(x, layer), tower), tower))
            assert why is None and back.layer == layer and back.x == pytest.approx(x, abs=1e-6)
    assert spaces.unflatten([5.0, -7.0], tower)["layer"] == 1 and spaces.unflatten([5.0, 7.0], tower)["layer"] == 4
    start = State(Geometry((Block(1.2, 0.0, 0),)), (0.6,))
    assert {spaces.unflatten([0.0, a], start)["layer"] for a in np.linspace(-1, 1, 9)} == {1}
    assert math.isnan(spaces.unflatten([float("nan"), 0.0], tower)["x"][0])


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_a_vectorised_rollout_matches_single_environments(mode):
    from overhang_framework.rules import random_legal_action

    n, steps = 2, 16
    vec = gym.make_vec(ENV_ID, num_envs=n, vectorization_mode=mode, physics="static", tasks="paper20",
                       wrappers=[FlattenAction])
    obs, _ = vec.reset(seed=[10, 11])
    singles = [FlattenAction(make(tasks="paper20")) for _ in range(n)]
    pending = [False] * n  # the vector env resets this one on its next step (next-step autoreset)
    for i, (env, s) in enumerate(zip(singles, (10, 11))):
        np.testing.assert_allclose(obs["blocks"][i], env.reset(seed=s)[0]["blocks"])
    rng = np.random.default_rng(0)
    spaces = singles[0].unwrapped.spaces
    ended = placed = 0
    for _ in range(steps):
        actions = np.zeros((n, 2), np.float32)
        for i, env in enumerate(singles):
            state = env.unwrapped.state
            if not pending[i]:  # a legal placement, near the centre so that towers grow as well as fall
                a = random_legal_action(state.geometry, state.next_width, 0.1, rng)
                actions[i] = spaces.flatten_action(Action(float(np.clip(a.x, -0.6, 0.6)), a.layer), state)
        obs, rewards, terms, _, _ = vec.step(actions)
        for i, env in enumerate(singles):
            if pending[i]:
                o, _ = env.reset()
                pending[i] = False
            else:
                o, r, t, _, info = env.step(actions[i])
                assert r == pytest.approx(rewards[i]) and t == terms[i]
                pending[i] = t
                ended += t
                placed += info["illegal"] is None
            np.testing.assert_allclose(obs["blocks"][i], o["blocks"])
            np.testing.assert_allclose(obs["remaining"][i], o["remaining"])
    vec.close()
    assert ended >= 2 and placed >= 8


def test_the_speed_benchmark_prints_both_physics_in_one_json_line():
    import json as _json
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "overhang_framework.bench.env", "--steps", "50",
                           "--tiered-steps", "20", "--quiet"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    rows = _json.loads(done.stdout.strip().splitlines()[-1])["rows"]
    assert {(r["agent"], r["physics"]) for r in rows} == {(a, p) for a in ("legal", "sample")
                                                          for p in ("tiered", "static")}
    legal = [r for r in rows if r["agent"] == "legal"]
    assert all(r["illegal"] == 0 and r["steps_per_second"] > 0 for r in legal)
    assert all(r["illegal"] > 0 for r in rows if r["agent"] == "sample")


def test_ppo_training_progress_off_a_terminal_is_whole_lines_not_carriage_returns(tmp_path, capsys):
    """In a log file or a pipe the training's progress is the project's line now and then, never a bar's
    carriage-return redraws; a bad setting stops the command in one line before any training."""
    pytest.importorskip("stable_baselines3")
    from overhang_framework.envs import ppo

    args = ppo.parse(["--steps", "256", "--envs", "4", "--n-steps", "64", "--out", str(tmp_path)])
    path, figures = ppo.train(args)
    err = capsys.readouterr().err
    assert path.exists() and figures["steps"] >= 256
    assert "\r" not in err
    lines = [line for line in err.splitlines() if line.startswith("training:")]
    assert lines and lines[-1].startswith("training: 100%") and "256/256" in lines[-1], err
    for argv, said in ((["--physics", "statc"], "unknown physics 'statc'"),
                       (["--test", "papr20"], "unknown tasks 'papr20'"),
                       (["--tasks", "papr20"], "the training environment: unknown task set 'papr20'")):
        assert ppo.main([*argv, "--out", str(tmp_path / "bad")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.count("\n") == 1 and said in err, err
    assert not (tmp_path / "bad").exists()
