"""Simulation-based predictors: the Intuitive Physics Engine (IPE) and its noise-free case.

The IPE (paper, Models) scores a candidate action by running ``K`` forward
simulations of the tower after the action, each under a Gaussian perturbation
of block positions, gravity and friction, and reporting the fraction of runs in
which the tower stands:

    p_IPE(stable | s, a) = (1 / K) * sum_i 1[Stable^(i)(G_{t+1})]

The veridical predictor is the same code with no noise and one sample.

Perturbations
-------------
Every perturbation is ``sigma * eps`` with ``eps ~ N(0, 1)``; each channel has its
own ``sigma`` (the paper's single ``sigma = 0.03`` is the default for all three).
Units are those of the task: metres, radians, and the dimensionless friction
coefficient.

``position`` (metres, per block, per sample)
    The x of every block's centre, the ground block included, is offset by
    ``sigma_position * eps``. The layer, and so z, is kept: blocks still rest on
    one another, because a vertical offset would only open a gap the block drops
    through or an interpenetration the solver ejects, not uncertainty about
    support. Offsets that make two blocks of one layer overlap are removed by
    the smallest equal-weight displacement that restores contact (the
    least-squares projection onto non-penetration, computed by isotonic
    regression); the scene a perceiver imagines still obeys the task's
    non-penetration rule. A block whose support is lost falls, as it should.

``gravity`` (radians and relative magnitude, per sample)
    The gravity vector of one run is ``g * s * (sin(theta), -cos(theta))`` with
    tilt ``theta = sigma_gravity * eps1`` radians and scale
    ``s = 1 + sigma_gravity * eps2``, where ``g`` is the backend's gravity
    (9.81 m/s^2). This is a Gaussian perturbation of gravity expressed in units
    of ``g``: adding ``N(0, sigma^2) * g`` to each component of ``(0, -g)`` is the
    same to first order. The alternative, ``N(0, sigma^2)`` in m/s^2, would be a
    0.3% perturbation that no tower can feel, which cannot be what the paper
    fitted. Gravity is a field, so one vector per run (the backends take one
    per scene) rather than one per block. A tilt shifts the effective centre of
    mass of a block at height h by about ``h * theta``, so its effect grows with
    the tower's height; the scale changes only how fast an unstable tower falls.

``friction`` (dimensionless coefficient, per block, per sample)
    The lateral friction coefficient of every block is
    ``mu + sigma_friction * eps``, clipped at 0, where ``mu`` is the backend's
    friction (0.5 in the reference world).

Common random numbers
---------------------
One call draws ``eps`` once, as standard normals of shape ``(K, n)`` for
positions, ``(K, 2)`` for gravity and ``(K, n)`` for friction, in that order,
``n`` being the number of blocks after the action; every candidate action of
the call is simulated under the same ``K`` draws (the new block's offset is the
last column). Differences between candidates are therefore not sampling noise,
and scoring actions one at a time from the same seed gives the same numbers as
scoring them together. The draws are made whatever the sigmas are (scaled by
zero where a sigma is 0), so changing one channel's sigma leaves the other
channels' draws unchanged; with every sigma 0 nothing is drawn and each
successor is checked once, exactly as the veridical predictor checks it.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np

from overhang_framework.geometry import Action, Block, Geometry, separate_overlaps
from overhang_framework.interfaces import Predictor, State, World
from overhang_framework.physics import PhysicsBackend

BACKENDS = ("static", "pybullet", "world")
#: How scenes reach a backend that takes arrays: as arrays, or as a Geometry each (the reference path).
SCENE_PATHS = ("arrays", "objects")
DEFAULT_FRICTION = 0.5
DEFAULT_GRAVITY = 9.81


@dataclass(frozen=True)
class Noise:
    """Standard deviations of the three perturbation channels (see the module docstring)."""

    position: float = 0.03
    gravity: float = 0.03
    friction: float = 0.03

    def __post_init__(self):
        for channel in ("position", "gravity", "friction"):
            value = getattr(self, channel)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"sigma for {channel} must be a finite number >= 0, got {value!r}")

    @property
    def zero(self) -> bool:
        return self.position == 0 and self.gravity == 0 and self.friction == 0


@dataclass(frozen=True)
class Draws:
    """Standard normal draws for one decision, shared by all its candidate actions."""

    position: np.ndarray  # (K, n)
    gravity: np.ndarray  # (K, 2): tilt, scale
    friction: np.ndarray  # (K, n)

    @classmethod
    def sample(cls, rng: np.random.Generator, k: int, n_blocks: int) -> "Draws":
        position = rng.standard_normal((k, n_blocks))
        gravity = rng.standard_normal((k, 2))
        friction = rng.standard_normal((k, n_blocks))
        return cls(position, gravity, friction)


@dataclass(frozen=True)
class Scenes:
    """What one decision asks the backend: the scenes, candidate-major, and how to read the verdicts.

    The scenes are arrays of shape ``(scenes, blocks)``: every block's ``widths``, the ``xs`` of its
    centre and its ``layers``. ``repeat`` marks noise-free scenes, one per candidate, whose verdict
    stands for all ``samples`` simulations.
    """

    widths: np.ndarray
    xs: np.ndarray
    layers: np.ndarray
    gravity: Optional[np.ndarray]
    friction: Optional[np.ndarray]
    candidates: int
    samples: int
    repeat: bool

    @property
    def size(self) -> int:
        return int(self.widths.shape[0])

    @property
    def geometries(self) -> list[Geometry]:
        """The scenes as :class:`Geometry` objects (for backends that take only those)."""
        out = []
        for w_row, x_row, l_row in zip(self.widths.tolist(), self.xs.tolist(), self.layers.tolist()):
            out.append(Geometry(tuple(Block(w, x, int(l)) for w, x, l in zip(w_row, x_row, l_row))))
        return out

    @classmethod
    def of(cls, geometries: Sequence[Geometry], gravity, friction, candidates: int, samples: int,
           repeat: bool) -> "Scenes":
        n = len(geometries[0]) if geometries else 0
        arr = np.stack([g.as_array() for g in geometries]) if geometries else np.zeros((0, n, 3))
        return cls(arr[:, :, 0], arr[:, :, 1], arr[:, :, 2].astype(np.int64), gravity, friction, candidates,
                   samples, repeat)


def _stack(parts: list):
    """Rows of ``parts`` as one array, or a list of rows when their lengths differ."""
    if not parts or all(p is None for p in parts):
        return None
    if any(p is None for p in parts):
        raise ValueError("scenes with and without gravity or friction noise cannot share one backend call")
    if len({p.shape[1:] for p in parts}) == 1:
        return np.concatenate(parts, axis=0)
    return [row for p in parts for row in p]


def _rng_state(rng: np.random.Generator):
    """The state of ``rng``'s bit generator, hashable."""
    state = rng.bit_generator.state
    inner = state.get("state")
    if isinstance(inner, dict) and set(inner) <= {"state", "inc"}:
        return (state["bit_generator"], inner.get("state"), inner.get("inc"), state.get("has_uint32"),
                state.get("uinteger"))
    return repr(state)


