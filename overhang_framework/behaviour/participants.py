"""Simulated participants: model agents that do the Overhang Tower experiment and write a behaviour log.

A participant is a planner with a physics predictor (by default the lookahead
planner with the IPE), with parameters of its own drawn from the cohort's
distributions:

* ``sigma``: the noise of its IPE (the predictor's ``sigma``);
* ``depth``: its search horizon (the planner's ``depth``; 1 is the myopic-equivalent lookahead);
* ``beta``: the inverse temperature of its softmax choice over the planner's root scores;
* ``lapse``: the probability that a placement is a uniformly random legal action instead;
* ``switch``: the switch point of its hybrid predictor (towers of fewer blocks go to the early
  predictor; the predictor's ``switch``), drawn only when the cohort gives it a distribution.

Three more axes separate what makes a person's towers fall from how far the person aims; each is drawn
only when the cohort gives it a distribution, and a participant who does not draw it decides as before,
draw for draw:

* ``risk``: risk aversion of its planner (the planner's ``risk``, 0 to below 1): each placement's chance
  ``p`` of standing counts as a weight below it (with the planner's default ``risk_form=power``,
  ``p ** (1 / (1 - risk))``), so a collapse weighs more than its expected loss
  (:func:`overhang_framework.search.risk_weight`);
* ``percept``: perceptual noise, metres: before each decision the participant sees the x of every block
  placed after the first with an error ``N(0, percept^2)`` of its own (one percept per decision, shared by
  everything the decision's search imagines, apart from the dynamics noise inside the IPE's simulations),
  plans on the tower it sees, and places the block in the real one (:func:`perceive`);
* ``hand``: the motor noise its planner plans for, metres: its predictor's answers are averaged over a
  placement error ``N(0, hand^2)`` (``predictor=hand``), so that an unsteady hand that knows it aims lower.
  The noise actually applied is the cohort's ``motor.sd``, whatever ``hand`` is;
* ``steadiness``: a factor on the participant's hand, both the one it has and the one it plans for: its
  placements are off by ``N(0, (steadiness * motor.sd)^2)`` and its planner plans for
  ``steadiness * hand``, so that a steadier hand that knows it aims further, and falls no more often.

One more sets how long the participant takes, and nothing else:

* ``pace``: a factor on every decision time of the participant (a slow deliberator has ``pace`` above 1),
  so that participants differ in their times as people do; it draws nothing while deciding, so a
  participant's choices are those it makes without it, unless a time limit cuts a slower decision off.

Each decision runs the planner on the grid of legal actions under the
condition's budget of predictor calls (``call_limit``, the machine-independent
budget that truncates the search: the lookahead deepens iteratively and plays
the best action of the deepest depth it completed). Its *decision time* is
simulated from what the search cost, never measured::

    t = pace * (t0 + per_call * predictor_calls) * exp(noise * z),   z ~ N(0, 1)

A decision whose time is over the condition's ``time_limit`` times out: the
trial ends with reward 0 (a timed-out record). Otherwise the block goes to the
chosen grid x plus motor noise ``N(0, motor.sd^2)``, resampled up to
``motor.retries`` times while the placement is illegal (else the grid x), and
the world's physics says whether the tower stands; the trial ends at the first
collapse. Each participant does the cohort's tasks in an order of its own.

Everything a participant does comes from two generators derived from
``(seed, participant index)``: one draws its parameters, the other its
behaviour (task order, choices, lapses, times, motor noise). The same config
and seed give the same log. Config keys and the model in full: ``docs/participants.md``.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Optional, Sequence

import numpy as np

from overhang_framework.errors import ConfigError
from overhang_framework.geometry import X_DECIMALS, Action
from overhang_framework.perception import nearest_legal, perceive, perceive_with  # noqa: F401  (perceive_with: the fit's, here as before)
from overhang_framework.interfaces import Budget, Task, World
from overhang_framework.plugins import Registry, accepted_parameters

#: The parameters each participant draws, and the model parameter each one sets.
PARAMETERS = ("sigma", "depth", "beta", "lapse", "switch", "risk", "percept", "hand", "pace", "steadiness", "K")
#: Where a drawn parameter goes: (model group, parameter name).
TARGETS = {"sigma": ("predictor", "sigma"), "depth": ("planner", "depth"), "beta": ("planner", "beta"),
           "switch": ("predictor", "switch"), "risk": ("planner", "risk"), "K": ("predictor", "K")}
#: The largest risk aversion a participant draws (the planner's ``risk`` must be below 1).
MAX_RISK = 0.999
#: Parameters whose column ``participants.csv`` has only when some participant draws them.
OPTIONAL = ("switch", "risk", "percept", "hand", "pace", "steadiness", "K")
#: The deepest search a participant may have (a paper20 trial has 5 placements).
MAX_DEPTH = 5
#: The distributions a parameter may be drawn from, with their arguments.
DISTRIBUTIONS = {
    "fixed": ("value",),
    "uniform": ("low", "high"),
    "normal": ("mean", "sd"),
    "lognormal": ("median", "sigma"),
    "beta": ("a", "b"),
    "categorical": ("values", "p"),
}
#: Short names of the paper's conditions in participant ids (``sim-tl-001``); other conditions use their name.
CONDITION_CODES = {"time_limited": "tl", "unconstrained": "un"}


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class Distribution:
    """A named distribution with its arguments; ``sample`` draws one value."""

    kind: str
    args: tuple

    def sample(self, rng: np.random.Generator) -> float:
        a = self.args
        if self.kind == "fixed":
            return a[0]
        if self.kind == "uniform":
            return float(rng.uniform(a[0], a[1]))
        if self.kind == "normal":
            return float(rng.normal(a[0], a[1]))
        if self.kind == "lognormal":
            return float(a[0] * math.exp(a[1] * rng.standard_normal()))
        if self.kind == "beta":
            return float(rng.beta(a[0], a[1]))
        values, p = a
        return values[int(rng.choice(len(values), p=p))]

    def log_density(self, x) -> np.ndarray:
        """The log of the density (continuous) or probability (discrete) of each value of ``x``; -inf outside
        the support. A lognormal or normal of spread 0 is a point mass, as ``fixed`` is."""
        x = np.asarray(x, dtype=float)
        a = self.args
        lo, hi = self.support()
        if self.kind == "fixed" or lo == hi:
            return np.where(np.isclose(x, lo), 0.0, -np.inf)
        if self.kind == "categorical":
            out = np.full(x.shape, -np.inf)
            for v, q in zip(*a):
                out = np.where(np.isclose(x, v), np.log(q) if q > 0 else -np.inf, out)
            return out
        with np.errstate(divide="ignore", invalid="ignore"):
            if self.kind == "uniform":
                return np.where((x >= a[0]) & (x <= a[1]), -math.log(a[1] - a[0]), -np.inf)
            if self.kind == "normal":
                return -0.5 * ((x - a[0]) / a[1]) ** 2 - math.log(a[1] * math.sqrt(2 * math.pi))
            if self.kind == "lognormal":
                z = (np.log(np.where(x > 0, x, np.nan)) - math.log(a[0])) / a[1]
                out = -0.5 * z ** 2 - np.log(np.where(x > 0, x, np.nan) * a[1] * math.sqrt(2 * math.pi))
                return np.where(x > 0, out, -np.inf)
            from scipy.stats import beta

            return np.where((x >= 0) & (x <= 1), beta.logpdf(x, a[0], a[1]), -np.inf)

    def support(self) -> tuple[float, float]:
        """The smallest and largest value a draw can take."""
        a = self.args
        if self.kind == "fixed":
            return a[0], a[0]
        if self.kind == "uniform":
            return a[0], a[1]
        if self.kind == "normal":
            return (a[0], a[0]) if a[1] == 0 else (-math.inf, math.inf)
        if self.kind == "lognormal":
            return (a[0], a[0]) if a[1] == 0 else (0.0, math.inf)
        if self.kind == "beta":
            return 0.0, 1.0
        return min(a[0]), max(a[0])

    def values(self) -> Optional[list]:
        """The values a discrete distribution takes (``None`` for a continuous one)."""
        if self.kind == "fixed":
            return [self.args[0]]
        if self.kind == "categorical":
            return list(self.args[0])
        return None


def parse_distribution(where: str, spec: Any) -> Distribution:
    """The distribution ``spec`` (``{dist: NAME, ARG: VALUE, ...}``) names; :class:`ConfigError` otherwise."""
    if not isinstance(spec, Mapping) or "dist" not in spec:
        raise ConfigError(f"{where} must be a distribution {{dist: NAME, ...}} or null, got {spec!r}; "
                          f"distributions: {', '.join(DISTRIBUTIONS)}")
    kind = spec["dist"]
    if kind not in DISTRIBUTIONS:
        raise ConfigError(f"{where}: unknown distribution {kind!r}; allowed: {', '.join(DISTRIBUTIONS)}")
    names = DISTRIBUTIONS[kind]
    given = set(spec) - {"dist"}
    if given != set(names):
        raise ConfigError(f"{where}: distribution {kind!r} takes {', '.join(names)}, got "
                          f"{', '.join(sorted(given)) or '(none)'}")
    args = [spec[n] for n in names]
    if kind == "categorical":
        values, p = list(args[0] or []), list(args[1] or [])
        if not values or not all(_number(v) for v in values):
            raise ConfigError(f"{where}: categorical values must be a non-empty list of numbers, got {args[0]!r}")
        if len(p) != len(values) or not all(_number(q) and q >= 0 for q in p) or abs(sum(p) - 1) > 1e-9:
            raise ConfigError(f"{where}: categorical p must be {len(values)} probabilities >= 0 summing to 1, "
                              f"got {args[1]!r}")
        return Distribution(kind, (tuple(values), tuple(float(q) for q in p)))
    for name, value in zip(names, args):
        if not _number(value):
            raise ConfigError(f"{where}: {name} of {kind!r} must be a number, got {value!r}")
    if kind == "uniform" and args[0] > args[1]:
        raise ConfigError(f"{where}: uniform needs low <= high, got {args[0]} > {args[1]}")
    if kind in ("normal", "lognormal") and args[1] < 0:
        raise ConfigError(f"{where}: {names[1]} of {kind!r} must be >= 0, got {args[1]}")
    if kind == "lognormal" and args[0] <= 0:
        raise ConfigError(f"{where}: median of 'lognormal' must be > 0, got {args[0]}")
    if kind == "beta" and (args[0] <= 0 or args[1] <= 0):
        raise ConfigError(f"{where}: a and b of 'beta' must be > 0, got a={args[0]}, b={args[1]}")
    return Distribution(kind, tuple(args))


def _check_range(where: str, dist: Distribution, low: float, high: float, what: str, whole: bool = False) -> None:
    lo, hi = dist.support()
    if lo < low or hi > high:
        raise ConfigError(f"{where} must give {what}, but its {dist.kind} distribution reaches "
                          f"{lo if lo < low else hi:g}")
    values = dist.values()
    if whole:
        if values is None or not all(float(v).is_integer() for v in values):
            raise ConfigError(f"{where} must give whole numbers ({what}): use a categorical or fixed "
                              f"distribution of whole numbers")


@dataclass(frozen=True)
class TimeModel:
    """Decision time from the search's cost: ``(t0 + per_call * calls) * exp(noise * z)``, ``z ~ N(0, 1)``."""

    t0: float
    per_call: float
    noise: float

    def sample(self, calls: int, rng: np.random.Generator) -> float:
        return (self.t0 + self.per_call * calls) * math.exp(self.noise * rng.standard_normal())


