"""Fixtures the search-planner and fitting tests share: a static-physics world, its predictors and value, and
small simulated logs."""

from pathlib import Path

import pytest

from overhang_framework.plugins import Registry

REG = Registry()


@pytest.fixture(scope="module")
def world():
    return REG.create("world", {"name": "overhang", "physics": "static"})


@pytest.fixture(scope="module")
def veridical(world):
    return REG.create("predictor", {"name": "veridical"}, world=world)


@pytest.fixture(scope="module")
def ipe(world):
    return REG.create("predictor", {"name": "ipe", "K": 8}, world=world)


@pytest.fixture(scope="module")
def value(world):
    return REG.create("value", {"name": "overhang"}, world=world)


def simulated_log(out: Path, sequences: str) -> Path:
    """A simulated log of 2 + 2 participants doing every task of ``sequences`` (a Hydra list of width lists),
    static physics, the IPE with K = 10: small enough for a fit in seconds."""
    from overhang_framework.config import compose_config
    from overhang_framework.behaviour.simulation import CONFIG_NAME, run

    run(compose_config(["tasks=custom", f"tasks.sequences={sequences}", "world.physics=static", "predictor.K=10",
                        "progress=false", "cohort.participants.time_limited=2", "cohort.participants.unconstrained=2",
                        "cohort.n_tasks=null"], config_name=CONFIG_NAME), out)
    return out / "log.jsonl"


def fixed_cohort(out: Path, parameters: dict, participants: int, n_tasks: int, *overrides: str) -> Path:
    """The log of ``participants`` unconstrained simulated participants on the first ``n_tasks`` tasks, static
    physics, each drawing ``parameters`` (``cohort.parameters``, replaced whole); ``overrides`` are more of the
    participants command's (the predictor, the planner, the motor noise)."""
    from omegaconf import OmegaConf

    from overhang_framework.config import compose_config
    from overhang_framework.behaviour.simulation import CONFIG_NAME, run

    cfg = compose_config(["world.physics=static", "progress=false", "cohort.participants.time_limited=0",
                          f"cohort.participants.unconstrained={participants}", f"cohort.n_tasks={n_tasks}",
                          *overrides], config_name=CONFIG_NAME)
    OmegaConf.set_struct(cfg, False)
    cfg.cohort.parameters = parameters
    run(cfg, out)
    return out / "log.jsonl"