def _padded(parts: list, fill) -> np.ndarray:
    """``(rows, n_i)`` arrays side by side as one ``(rows, max n_i)`` array, padded with ``fill``."""
    n = max(p.shape[1] for p in parts)
    if all(p.shape[1] == n for p in parts):
        return np.concatenate(parts, axis=0)
    return np.concatenate([np.pad(p, ((0, 0), (0, n - p.shape[1])), constant_values=fill) for p in parts], axis=0)


class IPEPredictor(Predictor):
    """The Intuitive Physics Engine: the fraction of ``K`` perturbed simulations that stand.

    ``K`` is the number of simulations per candidate action. ``sigma`` is the
    noise scale of every channel; ``sigma_position`` (metres),
    ``sigma_gravity`` (radians of tilt and relative magnitude) and
    ``sigma_friction`` (friction coefficient) override it per channel when not
    ``None``. ``backend`` is ``static`` (fast static-equilibrium physics),
    ``pybullet`` (the paper's simulator) or ``world`` (whatever physics the
    world uses, through ``world.backend``), or a backend object to use as is
    (a process pool, say). ``static`` and ``pybullet`` take the
    world's parameters for that backend (``world.backend_params``), updated by
    ``backend_params``. ``scenes`` is how the scenes reach a backend that takes arrays (the static one):
    ``arrays`` (no Python object per scene) or ``objects`` (a :class:`Geometry` each, the reference path;
    the same verdicts). ``lazy`` lets a search ask only for the candidates whose answer can change its
    result, ``settle_batch`` at a time, under the draws of the call (docs/planners.md, "Lazy answers"); the
    answers are the same. The module docstring defines each perturbation.
    """

    def __init__(self, world: World, K: int = 50, sigma: float = 0.03,
                 sigma_position: Optional[float] = None, sigma_gravity: Optional[float] = None,
                 sigma_friction: Optional[float] = None, backend: Union[str, PhysicsBackend] = "static",
                 backend_params: Optional[Mapping[str, Any]] = None, scenes: str = "arrays",
                 lazy: bool = False, settle_batch: int = 16):
        if isinstance(K, bool) or not isinstance(K, (int, float)) or int(K) != K or K < 1:
            raise ValueError(f"K must be a whole number >= 1, got {K!r}")
        for name, value in (("sigma", sigma), ("sigma_position", sigma_position),
                            ("sigma_gravity", sigma_gravity), ("sigma_friction", sigma_friction)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                      or not np.isfinite(value) or value < 0):
                raise ValueError(f"{name} must be a number >= 0, got {value!r}")
        if isinstance(backend, str) and backend not in BACKENDS:
            raise ValueError(f"unknown IPE backend {backend!r}; allowed: {', '.join(BACKENDS)}")
        if scenes not in SCENE_PATHS:
            raise ValueError(f"unknown IPE scenes {scenes!r}; allowed: {', '.join(SCENE_PATHS)}")
        if not isinstance(lazy, bool):
            raise ValueError(f"lazy must be true or false, got {lazy!r}")
        if isinstance(settle_batch, bool) or not isinstance(settle_batch, int) or settle_batch < 1:
            raise ValueError(f"settle_batch must be a whole number >= 1, got {settle_batch!r}")
        self.scene_path = scenes
        self.lazy = lazy
        self.settle_batch = settle_batch
        #: a search settles an inner node's children together (a batch costs about the same per answer)
        self.settle_inner = True
        #: a scene's verdict does not depend on the scenes simulated with it (the static backend decides each
        #: alone; only the rare scene that NNLS leaves to HiGHS is solved in a stacked LP, none of 87,050)
        self.batch_invariant = True
        self.world = world
        self.K = int(K)
        self.memory_size = 0
        self._memory: OrderedDict = OrderedDict()
        self.counts = {"calls": 0, "remembered": 0}
        self.noise = Noise(
            position=float(sigma if sigma_position is None else sigma_position),
            gravity=float(sigma if sigma_gravity is None else sigma_gravity),
            friction=float(sigma if sigma_friction is None else sigma_friction),
        )
        self.backend_name = backend if isinstance(backend, str) else getattr(backend, "name", "custom")
        if backend_params is not None and not isinstance(backend_params, Mapping):
            raise ValueError(f"backend_params must be a mapping of parameter names to values, got {backend_params!r}")
        self.backend_params = dict(backend_params or {})
        self._backend = None if isinstance(backend, str) else backend
        if self._backend is None and self.backend_name in ("static", "pybullet"):
            from overhang_framework.physics.factory import backend_params as checked

            params = dict(getattr(world, "backend_params", {}).get(self.backend_name, {}))
            params.update(self.backend_params)
            checked(self.backend_name, **params)  # refuse unknown or bad parameters now, not mid-run

    @property
    def deterministic(self) -> bool:
        """True when every sigma is 0: the successors themselves are simulated, and ``rng`` is not used."""
        return self.noise.zero

    @property
    def backend(self):
        """The physics backend the simulations run on (built on first use)."""
        if self._backend is None:
            self._backend = self._make_backend()
        return self._backend

    def _make_backend(self):
        if self.backend_name == "world":
            backend = getattr(self.world, "backend", None)
            if backend is None:
                raise ValueError(
                    f"backend 'world' needs a world with a .backend; {type(self.world).__name__} has none"
                )
            return backend if self.noise.zero else getattr(backend, "backend", backend)
        from overhang_framework.physics.factory import make_backend

        params = dict(getattr(self.world, "backend_params", {}).get(self.backend_name, {}))
        params.update(self.backend_params)
        return make_backend(self.backend_name, **params)

    def _constant(self, name: str, default: float) -> float:
        backend = self.backend
        for holder in (backend, getattr(backend, "backend", None)):
            params = getattr(holder, "params", None)
            if params is not None and getattr(params, name, None) is not None:
                return float(getattr(params, name))
        return default

    def successors(self, state: State, actions: Sequence[Action]) -> list[Geometry]:
        return [self.world.successor(state, a).geometry for a in actions]

    def scenes(self, state: State, actions: Sequence[Action], rng: np.random.Generator) -> "Scenes":
        """The scenes to simulate for ``actions``: ``len(actions) * K`` perturbed ones, or the
        ``len(actions)`` successors themselves when every sigma is 0 (then ``rng`` is not used)."""
        geometries = self.successors(state, actions)
        return self._scenes(geometries, self.draws(rng, geometries))

    def draws(self, rng: np.random.Generator, geometries: Sequence[Geometry]) -> Optional[Draws]:
        """The one set of draws every candidate of a call shares (``None`` when nothing is drawn)."""
        if not geometries or self.noise.zero:
            return None
        return Draws.sample(rng, self.K, len(geometries[0]))

    def _scenes(self, geometries: Sequence[Geometry], draws: Optional[Draws]) -> "Scenes":
        if not geometries:
            return Scenes.of([], None, None, 0, self.K, repeat=True)
        if draws is None:
            return Scenes.of(geometries, None, None, len(geometries), self.K, repeat=True)
        (widths, xs, layers), gravity, friction = self.perturb_arrays(geometries, draws)
        return Scenes(widths, xs, layers, gravity, friction, len(geometries), self.K, repeat=False)

    @property
    def predict_lazy(self):
        """With ``lazy``, :meth:`_predict_lazy`; else ``None`` (searches then call :meth:`predict`)."""
        return self._predict_lazy if self.lazy else None

    def _predict_lazy(self, state: State, actions: Sequence[Action], rng: np.random.Generator):
        """Every answer unknown for now, with the functions that give given actions' answers: the call's
        draws are made now, as :meth:`predict` makes them, and ``settle`` simulates only the candidates it is
        asked about under them, so each answer is the one :meth:`predict` gives. ``classify`` gives the
        remembered answers (:meth:`remember`), -1 for the others. A search asks only for the candidates whose
        answer can change its result (:class:`~overhang_framework.search.Expansion`)."""
        self.counts["calls"] += 1
        geometries = self.successors(state, actions)
        memo = None
        if self.memory_size:
            key = ("lazy", state.geometry.blocks, state.remaining, tuple(actions),
                   None if self.noise.zero else _rng_state(rng))
            hit = self._memory.get(key)
            if hit is not None:
                self._memory.move_to_end(key)
                if hit[1] is not None:
                    rng.bit_generator.state = hit[1]
                self.counts["remembered"] += 1
                draws, memo = hit[2], hit[0]
            else:
                draws = self.draws(rng, geometries)
                memo = np.full(len(actions), np.nan)
                self._memory[key] = (memo, None if self.noise.zero else rng.bit_generator.state, draws)
                while len(self._memory) > self.memory_size:
                    self._memory.popitem(last=False)
        else:
            draws = self.draws(rng, geometries)

        def classify(indices):
            if memo is None:
                return np.full(len(indices), -1.0)
            known = memo[np.asarray(indices, dtype=int)]
            return np.where(np.isnan(known), -1.0, known)

        def settle(indices):
            verdicts = self.run([self._scenes([geometries[i] for i in indices], draws)])[0]
            p = verdicts.mean(axis=1)
            if memo is not None:
                memo[np.asarray(indices, dtype=int)] = p
            return p

        return np.full(len(actions), np.nan), settle, classify

    def run(self, scenes: Sequence["Scenes"]) -> list[np.ndarray]:
        """Simulate several :class:`Scenes` in one backend call; one ``(candidates, K)`` boolean array each.

        A backend with ``stable_arrays`` (the static one) takes the scenes as arrays, unless ``scenes`` is
        ``objects``; any other gets a :class:`Geometry` per scene.
        """
        busy = [sc for sc in scenes if sc.size]
        if not busy:
            return [np.zeros((sc.candidates, sc.samples), dtype=bool) for sc in scenes]
        gravity = _stack([sc.gravity for sc in busy])
        friction = _stack([sc.friction for sc in busy])
        backend = self.backend
        if self.scene_path == "arrays" and hasattr(backend, "stable_arrays"):
            # scenes of states with fewer blocks are padded (width 0), their friction rows alike
            if friction is not None:
                friction = _padded([sc.friction for sc in busy], 0.0)
            verdicts = backend.stable_arrays(_padded([sc.widths for sc in busy], 0.0), _padded([sc.xs for sc in busy], 0.0),
                                             _padded([sc.layers for sc in busy], -1), gravity, friction)
        else:
            geometries = [g for sc in busy for g in sc.geometries]
            verdicts = backend.stable_batch(geometries, gravity, friction)
        verdicts = np.asarray(verdicts, dtype=bool)
        out, start = [], 0
        for sc in scenes:
            chunk = verdicts[start:start + sc.size]
            start += sc.size
            if sc.repeat:
                out.append(np.repeat(chunk[:, None], sc.samples, axis=1))
            else:
                out.append(chunk.reshape(sc.candidates, sc.samples))
        return out

    def sample_verdicts(self, state: State, actions: Sequence[Action],
                        rng: np.random.Generator) -> np.ndarray:
        """Boolean ``(len(actions), K)`` verdicts of every simulation, under common random numbers."""
        return self.run([self.scenes(state, actions, rng)])[0]

    def perturb_arrays(self, geometries: Sequence[Geometry], draws: Draws):
        """The ``len(geometries) * K`` perturbed scenes, candidate-major, as arrays.

        Returns ``((widths, xs, layers), gravity, friction)``: three ``(C*K, n)`` arrays, ``gravity``
        ``(C*K, 2)`` or ``None`` when its sigma is 0, ``friction`` ``(C*K, n)`` or ``None`` likewise.
        """
        arr = np.stack([g.as_array() for g in geometries])  # (C, n, 3)
        c, n, _ = arr.shape
        k = draws.position.shape[0]
        widths, layers = arr[:, :, 0], arr[:, :, 2].astype(np.int64)
        xs = arr[:, None, :, 1] + self.noise.position * draws.position[None]  # (C, K, n)
        if self.noise.position > 0:
            # candidates with the same layers and left-to-right order in each layer are separated together
            order = np.lexsort((arr[:, :, 1], layers), axis=1)
            groups: dict = {}
            for i in range(c):
                groups.setdefault((layers[i].tobytes(), order[i].tobytes(), widths[i].tobytes()), []).append(i)
            for members in groups.values():
                i = members[0]
                rows = xs[members].reshape(len(members) * k, n)
                xs[members] = separate_overlaps(rows, widths[i], layers[i], arr[i, :, 1]).reshape(len(members), k, n)
        gravity = None
        if self.noise.gravity > 0:
            g = self._constant("gravity", DEFAULT_GRAVITY)
            theta = self.noise.gravity * draws.gravity[:, 0]
            scale = np.maximum(1.0 + self.noise.gravity * draws.gravity[:, 1], 0.0)
            vec = np.stack([g * scale * np.sin(theta), -g * scale * np.cos(theta)], axis=1)
            gravity = np.tile(vec, (c, 1))
        friction = None
        if self.noise.friction > 0:
            mu = self._constant("friction", DEFAULT_FRICTION)
            rows = np.maximum(mu + self.noise.friction * draws.friction, 0.0)
            friction = np.tile(rows, (c, 1))
        shape = (c * k, n)
        return ((np.broadcast_to(widths[:, None, :], (c, k, n)).reshape(shape), xs.reshape(shape),
                 np.broadcast_to(layers[:, None, :], (c, k, n)).reshape(shape)), gravity, friction)

    def perturb(self, geometries: Sequence[Geometry], draws: Draws):
        """:meth:`perturb_arrays` with a :class:`Geometry` per scene: ``(scenes, gravity, friction)``."""
        (widths, xs, layers), gravity, friction = self.perturb_arrays(geometries, draws)
        scenes = Scenes(widths, xs, layers, gravity, friction, len(geometries), draws.position.shape[0], False)
        return scenes.geometries, gravity, friction

    def remember(self, size: int = 100_000) -> None:
        """Keep the answers of the last ``size`` calls (0: none), keyed by the tower, the actions and the
        generator's state, so a question asked again with the same draws (by the hybrids of every switch
        point of a fit, say) is answered without simulating. The generator is left as the simulation would
        leave it, so remembering changes no number."""
        if isinstance(size, bool) or not isinstance(size, int) or size < 0:
            raise ValueError(f"size must be a whole number >= 0, got {size!r}")
        self.memory_size = size
        while len(self._memory) > size:
            self._memory.popitem(last=False)

    def clear_cache(self) -> None:
        """Forget the remembered answers."""
        self._memory.clear()

    def stats(self) -> dict:
        """Calls answered, and how many of them from the remembered answers."""
        return dict(self.counts)

    def predict(self, state: State, actions: Sequence[Action], rng: np.random.Generator) -> np.ndarray:
        return self.predict_many([(state, actions)], [rng])[0]

    def predict_many(self, requests: Sequence[tuple[State, Sequence[Action]]],
                     rngs: Sequence[np.random.Generator]) -> list[np.ndarray]:
        """:meth:`predict` for several states, simulated in one backend call."""
        self.counts["calls"] += len(requests)
        if not self.memory_size:
            scenes = [self.scenes(state, actions, rng) for (state, actions), rng in zip(requests, rngs)]
            return [verdicts.mean(axis=1) for verdicts in self.run(scenes)]
        # each request in turn, as a simulation would take them: its key is the generator's state just
        # before its own draws, and the state after them is what a remembered answer puts back
        out: list = [None] * len(requests)
        todo, scenes, keys, after = [], [], [], []
        for i, ((state, actions), rng) in enumerate(zip(requests, rngs)):
            key = (state.geometry.blocks, state.remaining, tuple(actions),
                   None if self.noise.zero else _rng_state(rng))
            hit = self._memory.get(key)
            if hit is not None:
                self._memory.move_to_end(key)
                out[i] = hit[0].copy()
                if hit[1] is not None:
                    rng.bit_generator.state = hit[1]
                self.counts["remembered"] += 1
                continue
            todo.append(i)
            scenes.append(self.scenes(state, actions, rng))
            keys.append(key)
            after.append(None if self.noise.zero else rng.bit_generator.state)
        if todo:
            for i, key, state_after, verdicts in zip(todo, keys, after, self.run(scenes)):
                out[i] = verdicts.mean(axis=1)
                self._memory[key] = (out[i].copy(), state_after)
            while len(self._memory) > self.memory_size:
                self._memory.popitem(last=False)
        return out


