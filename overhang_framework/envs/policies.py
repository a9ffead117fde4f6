"""Saving and loading trained policies with what the environment showed them.

A policy is a Stable-Baselines3 model (the ``[rl]`` extra). :func:`save_policy`
stores, inside the model's own zip file, the algorithm and the environment's
:class:`~overhang_framework.envs.spaces.TowerSpaces`, so the ``policy`` planner
shows the policy the same observation and reads its action the same way.

The policies the project ships (the benchmark's PPO row) are in
``overhang_framework/data/policies`` and are named without a path:
``planner.path=ppo-train-3m``.
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Any

from overhang_framework.envs.spaces import TowerSpaces

ALGORITHMS = ("PPO", "A2C", "SAC", "TD3", "DDPG")
KEY = "overhang_framework"
INSTALL = "pip install 'overhang-framework[rl]'"


#: The policies the project ships, named by their file's stem.
SHIPPED = Path(__file__).resolve().parent.parent / "data" / "policies"


class PolicyFileError(ValueError):
    """A policy file that cannot be read, with the reason in one line."""


def shipped_policies() -> list[str]:
    return sorted(p.stem for p in SHIPPED.glob("*.zip"))


def policy_path(path: str | os.PathLike) -> Path:
    """The file of ``path``: a file as named, or a shipped policy named by its stem (``ppo-train-3m``)."""
    path = Path(path)
    if path.is_file():
        return path
    if path.parent == Path(".") and (SHIPPED / f"{path.stem}.zip").is_file() and path.suffix in ("", ".zip"):
        return SHIPPED / f"{path.stem}.zip"
    shipped = shipped_policies()
    raise PolicyFileError(f"no policy file at {path}; train one with python -m overhang_framework.envs.ppo"
                          + (f", or name a shipped one: {', '.join(shipped)}" if shipped else ""))


def stable_baselines3():
    """The Stable-Baselines3 module, or :class:`PolicyFileError` saying how to install it."""
    try:
        import stable_baselines3
    except ImportError:
        raise PolicyFileError(f"playing or training a policy needs Stable-Baselines3: {INSTALL}") from None
    return stable_baselines3


def save_policy(model: Any, path: str | os.PathLike, env: Any, **extra: Any) -> Path:
    """Save the Stable-Baselines3 ``model`` trained on ``env`` (an ``OverhangTower-v0``, wrapped or not)
    to ``path`` (``.zip``), atomically; ``extra`` plain data is kept with it (e.g. training figures)."""
    algorithm = type(model).__name__
    if algorithm not in ALGORITHMS:
        raise PolicyFileError(f"unsupported algorithm {algorithm}; allowed: {', '.join(ALGORITHMS)}")
    inner = env.unwrapped if hasattr(env, "unwrapped") else env
    if hasattr(env, "get_attr"):  # a Stable-Baselines3 vectorised env
        spaces = env.get_attr("spaces")[0]
    else:
        spaces = inner.spaces
    path = Path(path)
    if path.suffix != ".zip":
        path = path.with_name(path.name + ".zip")
    path.parent.mkdir(parents=True, exist_ok=True)
    info = {"algorithm": algorithm, "spaces": spaces.spec(), **extra}
    for key, value in extra.items():
        try:
            json.dumps(value, allow_nan=False)
        except (TypeError, ValueError):
            raise PolicyFileError(f"save_policy keeps plain JSON data only; {key}={value!r} is not") from None
    setattr(model, KEY, info)
    tmp = path.with_name(f".{path.name}.tmp.zip")
    model.save(tmp)
    os.replace(tmp, path)
    return path


def policy_info(path: str | os.PathLike) -> dict:
    """What :func:`save_policy` kept with the policy at ``path``."""
    path = policy_path(path)
    try:
        with zipfile.ZipFile(path) as z:
            data = json.loads(z.read("data"))
    except (zipfile.BadZipFile, KeyError, json.JSONDecodeError, UnicodeDecodeError) as err:
        raise PolicyFileError(f"{path} is not a Stable-Baselines3 policy file ({err})") from None
    info = data.get(KEY)
    if not isinstance(info, dict) or info.get("algorithm") not in ALGORITHMS or not isinstance(info.get("spaces"), dict):
        raise PolicyFileError(f"{path} was not saved with overhang_framework.envs.save_policy, so the "
                              "observation it was trained on is unknown")
    return info


def policy_action(model: Any, spaces: TowerSpaces, observation_space: Any, observation: dict, state: Any,
                  deterministic: bool = True) -> dict:
    """The ``Dict`` action ``model`` takes in ``state``, shown ``observation`` flattened as :func:`flat_env`
    shows it, with its flat action read as :class:`FlattenAction` reads it."""
    import gymnasium as gym

    flat, _ = model.predict(gym.spaces.flatten(observation_space, observation), deterministic=deterministic)
    return spaces.unflatten(flat, state)


def load_policy(path: str | os.PathLike) -> tuple[Any, TowerSpaces, dict]:
    """``(model, spaces, info)`` of the policy at ``path``, on the CPU."""
    info = policy_info(path)
    sb3 = stable_baselines3()
    try:
        spaces = TowerSpaces(**info["spaces"])
    except (TypeError, ValueError) as err:
        raise PolicyFileError(f"{path}: the stored observation is not readable ({err})") from None
    model = getattr(sb3, info["algorithm"]).load(str(policy_path(path)), device="cpu")
    return model, spaces, info