@dataclass(frozen=True)
class ConditionSpec:
    """A condition of the cohort: how many take part, the simulated time limit and the call budget."""

    name: str
    n: int
    time_limit: Optional[float]
    call_limit: Optional[int]

    @property
    def code(self) -> str:
        return CONDITION_CODES.get(self.name, self.name)


@dataclass(frozen=True)
class Cohort:
    """Everything the cohort config says, checked."""

    name: str
    conditions: tuple[ConditionSpec, ...]
    n_tasks: Optional[int]
    parameters: Mapping[str, Optional[Distribution]]
    time: TimeModel
    motor_sd: float
    motor_retries: int
    #: Per condition, the parameters and time model that ``by_condition`` gives it (the shared ones merged in).
    condition_parameters: Mapping[str, Mapping[str, Optional[Distribution]]] = dataclasses.field(default_factory=dict)
    condition_time: Mapping[str, TimeModel] = dataclasses.field(default_factory=dict)

    @property
    def size(self) -> int:
        return sum(c.n for c in self.conditions)

    def parameters_for(self, condition: str) -> Mapping[str, Optional[Distribution]]:
        """The distributions the participants of ``condition`` draw from."""
        return self.condition_parameters.get(condition, self.parameters)

    def time_for(self, condition: str) -> TimeModel:
        """The decision-time model of ``condition``."""
        return self.condition_time.get(condition, self.time)

    def draws(self, name: str) -> bool:
        """Whether participants of some condition draw parameter ``name``."""
        return any(self.parameters_for(c.name).get(name) is not None for c in self.conditions)


