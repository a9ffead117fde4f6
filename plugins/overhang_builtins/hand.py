"""A predictor that knows its own hand: another predictor's answers averaged over the planner's motor noise.

A person who means to put a block at ``x`` puts it at ``x + e``, ``e ~ N(0, sd^2)`` (a simulated
participant's ``cohort.motor``). A planner that knows this judges a placement by its chance of standing
where the hand will put it:

    p_hand(s, a) = E_e[ p(s, a + e) ] ~ sum_j w_j * p(s, a + sd * z_j)

with the Gauss-Hermite nodes ``z_j`` and weights ``w_j`` of the standard normal (``nodes`` of them; 3 are
exact for any polynomial of degree 5 in ``e``), or with ``rule=equal-probability`` the midpoints of ``nodes``
equal-mass intervals of the normal, equally weighted: on step-like answers (near the edge of stability) 3
Gauss-Hermite nodes are off by up to 0.3-0.4 in probability and more nodes barely help, while 15
equal-probability nodes are within 0.04 (``python -m overhang_framework.bench.hand``). A shifted placement that the rules forbid (it would overlap
a block or lose its support) counts as the placement itself, as the hand is steered back to a legal spot.
Every shifted placement of a state is judged in one call of the inner predictor, with its own draws shared
by all of them (the IPE's common random numbers). Near the edge of stability the average falls more steeply
than the inner predictor's answer, so a planner with an unsteady hand aims lower; ``sd = 0`` is the inner
predictor exactly.

    python -m overhang_framework predictor=hand predictor.inner=hybrid predictor.sd=0.02
"""

from __future__ import annotations

from typing import Any, Mapping, Optional, Sequence

import numpy as np

from overhang_framework.geometry import X_DECIMALS, Action
from overhang_framework.interfaces import Predictor, State, World
from overhang_framework.rules import legal_mask



class HandPredictor(Predictor):
    """``inner`` (a registered predictor's name, built with ``inner_params``, or a predictor object used as it
    is) averaged over motor noise of standard deviation ``sd`` metres with ``nodes`` Gauss-Hermite nodes."""

    #: The rules of the average's nodes: Gauss-Hermite (exact for polynomials; coarse on step-like answers), and
    #: equal-probability nodes (the midpoints of ``nodes`` equal-mass intervals of the normal, equal weights; off
    #: by at most ``1 / (2 nodes)`` on any answer between 0 and 1: ``python -m overhang_framework.bench.hand``).
    RULES = ("gauss-hermite", "equal-probability")

    def __init__(self, world: World, inner: Any = "hybrid", inner_params: Optional[Mapping[str, Any]] = None,
                 sd: float = 0.02, nodes: int = 3, rule: str = "gauss-hermite"):
        from overhang_framework.plugins import Registry

        registry = Registry()
        names = [n for n in registry.names("predictor") if n != "hand"]
        if not isinstance(inner, (str, Predictor)) or (isinstance(inner, str) and inner not in names):
            raise ValueError(f"unknown inner predictor {inner!r}; allowed: {', '.join(names)}")
        if inner_params is not None and not isinstance(inner_params, Mapping):
            raise ValueError(f"inner_params must be a mapping of parameter names to values, got {inner_params!r}")
        if isinstance(sd, bool) or not isinstance(sd, (int, float)) or not np.isfinite(sd) or sd < 0:
            raise ValueError(f"sd must be a number of metres >= 0, got {sd!r}")
        if isinstance(nodes, bool) or not isinstance(nodes, int) or nodes < 1:
            raise ValueError(f"nodes must be a whole number >= 1, got {nodes!r}")
        if rule not in self.RULES:
            raise ValueError(f"unknown hand rule {rule!r}; allowed: {', '.join(self.RULES)}")
        self.world = world
        self.sd = float(sd)
        self.rule = rule
        self.inner = inner if isinstance(inner, Predictor) else \
            registry.create("predictor", {"name": inner, **dict(inner_params or {})}, world=world)
        if rule == "gauss-hermite":
            z, w = np.polynomial.hermite_e.hermegauss(nodes)
        else:
            from scipy.special import ndtri

            z, w = ndtri((np.arange(nodes) + 0.5) / nodes), np.ones(nodes)
        self.offsets = np.round(self.sd * z, X_DECIMALS) if self.sd > 0 else np.zeros(1)
        self.weights = w / w.sum() if self.sd > 0 else np.ones(1)
        self.deterministic = bool(getattr(self.inner, "deterministic", False))
        self.batched = bool(getattr(self.inner, "batched", False))
        self.batch_invariant = bool(getattr(self.inner, "batch_invariant", False))

    def shifted(self, state: State, actions: Sequence[Action]) -> list[Action]:
        """Every action at every node's offset (node-major), a forbidden shift replaced by the action itself."""
        if self.sd == 0:
            return list(actions)
        xs = np.array([a.x for a in actions], dtype=float)
        layers = np.array([a.layer for a in actions], dtype=int)
        moved = np.round(xs[None, :] + self.offsets[:, None], X_DECIMALS)
        ok = legal_mask(state.geometry, state.next_width, moved.ravel(), np.tile(layers, len(self.offsets)))
        moved = np.where(ok.reshape(moved.shape), moved, xs[None, :])
        return [Action(float(x) + 0.0, int(layer)) for row in moved for x, layer in zip(row.tolist(), layers.tolist())]

    def _average(self, p, n: int) -> np.ndarray:
        p = np.asarray(p, dtype=float).reshape(len(self.offsets), n)
        return self.weights @ p

    def predict(self, state: State, actions: Sequence[Action], rng: np.random.Generator) -> np.ndarray:
        if not actions:
            return np.zeros(0)
        return self._average(self.inner.predict(state, self.shifted(state, actions), rng), len(actions))

    def predict_many(self, requests, rngs) -> list[np.ndarray]:
        asked = [(state, self.shifted(state, actions)) for state, actions in requests]
        answers = self.inner.predict_many(asked, rngs)
        return [self._average(p, len(actions)) if len(actions) else np.zeros(0)
                for p, (_, actions) in zip(answers, requests)]

    def stats(self) -> dict:
        inner = getattr(self.inner, "stats", None)
        return inner() if callable(inner) else {}
