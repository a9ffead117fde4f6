"""How a person sees a tower and where a choice made on what they saw lands: every block's x seen with perceptual
noise (:func:`perceive`, :func:`perceive_with`), and the legal action nearest a choice the real tower does not allow
(:func:`nearest_legal`). The simulated participants (:mod:`overhang_framework.behaviour.participants`) and the fit's
likelihood (:mod:`overhang_framework.fit`) both see through these."""

from __future__ import annotations

import numpy as np

from overhang_framework.geometry import X_DECIMALS, Action, Block, Geometry, separate_overlaps
from overhang_framework.interfaces import State, World


def perceive(state, sd: float, rng: np.random.Generator):
    """``state`` as a participant with perceptual noise ``sd`` (metres) sees it: every block placed after the
    first (which stands fixed at the ground centre) seen at its x plus ``N(0, sd^2)``, one draw per block, in
    placement order; blocks of a layer that would then overlap are moved apart by the least displacement
    that makes them touch (as the IPE's perturbed scenes are). The layers, widths and blocks still to come
    are seen as they are."""
    if sd <= 0 or len(state.geometry.blocks) < 2:
        return state
    return perceive_with(state, sd, rng.standard_normal(len(state.geometry.blocks) - 1))


def perceive_with(state, sd: float, z: np.ndarray):
    """:func:`perceive` with the standard normal draws ``z`` given, one per block after the first: the percepts
    of every ``sd`` from one set of draws (the fit's common random numbers)."""
    blocks = state.geometry.blocks
    if sd <= 0 or len(blocks) < 2:
        return state
    xs = np.array([b.x for b in blocks], dtype=float)
    seen = xs.copy()
    seen[1:] = xs[1:] + sd * np.asarray(z, dtype=float)[: len(blocks) - 1]
    widths = np.array([b.width for b in blocks], dtype=float)
    layers = np.array([b.layer for b in blocks], dtype=int)
    seen = separate_overlaps(seen[None, :], widths, layers, xs)[0]
    seen = np.round(seen, X_DECIMALS) + 0.0
    return State(Geometry(tuple(Block(b.width, float(x), b.layer) for b, x in zip(blocks, seen))), state.remaining)


def nearest_legal(world: World, state, action: Action) -> Action:
    """The legal grid action of ``state`` nearest ``action`` (same layer first, then by |x|), for a choice made
    on a misperceived tower that the real one does not allow."""
    if world.is_legal(state, action):
        return action
    legal = world.legal_actions(state)
    return min(legal, key=lambda a: (a.layer != action.layer, abs(a.x - action.x), abs(a.layer - action.layer), a.x))