def _whole(where: str, value: Any, minimum: int, allow_none: bool = False) -> Optional[int]:
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ConfigError(f"{where} must be a whole number >= {minimum}{' or null' if allow_none else ''}, "
                          f"got {value!r}")
    return value


def _real(where: str, value: Any, minimum: float = 0.0) -> float:
    if not _number(value) or value < minimum:
        raise ConfigError(f"{where} must be a number >= {minimum:g}, got {value!r}")
    return float(value)


def _keys(where: str, node: Mapping, allowed: Sequence[str]) -> None:
    from overhang_framework.errors import closest

    for key in node:
        if key not in allowed:
            close = closest(str(key), list(allowed))
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise ConfigError(f"unknown key '{where}.{key}'{hint}; keys of {where}: {', '.join(allowed)}")


def cohort_from_config(cohort: Mapping[str, Any], conditions: Mapping[str, Any]) -> Cohort:
    """The checked cohort of the ``cohort`` and ``conditions`` config nodes (plain mappings)."""
    # ``defaults`` (a cohort file's choice of predictor, as Hydra reads it) is not the cohort's own
    cohort = {k: v for k, v in cohort.items() if k != "defaults"}
    _keys("cohort", cohort, ("name", "participants", "n_tasks", "parameters", "by_condition", "decision_time", "motor"))
    counts = cohort.get("participants")
    if not isinstance(counts, Mapping) or not counts:
        raise ConfigError(f"cohort.participants must map condition names to numbers of participants, "
                          f"got {counts!r}")
    specs = []
    for name, n in counts.items():
        if name not in conditions:
            raise ConfigError(f"cohort.participants names the condition {name!r}, which is not configured; "
                              f"conditions: {', '.join(conditions)}")
        node = conditions[name] or {}
        _keys(f"conditions.{name}", node, ("name", "time_limit", "call_limit"))
        limit = node.get("time_limit")
        if limit is not None and (not _number(limit) or limit <= 0):
            raise ConfigError(f"conditions.{name}.time_limit must be a number of seconds > 0 or null, got {limit!r}")
        calls = _whole(f"conditions.{name}.call_limit", node.get("call_limit"), 1, allow_none=True)
        specs.append(ConditionSpec(str(name), _whole(f"cohort.participants.{name}", n, 0),
                                   None if limit is None else float(limit), calls))
    if sum(s.n for s in specs) < 1:
        raise ConfigError("cohort.participants adds up to no participant")
    _keys("cohort.by_condition", cohort.get("by_condition") or {}, [s.name for s in specs])
    dists = _distributions("cohort.parameters", cohort.get("parameters") or {})
    time = _time_model("cohort.decision_time", cohort.get("decision_time") or {})
    by_params, by_time = {}, {}
    for name, node in (cohort.get("by_condition") or {}).items():
        where = f"cohort.by_condition.{name}"
        if not isinstance(node, Mapping):
            raise ConfigError(f"{where} must be a mapping with parameters and/or decision_time, got {node!r}")
        _keys(where, node, ("parameters", "decision_time"))
        own = node.get("parameters") or {}
        _keys(f"{where}.parameters", own, PARAMETERS)
        merged = {k: v for k, v in (cohort.get("parameters") or {}).items()}
        merged.update(own)
        by_params[name] = _distributions(f"{where}.parameters", merged)
        shared_time = dict(cohort.get("decision_time") or {})
        own_time = node.get("decision_time") or {}
        _keys(f"{where}.decision_time", own_time, ("t0", "per_call", "noise"))
        shared_time.update(own_time)
        by_time[name] = _time_model(f"{where}.decision_time", shared_time)
    motor = cohort.get("motor") or {}
    _keys("cohort.motor", motor, ("sd", "retries"))
    return Cohort(
        name=str(cohort.get("name")),
        conditions=tuple(specs),
        n_tasks=_whole("cohort.n_tasks", cohort.get("n_tasks"), 1, allow_none=True),
        parameters=dists,
        time=time,
        motor_sd=_real("cohort.motor.sd", motor.get("sd")),
        motor_retries=_whole("cohort.motor.retries", motor.get("retries"), 0),
        condition_parameters=by_params,
        condition_time=by_time,
    )


