"""The executed placement's motor noise in the likelihood: the probability of the x a participant placed at, given
each grid action they may have planned.

A simulated participant places a planned grid action ``a`` at ``x = a.x + N(0, sd^2)``, drawn again while the
placement is illegal, up to ``retries`` more times, and at ``a.x`` itself when every draw was illegal
(:func:`overhang_framework.behaviour.participants.decide`). People's placements are continuous too (the browser
study logs x to the millimetre). So with a motor model the fit does not map a placement onto its nearest grid
action: it asks, for every legal grid action ``a_j`` of the placement's state, the probability that a placement
planned as ``a_j`` lands where this one did, to ``precision`` metres::

    W_j = P(x in cell | a_j)
        = C_j * (1 - q_j^(R+1)) / (1 - q_j) * [x legal]  +  q_j^(R+1) * [a_j.x in cell]

with ``C_j`` the normal's mass on the cell ``[x - precision/2, x + precision/2]`` around ``a_j.x``, ``q_j`` the
probability that one draw around ``a_j.x`` is illegal (on the action's layer: out of the grid, unsupported or
overlapping), and ``R`` the retries. The placement's probability under a model is then ``sum_j P(a_j) W_j``, the
lapse's uniform action included: the likelihood of what was done, not of its nearest grid action. A placement
is left out only when no legal grid action of its layer can reach it (every ``W_j`` is 0); it is counted in
``fits.csv``'s ``unmapped`` as before.

``q_j`` is one minus the normal's mass on the intervals of legal x of the action's layer (:func:`legal_intervals`,
exact), so ``W`` sums to 1 over the cells of a planned action up to the cells cut by an interval's end
(tests/test_fit_motor.py measures it, and ``W`` against the simulator's own draws). The legal x are those of the
built-in world's rules (:mod:`overhang_framework.rules`), which the simulated participants' hand obeys.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Optional

import numpy as np
from scipy.special import ndtr

from overhang_framework import rules
from overhang_framework.errors import ConfigError

#: The width (metres) of the cell a logged x is taken to lie in: the browser study logs x to the millimetre.
PRECISION = 0.001



@dataclass(frozen=True)
class Motor:
    """The motor noise of executed placements: ``sd`` metres, ``retries`` redraws while illegal, x logged to
    ``precision`` metres."""

    sd: float
    retries: int = 5
    precision: float = PRECISION

    @classmethod
    def from_config(cls, node: Optional[Mapping[str, Any]], where: str = "motor") -> Optional["Motor"]:
        """``null`` (no motor model: each placement's nearest grid action), or ``{sd, retries, precision}``; a
        one-line :class:`ConfigError` naming what is wrong otherwise."""
        if node is None:
            return None
        if not isinstance(node, Mapping):
            raise ConfigError(f"{where} must be null or a mapping {{sd, retries, precision}}, got {node!r}")
        unknown = sorted(set(node) - {"sd", "retries", "precision"})
        if unknown:
            raise ConfigError(f"{where}.{unknown[0]} is not a setting of the motor model; allowed: sd, retries, precision")
        sd = node.get("sd")
        if isinstance(sd, bool) or not isinstance(sd, (int, float)) or not 0 < sd <= 0.5:
            raise ConfigError(f"{where}.sd must be a number of metres above 0 and at most 0.5, got {sd!r}")
        retries = node.get("retries", 5)
        if isinstance(retries, bool) or not isinstance(retries, int) or not 0 <= retries <= 100:
            raise ConfigError(f"{where}.retries must be a whole number from 0 to 100, got {retries!r}")
        precision = node.get("precision", PRECISION)
        if isinstance(precision, bool) or not isinstance(precision, (int, float)) or not 0 < precision <= 0.05:
            raise ConfigError(f"{where}.precision must be a number of metres above 0 and at most 0.05, got {precision!r}")
        return cls(float(sd), int(retries), float(precision))

    def describe(self) -> dict:
        return {"sd": self.sd, "retries": self.retries, "precision": self.precision}


def legal_intervals(geometry, width: float, layer: int) -> list[tuple[float, float]]:
    """The x at which a block of ``width`` may be placed on ``layer``, as disjoint intervals: inside the grid,
    overlapping some block of the layer below, overlapping none of its own layer (:func:`rules.legal_mask`'s
    rule, whose overlaps are open intervals, so the ends themselves are left out)."""
    half = width / 2
    low, high = -rules.GRID_HALF_WIDTH + half, rules.GRID_HALF_WIDTH - half
    if not 1 <= layer <= rules.MAX_LAYER or low > high:
        return []
    below = sorted((b.left - half, b.right + half) for b in geometry.blocks if b.layer == layer - 1)
    same = sorted((b.left - half, b.right + half) for b in geometry.blocks if b.layer == layer)
    merged: list[list[float]] = []
    for lo, hi in below:
        if merged and lo < merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], hi)
        else:
            merged.append([lo, hi])
    out = []
    for lo, hi in merged:
        pieces = [(max(lo, low), min(hi, high))]
        for blo, bhi in same:
            pieces = [part for a, b in pieces for part in ((a, min(b, blo)), (max(a, bhi), b))]
        out += [(a, b) for a, b in pieces if b > a]
    return out


def illegal_mass(geometry, width: float, xs: np.ndarray, layers: np.ndarray, sd: float) -> np.ndarray:
    """For each planned placement ``(xs[j], layers[j])``, the probability that one draw ``xs[j] + N(0, sd^2)`` on
    its layer is illegal: one minus the normal's mass on the layer's legal intervals."""
    xs, layers = np.asarray(xs, dtype=float), np.asarray(layers, dtype=int)
    legal = np.zeros(len(xs))
    for layer in np.unique(layers):
        rows = np.flatnonzero(layers == layer)
        for lo, hi in legal_intervals(geometry, width, int(layer)):
            legal[rows] += ndtr((hi - xs[rows]) / sd) - ndtr((lo - xs[rows]) / sd)
    return np.clip(1.0 - legal, 0.0, 1.0)


def weights(world, state, x: float, layer: int, motor: Motor) -> np.ndarray:
    """``W_j`` (module docstring) for every legal grid action of ``state``, in ``world.legal_actions``' order: the
    probability that a placement planned as that action lands at ``x`` (to ``motor.precision``) on ``layer``."""
    actions = world.legal_actions(state)
    xs = np.array([a.x for a in actions], dtype=float)
    layers = np.array([a.layer for a in actions], dtype=int)
    out = np.zeros(len(xs))
    same = np.flatnonzero(layers == int(layer))
    if not same.size:
        return out
    width = state.next_width
    q = illegal_mass(state.geometry, width, xs[same], layers[same], motor.sd)
    half = motor.precision / 2
    cell = ndtr((x + half - xs[same]) / motor.sd) - ndtr((x - half - xs[same]) / motor.sd)
    tries = motor.retries + 1
    with np.errstate(invalid="ignore", divide="ignore"):
        kept = np.where(q < 1.0 - 1e-12, (1.0 - q ** tries) / (1.0 - q), float(tries))
    legal_here = bool(rules.legal_mask(state.geometry, width, np.array([x]), np.array([int(layer)]))[0])
    out[same] = cell * kept * legal_here + q ** tries * (np.abs(xs[same] - x) <= half + 1e-12)
    return out
