"""The stage-switch hybrid predictor (paper, Fig. 4 discussion): one predictor while the scene is
simple, another as it grows.

The paper finds the IPE explains human judgements better on sparse early scenes and the visual
heuristic (the CNN) on larger ones: the IPE's perceptual noise compounds with the height of the stack,
while the CNN's cost and reliability stay flat. The switch is by the number of blocks of the scene
being judged, the tower *after* the action, so inside a lookahead the deeper, larger towers go to
``late`` even when the decision itself is early. ``docs/cnn.md`` justifies the default switch point
with the accuracy of both predictors against the reference by number of blocks
(``python -m overhang_framework.analyses.predictor_accuracy``).
"""

from __future__ import annotations

from typing import Any, Mapping, Optional, Sequence

import numpy as np

from overhang_framework.geometry import Action
from overhang_framework.interfaces import Predictor, State, World


class HybridPredictor(Predictor):
    """``early`` judges towers of fewer than ``switch`` blocks (after the action), ``late`` the others.

    ``early`` and ``late`` are the registered names of any two predictors,
    built with ``early_params`` and ``late_params``, or predictor objects used as they are. Every call goes wholly to
    one of them: all the candidate actions of a state make towers of the same
    size. :meth:`stats` counts the calls and actions each one answered.
    """

    def __init__(self, world: World, early: Any = "ipe", late: Any = "cnn", switch: int = 4,
                 early_params: Optional[Mapping[str, Any]] = None,
                 late_params: Optional[Mapping[str, Any]] = None):
        from overhang_framework.plugins import Registry

        if isinstance(switch, bool) or not isinstance(switch, int) or switch < 1:
            raise ValueError(f"switch must be a whole number of blocks >= 1, got {switch!r}")
        for label, params in (("early_params", early_params), ("late_params", late_params)):
            if params is not None and not isinstance(params, Mapping):
                raise ValueError(f"{label} must be a mapping of parameter names to values, got {params!r}")
        registry = Registry()
        names = registry.names("predictor")
        for label, name in (("early", early), ("late", late)):
            if isinstance(name, Predictor):
                continue
            if name == "hybrid":
                raise ValueError(f"{label} cannot be 'hybrid' itself; allowed: "
                                 f"{', '.join(n for n in names if n != 'hybrid')}")
            if name not in names:
                raise ValueError(f"unknown {label} predictor {name!r}; allowed: "
                                 f"{', '.join(n for n in names if n != 'hybrid')}")
        self.world = world
        self.switch = switch
        self.names = {label: part if isinstance(part, str) else type(part).__name__
                      for label, part in (("early", early), ("late", late))}
        #: The settings each part was built with (a fit hands a part its own predictor of the same settings).
        self.params = {"early": dict(early_params or {}), "late": dict(late_params or {})}
        self.early = early if isinstance(early, Predictor) else \
            registry.create("predictor", {"name": early, **dict(early_params or {})}, world=world)
        self.late = late if isinstance(late, Predictor) else \
            registry.create("predictor", {"name": late, **dict(late_params or {})}, world=world)
        self.counts = {"early_calls": 0, "late_calls": 0, "early_actions": 0, "late_actions": 0}
        #: Whether either predictor prefers one large :meth:`predict_many` to many small ones.
        self.batched = bool(getattr(self.early, "batched", False) or getattr(self.late, "batched", False))
        #: Whether both predictors answer the same in any batch.
        self.batch_invariant = bool(getattr(self.early, "batch_invariant", False)
                                    and getattr(self.late, "batch_invariant", False))

    def route(self, state: State) -> str:
        """``early`` or ``late``: who judges the towers one block larger than ``state``'s."""
        return "late" if len(state.geometry) + 1 >= self.switch else "early"

    def equivalent_switch(self, blocks: int, depth: int) -> int:
        """The switch point whose hybrid answers every question of a depth-``depth`` search from a state of
        ``blocks`` blocks as this one does. Such a search judges towers of ``blocks + 1`` to ``blocks + depth``
        blocks, so every switch point up to ``blocks + 1`` sends them all to ``late`` and every one from
        ``blocks + depth + 1`` all to ``early``: the switch point clamped to that range. A fit computes the
        tables of equivalent switch points once (:func:`overhang_framework.fit.scores.share_tables`); a subclass
        that routes otherwise overrides this too."""
        return min(max(self.switch, blocks + 1), blocks + depth + 1)

    @staticmethod
    def _opted(part) -> bool:
        """Whether ``part`` was asked to answer lazily (``lazy: true`` or ``auto``); a part that is lazy of itself (the
        veridical predictor in a world with deferred verdicts) answers eagerly inside a hybrid, as it always has."""
        return getattr(part, "lazy", False) in (True, "auto") and getattr(part, "predict_lazy", None) is not None

    @property
    def lazy_auto(self) -> bool:
        """Whether the lazy answers are only for searches without a budget: when a lazy part's are
        (``lazy: auto``); the hybrid then answers eagerly under a budget, every part alike."""
        return any(getattr(p, "lazy_auto", False) for p in (self.early, self.late) if self._opted(p))

    @property
    def settle_batch(self) -> int:
        """How many unknown answers a search settles together: the larger of the lazy parts' wishes."""
        return max([1] + [int(getattr(p, "settle_batch", 1) or 1) for p in (self.early, self.late) if self._opted(p)])

    @property
    def settle_inner(self) -> bool:
        """Whether a search settles an inner node's children together: when every lazy part says so."""
        return all(getattr(p, "settle_inner", False) for p in (self.early, self.late) if self._opted(p))

    @property
    def predict_lazy(self):
        """:meth:`_predict_lazy` when either part was asked to answer lazily; else ``None``."""
        return self._predict_lazy if any(self._opted(p) for p in (self.early, self.late)) else None

    def lazy_for(self, state: State) -> bool:
        """Whether the part that judges ``state``'s children answers lazily."""
        return self._opted(getattr(self, self.route(state)))

    def _predict_lazy(self, state: State, actions: Sequence[Action], rng: np.random.Generator):
        """The routed part's lazy answer, or its whole answer when it answers eagerly (nothing left to settle)."""
        which = self.route(state)
        part = getattr(self, which)
        self.counts[f"{which}_calls"] += 1
        self.counts[f"{which}_actions"] += len(actions)
        if self._opted(part):
            return part.predict_lazy(state, actions, rng)
        return np.asarray(part.predict_many([(state, actions)], [rng])[0], dtype=float), None, None

    def predict(self, state: State, actions: Sequence[Action], rng: np.random.Generator) -> np.ndarray:
        return self.predict_many([(state, actions)], [rng])[0]

    def predict_many(self, requests: Sequence[tuple[State, Sequence[Action]]],
                     rngs: Sequence[np.random.Generator]) -> list[np.ndarray]:
        """The requests split by :meth:`route`, each share served by its predictor's own ``predict_many``."""
        out: list = [None] * len(requests)
        for which, predictor in (("early", self.early), ("late", self.late)):
            rows = [i for i, (state, _) in enumerate(requests) if self.route(state) == which]
            if not rows:
                continue
            self.counts[f"{which}_calls"] += len(rows)
            self.counts[f"{which}_actions"] += sum(len(requests[i][1]) for i in rows)
            answers = predictor.predict_many([requests[i] for i in rows], [rngs[i] for i in rows])
            for i, p in zip(rows, answers):
                out[i] = np.asarray(p, dtype=float)
        return out

    def clear_cache(self) -> None:
        """Forget both predictors' remembered answers, where they keep any."""
        for predictor in (self.early, self.late):
            clear = getattr(predictor, "clear_cache", None)
            if callable(clear):
                clear()

    def stats(self) -> dict:
        """Calls and actions each predictor answered, with the predictors' names and the switch point."""
        out = {"early": self.names["early"], "late": self.names["late"], "switch": self.switch, **self.counts}
        for label, predictor in (("early", self.early), ("late", self.late)):
            inner = getattr(predictor, "stats", None)
            if callable(inner):
                out[f"{label}_stats"] = inner()
        return out