def _time_model(where: str, node: Mapping[str, Any]) -> TimeModel:
    _keys(where, node, ("t0", "per_call", "noise"))
    return TimeModel(_real(f"{where}.t0", node.get("t0")), _real(f"{where}.per_call", node.get("per_call")),
                     _real(f"{where}.noise", node.get("noise")))


def _distributions(where_all: str, params: Mapping[str, Any]) -> dict[str, Optional[Distribution]]:
    """The checked distributions of a ``parameters`` node (None: not drawn)."""
    _keys(where_all, params, PARAMETERS)
    dists: dict[str, Optional[Distribution]] = {}
    for name in PARAMETERS:
        spec = params.get(name)
        where = f"{where_all}.{name}"
        dist = None if spec is None else parse_distribution(where, spec)
        if dist is not None:
            if name == "lapse":
                _check_range(where, dist, 0.0, 1.0, "a probability from 0 to 1")
            elif name == "depth":
                _check_range(where, dist, 1, MAX_DEPTH, f"a depth from 1 to {MAX_DEPTH}", whole=True)
            elif name == "switch":
                _check_range(where, dist, 1, math.inf, "a whole number of blocks >= 1", whole=True)
            elif name == "K":
                _check_range(where, dist, 1, math.inf, "a whole number of mental simulations >= 1", whole=True)
            elif name == "risk":
                _check_range(where, dist, 0.0, 1.0, "a risk aversion from 0 (risk-neutral) to 1 (a draw above "
                             f"{MAX_RISK} counts as {MAX_RISK})")
            elif name in ("pace", "steadiness"):
                what = "a factor on the decision time" if name == "pace" else "a factor on the hand"
                _check_range(where, dist, 0.0, math.inf, f"{what} > 0")
                if dist.support()[0] <= 0 and dist.kind != "lognormal":  # a lognormal's draws are all above 0
                    raise ConfigError(f"{where} must give {what} > 0, but its {dist.kind} "
                                      f"distribution reaches {dist.support()[0]:g} (a lognormal is always above 0)")
            else:
                _check_range(where, dist, 0.0, math.inf, "a number >= 0")
        dists[name] = dist
    return dists