class VeridicalPredictor(IPEPredictor):
    """Noise-free physics: 1 where the world's physics says the tower stands, else 0.

    The IPE with every sigma 0 and one sample; ``backend`` defaults to the
    world's own (cached) physics.
    """

    def __init__(self, world: World, backend: Union[str, PhysicsBackend] = "world",
                 backend_params: Optional[Mapping[str, Any]] = None):
        super().__init__(world, K=1, sigma=0.0, backend=backend, backend_params=backend_params)
        self.settle_batch = 1  # the world's own settling batches by its physics workers
        self.settle_inner = False  # a reference verdict is dear: settled one by one as the search needs it

    @property
    def world_verdicts(self) -> bool:
        """Whether the probabilities are exactly the world's own verdicts (1 stands, 0 falls)."""
        return self.backend_name == "world" and not self.backend_params

    @property
    def predict_lazy(self):
        """With the world's own verdicts from a world that can say which are cheap
        (``deferred_verdicts`` and ``stability_bounds``), :meth:`_predict_lazy`; else ``None`` (searches then call :meth:`predict`)."""
        if self.world_verdicts and getattr(self.world, "deferred_verdicts", False):
            return self._predict_lazy
        return None

    def _predict_lazy(self, state: State, actions: Sequence[Action], rng: np.random.Generator):
        """Every verdict unknown for now, with the functions that give given actions' verdicts: ``classify``
        what the world knows cheaply (1, 0, or -1 where only the reference can tell) and ``settle`` the
        verdict itself; a search asks only for what can change its result
        (:class:`~overhang_framework.search.Expansion`)."""
        geometries = self.successors(state, actions)

        def classify(indices):
            return np.asarray(self.world.stability_bounds([geometries[i] for i in indices]))

        def settle(indices):
            return np.asarray(self.world.settle([geometries[i] for i in indices]), dtype=float)

        return np.full(len(actions), np.nan), settle, classify
