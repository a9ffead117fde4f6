"""The visual-heuristic predictor (paper, Models): a CNN maps an image of the tower after an action to
the probability that it stands.

The model, its renderer and its training live in :mod:`overhang_framework.cnn`; this plugin loads a
checkpoint and scores all the candidate actions of a state in one batched pass, rendering included.
Answers are cached by the canonical geometry key, so a search that meets a tower again pays nothing.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Optional, Sequence

import numpy as np

from overhang_framework.geometry import Action
from overhang_framework.interfaces import Predictor, State, World


class Calibration:
    """``p -> sigmoid(logit(p) / temperature + bias)``; the identity at temperature 1 and bias 0."""

    #: Answers are clipped this far from 0 and 1 before the logit (a network's answer can round to 1).
    EPS = 1e-9

    def __init__(self, temperature: float = 1.0, bias: float = 0.0):
        for name, value in (("temperature", temperature), ("bias", bias)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
        if temperature <= 0:
            raise ValueError(f"temperature must be a number > 0, got {temperature!r}")
        self.temperature, self.bias = float(temperature), float(bias)
        self.identity = self.temperature == 1.0 and self.bias == 0.0

    def __call__(self, p: np.ndarray) -> np.ndarray:
        if self.identity:
            return p
        q = np.clip(np.asarray(p, dtype=float), self.EPS, 1.0 - self.EPS)
        z = (np.log(q) - np.log1p(-q)) / self.temperature + self.bias
        return 1.0 / (1.0 + np.exp(-z))

    def one(self, p: float) -> float:
        return p if self.identity else float(self(np.array([p]))[0])


class CNNPredictor(Predictor):
    """Stability probabilities from a trained CNN checkpoint.

    ``checkpoint`` is ``default`` (the model shipped with the package, see
    ``overhang_framework/cnn/checkpoints/default.md``) or a path to a ``.pt``
    file written by ``python -m overhang_framework.cnn.train``. ``device`` is
    ``auto`` (a GPU when present), ``cpu`` or ``cuda``; ``threads`` sets
    torch's CPU threads for the process, 1 by default: with more, torch's
    threads wait on each other, and on a machine where another job holds a
    core a forward pass becomes tens of times slower (``null``: torch's
    default of one thread per core; docs/cnn.md says when that pays). ``batch_size`` caps the
    images of one forward pass; ``cache_size`` the towers remembered (0: no
    cache). ``mirror`` averages the answers for each tower and its mirror
    image; ``auto`` follows the checkpoint, whose training records whether
    that scored higher on validation. ``fused`` (default) folds the network's
    batch norms into its convolutions and runs it with ``runtime``
    (``onnxruntime`` or ``torch``), which changes the answers by float rounding
    only, and marks the predictor :attr:`batched`: score tables then ask for
    the towers of many states in one call; ``false`` is the network as
    trained, run by torch and asked state by state (the reference for tests
    and benchmarks). ``temperature`` and ``bias`` recalibrate every answer on the logit scale,
    ``p' = sigmoid(logit(p) / temperature + bias)``: a temperature below 1 makes the network more
    confident and above 1 less; a positive bias makes it judge towers standing more often (1 and 0, the
    defaults, leave the answers as trained). The cache keeps the network's own answers. ``lazy`` lets a search ask only for the towers whose answer can change its result,
    ``settle_batch`` at a time (docs/planners.md, "Lazy answers"); the scores are the same, and it needs
    ONNX Runtime, whose answer for a tower does not depend on the batch. The predictor is deterministic:
    ``rng`` is not used.
    """

    deterministic = True

    @staticmethod
    def content_identity(params) -> dict:
        """What the answers of a CNN of settings ``params`` depend on beyond them: the SHA-256 of the bytes of the
        checkpoint file it loads (``checkpoint``, a shipped network's name or a path), so that score tables are
        keyed by the weights, not by the checkpoint's name (:func:`overhang_framework.fit.scores.content_identity`)."""
        from overhang_framework.cnn.model import resolve_checkpoint
        from overhang_framework.results import file_sha256

        try:
            path = resolve_checkpoint(params.get("checkpoint", "default"))
        except ValueError:
            return {}
        return {"checkpoint_sha256": file_sha256(path)}

    def __init__(self, world: World, checkpoint: str = "default", device: str = "auto",
                 threads: Optional[int] = 1, batch_size: int = 64, cache_size: int = 200_000,
                 mirror="auto", fused: bool = True, runtime: str = "onnxruntime", lazy="auto",
                 settle_batch: int = 16, temperature: float = 1.0, bias: float = 0.0):
        from overhang_framework.cnn.model import StabilityModel

        if isinstance(cache_size, bool) or not isinstance(cache_size, int) or cache_size < 0:
            raise ValueError(f"cache_size must be a whole number >= 0, got {cache_size!r}")
        if not isinstance(lazy, bool) and lazy != "auto":
            raise ValueError(f"lazy must be true, false or auto, got {lazy!r}")
        if isinstance(settle_batch, bool) or not isinstance(settle_batch, int) or settle_batch < 1:
            raise ValueError(f"settle_batch must be a whole number >= 1, got {settle_batch!r}")
        self.calibration = Calibration(temperature, bias)
        self.world = world
        self.lazy = lazy
        self.settle_batch = settle_batch
        #: a search settles an inner node's children together (a batch costs about the same per answer)
        self.settle_inner = True
        self.model = StabilityModel(checkpoint, device=device, threads=threads, batch_size=batch_size,
                                    mirror=mirror, fused=fused, runtime=runtime)
        #: One large :meth:`predict_many` costs much less than many small ones (see ``fit.scores``).
        self.batched = fused
        #: Whether a tower's answer is the same in any batch: ONNX Runtime's on the CPU is, to the bit;
        #: torch's differs by float rounding (about 1e-6) with the batch's size.
        self.batch_invariant = self.model.runtime == "onnxruntime"
        if lazy is True and not self.batch_invariant:
            raise ValueError("lazy needs a tower's answer to be the same in any batch, which only "
                             "runtime=onnxruntime on the CPU gives (with fused=true); this network runs in torch")
        if lazy == "auto":  # lazy where it keeps every answer to the bit, in searches without a budget
            self.lazy = self.batch_invariant and "auto"
        self.cache_size = cache_size
        self._cache: OrderedDict = OrderedDict()
        self.counts = {"towers": 0, "cache_hits": 0, "images": 0}

    def probabilities(self, geometries) -> np.ndarray:
        """Stability probability of each geometry, recalibrated by ``temperature`` and ``bias``."""
        return self.calibration(self.raw_probabilities(geometries))

    def raw_probabilities(self, geometries) -> np.ndarray:
        """The network's own probability for each geometry (cached by canonical key; a tower listed twice
        in one call is scored once when the cache is on)."""
        out = np.empty(len(geometries))
        missing: dict = {}  # key -> the indices of the geometries that need it
        for i, g in enumerate(geometries):
            key = g.key
            hit = self._cache.get(key) if self.cache_size else None
            if hit is None:
                missing.setdefault(key if self.cache_size else i, []).append(i)
            else:
                out[i] = hit
        self.counts["towers"] += len(geometries)
        self.counts["cache_hits"] += len(geometries) - len(missing)
        if missing:
            rows = list(missing.values())
            probs = self.model.probabilities([geometries[r[0]] for r in rows])
            self.counts["images"] += len(rows) * self.model.images_per_tower
            for r, p in zip(rows, probs):
                out[r] = p
            if self.cache_size:
                for key, p in zip(missing, probs):
                    self._cache[key] = float(p)
                while len(self._cache) > self.cache_size:
                    self._cache.popitem(last=False)
        return out

    def predict(self, state: State, actions: Sequence[Action], rng: np.random.Generator) -> np.ndarray:
        if not len(actions):
            return np.zeros(0)
        return self.probabilities([self.world.successor(state, a).geometry for a in actions])

    @property
    def predict_lazy(self):
        """With ``lazy`` (``true`` or ``auto``), :meth:`_predict_lazy`; else ``None`` (searches then call
        :meth:`predict`)."""
        return self._predict_lazy if self.lazy else None

    @property
    def lazy_auto(self) -> bool:
        """Whether the answers are lazy only where that changes nothing a search reports: ``lazy: auto``
        (see :class:`~overhang_framework.search.Expander`)."""
        return self.lazy == "auto"

    def _predict_lazy(self, state: State, actions: Sequence[Action], rng: np.random.Generator):
        """Every answer unknown for now, with the functions that give given actions' answers: ``classify`` the
        remembered ones (-1 for the others) and ``settle`` the network's, in one pass; a search asks only
        for the towers whose answer can change its result (:class:`~overhang_framework.search.Expansion`)."""
        made: list = [None] * len(actions)  # each tower drawn up when first asked about

        def geometry(i):
            g = made[i]
            if g is None:
                g = made[i] = self.world.successor(state, actions[i]).geometry
            return g

        def classify(indices):
            out = np.full(len(indices), -1.0)
            if self.cache_size:
                for n, i in enumerate(indices):
                    hit = self._cache.get(geometry(i).key)
                    if hit is not None:
                        out[n] = self.calibration.one(hit)
            return out

        def settle(indices):
            return self.probabilities([geometry(i) for i in indices])

        return np.full(len(actions), np.nan), settle, classify

    def predict_many(self, requests: Sequence[tuple[State, Sequence[Action]]],
                     rngs: Sequence[np.random.Generator]) -> list[np.ndarray]:
        """Every request's candidates rendered and scored together: one pass over all the images."""
        towers, bounds = [], [0]
        for state, actions in requests:
            towers.extend(self.world.successor(state, a).geometry for a in actions)
            bounds.append(len(towers))
        probs = self.probabilities(towers) if towers else np.zeros(0)
        return [probs[a:b] for a, b in zip(bounds[:-1], bounds[1:])]

    def clear_cache(self) -> None:
        """Forget the remembered answers (a benchmark that times cold work calls this)."""
        self._cache.clear()

    def stats(self) -> dict:
        """Towers asked about, cache hits, and images the network scored."""
        return dict(self.counts)