@dataclass(frozen=True)
class Participant:
    """One simulated participant: who, in which condition, and its true parameters (None: not drawn)."""

    id: str
    index: int
    condition: str
    sigma: Optional[float]
    depth: Optional[int]
    beta: Optional[float]
    lapse: float
    switch: Optional[int] = None
    risk: Optional[float] = None
    percept: Optional[float] = None
    hand: Optional[float] = None
    pace: Optional[float] = None
    steadiness: Optional[float] = None
    #: The number of mental simulations of the IPE (its ``K``; None: the predictor's own).
    K: Optional[int] = None

    @property
    def planned_hand(self) -> Optional[float]:
        """The motor noise the planner plans for: ``hand``, times ``steadiness`` when drawn."""
        return None if not self.hand else self.hand * (self.steadiness if self.steadiness is not None else 1.0)

    def motor_sd(self, cohort_sd: float) -> float:
        """The motor noise of the participant's placements: the cohort's, times ``steadiness`` when drawn."""
        return cohort_sd * self.steadiness if self.steadiness is not None else cohort_sd


def participant_rngs(seed: int, index: int) -> tuple[np.random.Generator, np.random.Generator]:
    """The generators of participant ``index``: one for its parameters, one for its behaviour."""
    params, behaviour = np.random.SeedSequence([int(seed), int(index)]).spawn(2)
    return np.random.default_rng(params), np.random.default_rng(behaviour)


def practice_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of participant ``index``'s practice trials (in a pilot through the experiment server): a
    third child of the seed that :func:`participant_rngs` splits, so the practice leaves the main trials'
    draws as the offline simulation makes them."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]).spawn(3)[2])


