"""The practice's expected screen-out, from the design's simulated participants.

The served study screens out a participant who does not pass a practice tower within ``practice.max_attempts``
attempts (``conf/serve.yaml``; a pass: the tower stands and reaches ``practice.threshold`` of the way from the ground
block to the buildable tower shown after each attempt). The design's participants do the main trials only, so the
size its power analysis plans is one after exclusions. Here each of them does the practice as the server scores it:
the practice tasks in order, each attempted until it passes or the attempts are used up, under their level's time
limit, every decision drawn from the participant's practice generator (:func:`practice_rng`), as a pilot through the
server draws it. The share a level screens out then says how many to recruit for the planned size to remain.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping, Optional, Sequence

import pandas as pd

COLUMNS = ["participant", "condition", "passed", "attempts", "failed_task"]
#: The participants a level who do the practice (the first of the design's pool): a share screened out to within
#: about ±0.08 (its standard error at 40 and a share of one half).
PER_LEVEL = 40


def practice_of(serve_overrides: Sequence[str] = ()) -> tuple[Any, list, Optional[int], dict]:
    """The served study's world (whose physics scores the practice), its practice tasks (each with its pass mark)
    and the attempts a task allows (None: no limit), from ``conf/serve.yaml`` with ``serve_overrides``. A practice
    whose towers are not stored for the server's physics is the :class:`~overhang_framework.errors.ConfigError` of
    the server's own check. Also the served world's config."""
    from omegaconf import OmegaConf

    from overhang_framework.experiment.settings import compose, practice_tasks
    from overhang_framework.plugins import Registry, plain

    cfg = compose(serve_overrides)
    world = Registry().create("world", plain(cfg.world))
    return world, practice_tasks(cfg, world), OmegaConf.select(cfg, "practice.max_attempts"), plain(cfg.world)


def practise(participant, spec, cohort, practice: Sequence, max_attempts: Optional[int], world, predictor, planner,
             value, seed: int) -> dict[str, Any]:
    """One participant's practice: whether they pass every task, their attempts in all, and the task they failed
    (None when they passed). ``world`` is the server's: its physics decides what stands."""
    from overhang_framework.behaviour.participants import practice_rng, simulate_trial

    rng = practice_rng(seed, participant.index)
    attempts = 0
    for k, task in enumerate(practice, 1):
        tries = 0
        while True:
            tries += 1
            attempts += 1
            records = simulate_trial(participant, spec, cohort, task.task, k, world, predictor, planner, value, rng)
            reward = records[-1]["reward"] if records else None
            if reward is not None and reward >= task.pass_reward - 1e-9:
                break
            if max_attempts is not None and tries >= max_attempts:
                return {"participant": participant.id, "condition": participant.condition, "passed": False,
                        "attempts": attempts, "failed_task": task.task.id}
    return {"participant": participant.id, "condition": participant.condition, "passed": True, "attempts": attempts,
            "failed_task": None}


def _setup(config: dict, serve_overrides: tuple) -> dict:
    from omegaconf import OmegaConf

    from overhang_framework.behaviour.participants import draw_participants
    from overhang_framework.behaviour.simulation import check_config

    checked = check_config(OmegaConf.create(config))
    world, practice, max_attempts, _ = practice_of(serve_overrides)
    return {"checked": checked, "world": world, "practice": practice, "max_attempts": max_attempts,
            "specs": {s.name: s for s in checked.cohort.conditions},
            "participants": draw_participants(checked.cohort, checked.seed)}


def _one(state: dict, index: int) -> dict:
    checked, participant = state["checked"], state["participants"][index]
    predictor, planner = checked.agents.build(participant)
    return practise(participant, state["specs"][participant.condition], checked.cohort, state["practice"],
                    state["max_attempts"], state["world"], predictor, planner, checked.models["value"], checked.seed)


def chosen(participants: Sequence, per_level: Optional[int]) -> list[int]:
    """The indices of the first ``per_level`` participants of each condition (all when None), in the cohort's order."""
    taken: dict[str, int] = {}
    out = []
    for p in participants:
        if per_level is None or taken.get(p.condition, 0) < per_level:
            taken[p.condition] = taken.get(p.condition, 0) + 1
            out.append(p.index)
    return out


def simulate_practice(config: Mapping[str, Any], serve_overrides: Sequence[str] = (), jobs: int = 1,
                      on_participant: Callable[[], None] = lambda: None,
                      per_level: Optional[int] = PER_LEVEL) -> pd.DataFrame:
    """The practice of the design's participants (``config``: the study's participants config as a plain mapping,
    with its cohort, models and seed; the first ``per_level`` a condition), one row each (:data:`COLUMNS`), in the
    cohort's order, on ``jobs`` processes. The participants decide with the design's models; the served study's
    physics (``conf/serve.yaml`` with ``serve_overrides``) says what stands, as the server would. A participant's
    practice depends only on the seed and their index, so it is the one a pilot of them draws."""
    state = _setup(dict(config), tuple(serve_overrides))  # a practice the server could not serve stops here
    indices = chosen(state["participants"], per_level)
    if jobs > 1 and len(indices) > 1:
        from overhang_framework.parallel import pool_map

        rows = {}
        for index, row, _ in pool_map(_setup, (dict(config), tuple(serve_overrides)), _one, indices,
                                      min(jobs, len(indices)), on_tick=lambda: None):
            rows[index] = row
            on_participant()
        return pd.DataFrame([rows[i] for i in indices], columns=COLUMNS)
    rows = []
    for index in indices:
        rows.append(_one(state, index))
        on_participant()
    return pd.DataFrame(rows, columns=COLUMNS)


def shares(table: pd.DataFrame, levels: Sequence[str]) -> dict[str, tuple[int, int]]:
    """Per level: (screened out, simulated)."""
    return {lv: (int((~table[table["condition"] == lv]["passed"].astype(bool)).sum()),
                 int((table["condition"] == lv).sum())) for lv in levels if (table["condition"] == lv).any()}


def to_recruit(planned: int, screened: int, simulated: int) -> Optional[int]:
    """The participants a level recruits so that ``planned`` pass the practice, at the share the simulation screened
    out (None when it screened out everyone: no number of recruits is enough)."""
    if simulated <= 0 or screened >= simulated:
        return None
    return int(math.ceil(planned / (1.0 - screened / simulated) - 1e-9))


def summary(table: pd.DataFrame, levels: Sequence[str], planned: Optional[int]) -> list[Mapping[str, Any]]:
    """Per level: the screened-out count and share, and the recruits the planned size needs."""
    out = []
    for lv, (screened, n) in shares(table, levels).items():
        out.append({"level": lv, "screened_out": screened, "simulated": n, "share": screened / n,
                    "recruit": None if planned is None else to_recruit(planned, screened, n)})
    return out
