"""The model space of a fit: predictor families (with an optional sigma grid, a hybrid's switch points, a
grid of the planner's risk aversion and one of the motor noise it plans for) crossed with planning depths."""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any, Mapping, Optional, Sequence

from overhang_framework.errors import ConfigError
from overhang_framework.fit.scores import HAND, Model, predictor_config as _predictor_config, with_hand

#: Depths a model may have (1: myopic).
MAX_DEPTH = 5


@dataclass
class ModelIndex:
    """One model index (a family and a depth) and its variants: one model per sigma of the grid, switch
    point of the hybrid's grid, risk of the risk grid, hand of the hand grid and percept of the percept grid,
    else one."""

    family: str
    depth: int
    variants: list[Model]

    @property
    def label(self) -> str:
        return self.variants[0].label


def risk_grid(grid: Any, form: Any, family: str) -> tuple[list[float], str]:
    """The risks of ``fit.models.<family>.risk`` (``[0.0]`` when not set) and the form of their weight."""
    from overhang_framework.search import RISK_FORMS

    if form not in RISK_FORMS:
        raise ConfigError(f"fit.models.{family}.risk_form must be one of {', '.join(RISK_FORMS)}, got {form!r}")
    if grid is None:
        return [0.0], str(form)
    values = list(grid) if isinstance(grid, (list, tuple)) else [grid]
    if not values or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < 1 for v in values):
        raise ConfigError(f"fit.models.{family}.risk must be a risk aversion from 0 (risk-neutral) to below 1, or a "
                          f"list of them, got {grid!r}")
    return sorted({float(v) for v in values}), str(form)


#: The grids of metres a family may give, and what each is: the motor noise its planner plans for (each model
#: judging with ``predictor=hand`` around the family's predictor) and the participant's perceptual noise.
METRE_GRIDS = {"hand": "the motor noise a planner plans for", "percept": "a perceptual noise"}


def metre_grid(name: str, grid: Any, family: str) -> list[float]:
    """The values (metres, 0 to 1) of ``fit.models.<family>.<name>`` for a name of :data:`METRE_GRIDS`
    (``[0.0]``, none, when not set)."""
    if grid is None:
        return [0.0]
    values = list(grid) if isinstance(grid, (list, tuple)) else [grid]
    if not values or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v <= 1 for v in values):
        raise ConfigError(f"fit.models.{family}.{name} must be {METRE_GRIDS[name]}, in metres from 0 (none) to 1, or "
                          f"a list of them, got {grid!r}")
    return sorted({float(v) for v in values})


#: ``switch: all``: every switch point a task of ``blocks`` widths allows, from the late predictor judging every
#: tower (2: the first placement makes a tower of 2 blocks) to the early one judging every tower (``blocks + 1``).
ALL = "all"


def switch_grid(grid: Any, family: str, blocks: Optional[int], check_only: bool = False) -> list:
    """The switch points of ``fit.models.<family>.switch``: ``[None]`` when not set (and for ``all`` when
    ``check_only``, which checks the setting before the tasks are known)."""
    if grid is None:
        return [None]
    if grid == ALL:
        if check_only:
            return [None]
        if blocks is None:
            raise ConfigError(f"fit.models.{family}.switch: 'all' needs the tasks' number of blocks")
        return list(range(2, int(blocks) + 2))
    values = list(grid) if isinstance(grid, (list, tuple)) else [grid]
    if not values or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in values):
        raise ConfigError(f"fit.models.{family}.switch must be a whole number >= 1 of blocks, a list of them or "
                          f"'{ALL}' (every switch point the tasks allow), got {grid!r}")
    return sorted(set(values))


def model_space(models: Mapping[str, Any], depths: Sequence[int], blocks: Optional[int] = None,
                check_only: bool = False) -> list[ModelIndex]:
    """The model indices of ``models`` (``family: {predictor: name, sigma: [grid], switch: [grid] or all,
    risk: [grid], risk_form: power or cvar, hand: [grid], percept: [grid], <setting>: value}``) x ``depths``; ``blocks`` is the
    largest number of widths of a task (for ``switch: all``). ``check_only`` checks every setting without
    resolving ``switch: all``. ``risk`` is the planner's risk aversion (0, risk-neutral, when not given);
    ``hand`` the motor noise its predictor averages over (``predictor=hand``; 0, none, when not given);
    ``percept`` the participant's perceptual noise (0, none, when not given)."""
    if not models:
        raise ConfigError("fit.models is empty; give at least one predictor family")
    if not depths:
        raise ConfigError("fit.depths is empty; give at least one depth (1 is myopic)")
    for d in depths:
        if isinstance(d, bool) or not isinstance(d, int) or not 1 <= d <= MAX_DEPTH:
            raise ConfigError(f"fit.depths: {d!r} is not a depth; allowed: whole numbers from 1 (myopic) to {MAX_DEPTH}")
    out = []
    for family, spec in models.items():
        spec = dict(spec or {})
        name = spec.pop("predictor", family)
        grid = spec.pop("sigma", None)
        if grid is None:
            sigmas = [None]
        else:
            sigmas = list(grid) if isinstance(grid, (list, tuple)) else [grid]
            if not sigmas or any(isinstance(s, bool) or not isinstance(s, (int, float)) or s < 0 for s in sigmas):
                raise ConfigError(f"fit.models.{family}.sigma must be a number >= 0 or a list of them, got {grid!r}")
        switches = switch_grid(spec.pop("switch", None), str(family), blocks, check_only)
        risks, form = risk_grid(spec.pop("risk", None), spec.pop("risk_form", "power"), str(family))
        hands = metre_grid("hand", spec.pop("hand", None), str(family))
        seen = metre_grid("percept", spec.pop("percept", None), str(family))
        if name == HAND and hands != [0.0]:
            raise ConfigError(f"fit.models.{family}: a family of predictor {HAND!r} has its hand already; give "
                              f"fit.models.{family}.hand with the predictor it wraps instead")
        configs = []
        for sigma, switch in itertools.product(sigmas, switches):
            overrides = dict(spec)
            if sigma is not None:
                overrides["sigma"] = float(sigma)
            if switch is not None:
                overrides["switch"] = int(switch)
            configs.append(_predictor_config(str(name), overrides))
        for depth in depths:
            out.append(ModelIndex(str(family), int(depth), [
                Model(with_hand(c, hand), int(depth), str(family), risk, form, percept)
                for c in configs for hand in hands for risk in risks for percept in seen]))
    return out