def draw_participants(cohort: Cohort, seed: int) -> list[Participant]:
    """Every participant of the cohort, conditions in config order, each with parameters drawn from
    its own generator (the first of :func:`participant_rngs`)."""
    out = []
    for spec in cohort.conditions:
        for k in range(spec.n):
            index = len(out)
            rng = participant_rngs(seed, index)[0]
            drawn = {name: (None if dist is None else dist.sample(rng))
                     for name, dist in cohort.parameters_for(spec.name).items()}
            out.append(Participant(
                id=f"sim-{spec.code}-{k + 1:03d}", index=index, condition=spec.name,
                sigma=drawn["sigma"], depth=None if drawn["depth"] is None else int(drawn["depth"]),
                beta=drawn["beta"], lapse=0.0 if drawn["lapse"] is None else float(drawn["lapse"]),
                switch=None if drawn.get("switch") is None else int(drawn["switch"]),
                risk=None if drawn.get("risk") is None else min(float(drawn["risk"]), MAX_RISK),
                K=None if drawn.get("K") is None else int(drawn["K"]),
                **{k: None if drawn.get(k) is None else float(drawn[k])
                   for k in ("percept", "hand", "pace", "steadiness")}))
    return out


def participants_csv(participants: Sequence[Participant]) -> str:
    """``participants.csv``: one row per participant with its true parameters (empty: not drawn; the columns
    of :data:`OPTIONAL` only when some participant draws them)."""
    fields = [f.name for f in dataclasses.fields(Participant)]
    for name in OPTIONAL:
        if all(getattr(p, name) is None for p in participants):
            fields.remove(name)
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(fields)
    for p in participants:
        row = []
        for name in fields:
            value = getattr(p, name)
            row.append("" if value is None else (repr(float(value)) if isinstance(value, float) else value))
        writer.writerow(row)
    return out.getvalue()


class Agents:
    """Builds each participant's predictor and planner from the run's model configs.

    The participant's ``sigma`` replaces the predictor's ``sigma`` (a hybrid's: its IPE's); ``depth``
    and ``beta`` the planner's, whose ``choice`` becomes ``softmax`` when
    ``beta`` is drawn. A drawn parameter the chosen model does not take is a
    :class:`ConfigError` (set it to null in the cohort).
    """

    def __init__(self, registry: Registry, world: World, predictor: Mapping[str, Any], planner: Mapping[str, Any],
                 cohort: Cohort):
        self.registry, self.world = registry, world
        self.configs = {"predictor": dict(predictor), "planner": dict(planner)}
        #: parameters that go to a predictor nested in the configured one (the hybrid's IPE): name -> params key
        self.nested: dict[str, str] = {}
        for name, (group, key) in TARGETS.items():
            if not cohort.draws(name):
                continue
            config = self.configs[group]
            takes = accepted_parameters(registry.get(group, config["name"]).factory)
            inner = _nested_ipe(config) if group == "predictor" and key in ("sigma", "K") else None
            if inner is not None and (takes is None or key not in takes):
                self.nested[name] = inner
                continue
            if takes is not None and key not in takes:
                raise ConfigError(f"{group} {config['name']!r} has no parameter {key}, which "
                                  f"cohort.parameters.{name} draws; set cohort.parameters.{name}=null")
        if cohort.draws("beta"):
            self.configs["planner"]["choice"] = "softmax"

    def build(self, participant: Participant) -> tuple[Any, Any]:
        """The participant's (predictor, planner); with ``hand``, its predictor knows that hand
        (``predictor=hand`` around the configured one)."""
        built = {}
        for group in ("predictor", "planner"):
            config = dict(self.configs[group])
            for name, (target, key) in TARGETS.items():
                value = getattr(participant, name)
                if target == group and value is not None:
                    if name in self.nested:
                        config[self.nested[name]] = {**dict(config.get(self.nested[name]) or {}), key: value}
                    else:
                        config[key] = value
            if group == "predictor" and participant.hand:
                inner = {k: v for k, v in config.items() if k != "name"}
                config = {"name": "hand", "inner": config["name"], "inner_params": inner,
                          "sd": participant.planned_hand}
            built[group] = self.registry.create(group, config, world=self.world)
        return built["predictor"], built["planner"]


def _nested_ipe(config: Mapping[str, Any]) -> Optional[str]:
    """The params key of the IPE inside a hybrid predictor config (``early_params`` or ``late_params``), if any."""
    for side in ("early", "late"):
        if config.get(side) == "ipe" and f"{side}_params" in config:
            return f"{side}_params"
    return None


