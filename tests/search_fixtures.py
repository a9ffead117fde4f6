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
    from overhang_framework.participants import CONFIG_NAME, run

    run(compose_config(["tasks=custom", f"tasks.sequences={sequences}", "world.physics=static", "predictor.K=10",
                        "progress=false", "cohort.participants.time_limited=2", "cohort.participants.unconstrained=2",
                        "cohort.n_tasks=null"], config_name=CONFIG_NAME), out)
    return out / "log.jsonl"