def _legal_x(world: World, state, action: Action, sd: float, retries: int, rng: np.random.Generator) -> float:
    """The chosen grid x plus motor noise, resampled while illegal (up to ``retries`` more times), else the grid x."""
    if sd <= 0:
        return action.x
    for _ in range(retries + 1):
        x = round(action.x + sd * float(rng.standard_normal()), X_DECIMALS) + 0.0
        if world.is_legal(state, Action(x, action.layer)):
            return x
    return action.x


@dataclass(frozen=True)
class Choice:
    """One decision of a participant: what it chose, what the choice cost, and how long it took."""

    action: Action  # the grid action played (a random legal one after a lapse)
    lapsed: bool
    predictor_calls: int
    depth_completed: Optional[int]
    seconds: float  # the simulated decision time
    timed_out: bool  # the decision time was over the time limit: nothing is placed
    x: Optional[float]  # the placed x (grid x plus motor noise); None on a timeout


def decide(participant: Participant, spec: ConditionSpec, cohort: Cohort, state, world: World, predictor, planner,
           value, rng: np.random.Generator, time_limit: Optional[float] = None) -> Choice:
    """The participant's decision in ``state``: plan under the condition's call budget, lapse, draw the decision
    time, and, unless that is over ``time_limit`` (seconds; None: no limit), the placed x.

    The draws from ``rng`` come in one order (the percept, with perceptual noise; the plan, the lapse, the
    lapse's action, the time, the motor noise), so a participant who sees the same states makes the same
    choices however its outcomes reach it. With perceptual noise the participant plans on the tower it sees
    (:func:`perceive`); a chosen placement that the real tower does not allow becomes the nearest one it does.
    """
    budget = Budget(seconds=None, predictor_calls=spec.call_limit)
    seen = perceive(state, participant.percept, rng) if participant.percept else state
    decision = planner.plan(seen, predictor, value, budget, rng)
    action, lapsed = decision.action, bool(rng.random() < participant.lapse)
    if seen is not state and not lapsed:
        action = nearest_legal(world, state, action)
    if lapsed:
        legal = world.legal_actions(state)
        action = legal[int(rng.integers(len(legal)))]
    calls = decision.spend.predictor_calls
    seconds = cohort.time_for(spec.name).sample(calls, rng)
    if participant.pace is not None:
        seconds *= participant.pace
    if time_limit is not None and seconds > time_limit:
        return Choice(action, lapsed, calls, decision.spend.depth_completed, seconds, True, None)
    x = _legal_x(world, state, action, participant.motor_sd(cohort.motor_sd), cohort.motor_retries, rng)
    return Choice(action, lapsed, calls, decision.spend.depth_completed, seconds, False, x)


def simulate_trial(participant: Participant, spec: ConditionSpec, cohort: Cohort, task: Task, trial: int,
                   world: World, predictor, planner, value, rng: np.random.Generator) -> list[dict]:
    """The records of one trial: the participant places the task's blocks until the end, a collapse or a timeout."""
    state = world.initial_state(task)
    records: list[dict] = []
    stood = True
    while not state.done:
        choice = decide(participant, spec, cohort, state, world, predictor, planner, value, rng, spec.time_limit)
        before = [[b.width, b.x, b.layer] for b in state.geometry.blocks]
        record = {
            "log_version": 1, "participant": participant.id, "condition": participant.condition,
            "task_id": task.id, "sequence": list(task.sequence), "trial": trial, "step": len(records) + 1,
            "width": state.next_width, "tower_before": before, "decision_time": choice.seconds,
            "source": "simulated", "grid_x": choice.action.x, "lapse": choice.lapsed,
            "predictor_calls": choice.predictor_calls, "depth_completed": choice.depth_completed,
        }
        if choice.timed_out:
            record.update(x=None, layer=None, stable=None, overhang=None, reward=0.0,
                          decision_time=spec.time_limit, timed_out=True)
            records.append(record)
            return records
        state = world.step(state, Action(choice.x, choice.action.layer))
        stable = bool(world.is_stable(state.geometry))
        stood = stood and stable
        ends = not stable or state.done
        record.update(x=choice.x, layer=choice.action.layer, stable=stable, overhang=world.overhang(state.geometry),
                      reward=world.reward(state.geometry, stood) if ends else None, timed_out=False)
        records.append(record)
        if not stable:
            break
    return records


@dataclass
class Simulation:
    """What :func:`simulate` produced: the log's records and the participants with their parameters."""

    records: list[dict]
    participants: list[Participant]


def cohort_tasks(cohort: Cohort, tasks: Sequence[Task]) -> list[Task]:
    """The tasks every participant of ``cohort`` does: the first ``cohort.n_tasks`` (all when null)."""
    return list(tasks)[: cohort.n_tasks] if cohort.n_tasks else list(tasks)


def simulate_participant(participant: Participant, cohort: Cohort, tasks: Sequence[Task], models: Mapping[str, Any],
                         agents: "Agents", seed: int,
                         on_trial: Optional[Callable[[Participant, Task], None]] = None,
                         order: Optional[Sequence[int]] = None) -> list[dict]:
    """The records of one participant doing ``tasks`` (already cut to the cohort's) in an order of its own.

    They depend only on the participant, the models and ``seed``: participants
    can be simulated in any order, in any process. ``order`` (indices into ``tasks``) replaces the
    participant's own order (an experiment server's, say); its own is still drawn, so the trials' draws
    are those the participant makes when it does the tasks in that order.
    """
    specs = {s.name: s for s in cohort.conditions}
    world, value = models["world"], models["value"]
    predictor, planner = agents.build(participant)
    rng = participant_rngs(seed, participant.index)[1]
    own = rng.permutation(len(tasks))
    order = own if order is None else list(order)
    records: list[dict] = []
    for trial, k in enumerate(order, 1):
        records.extend(simulate_trial(participant, specs[participant.condition], cohort, tasks[int(k)], trial,
                                      world, predictor, planner, value, rng))
        if on_trial is not None:
            on_trial(participant, tasks[int(k)])
    return records


def simulate(cohort: Cohort, tasks: Sequence[Task], models: Mapping[str, Any], agents: Agents, seed: int,
             on_trial: Optional[Callable[[Participant, Task], None]] = None) -> Simulation:
    """Every participant of ``cohort`` does ``tasks`` (the first ``cohort.n_tasks``) in an order of its own.

    ``models`` holds the shared ``world`` and ``value``; ``agents`` builds each
    participant's predictor and planner. ``on_trial`` is called after each trial.
    """
    tasks = cohort_tasks(cohort, tasks)
    participants = draw_participants(cohort, seed)
    records: list[dict] = []
    for participant in participants:
        records.extend(simulate_participant(participant, cohort, tasks, models, agents, seed, on_trial))
    return Simulation(records, participants)


def condition_summary(records: Sequence[Mapping[str, Any]]) -> list[dict]:
    """Per condition, Table 1's measures: trials, success rate, overhang of successful trials, decision
    time, timeouts and predictor calls (means over records or trials, no SEM)."""
    out = []
    for condition in dict.fromkeys(r["condition"] for r in records):
        rs = [r for r in records if r["condition"] == condition]
        ends = [r for r in rs if r["reward"] is not None]
        won = [r for r in ends if not r["timed_out"] and r["stable"]]
        out.append({
            "condition": condition,
            "participants": len({r["participant"] for r in rs}),
            "trials": len(ends),
            "success": len(won) / len(ends) if ends else float("nan"),
            "total_reward": sum(r["reward"] for r in ends) / max(1, len({r["participant"] for r in rs})),
            "overhang_successful": float(np.mean([r["overhang"] for r in won])) if won else float("nan"),
            "decision_time": float(np.mean([r["decision_time"] for r in rs])),
            "timeouts": sum(bool(r["timed_out"]) for r in rs),
            "predictor_calls": float(np.mean([r["predictor_calls"] for r in rs])),
        })
    return out


def format_summary(rows: Sequence[Mapping[str, Any]]) -> str:
    head = f"{'condition':<16}{'people':>7}{'trials':>7}{'success':>9}{'reward/p':>10}{'overhang':>10}" \
           f"{'time (s)':>10}{'timeouts':>10}{'calls':>8}"
    lines = [head]
    for r in rows:
        lines.append(f"{r['condition']:<16}{r['participants']:>7}{r['trials']:>7}{r['success']:>9.3f}"
                     f"{r['total_reward']:>10.3f}{r['overhang_successful']:>10.3f}{r['decision_time']:>10.2f}"
                     f"{r['timeouts']:>10}{r['predictor_calls']:>8.1f}")
    return "\n".join(lines)
