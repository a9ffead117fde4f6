"""The CNN's data set: random partial towers of the task space, labelled by the reference physics.

A *question* is what a planner asks a predictor: a tower whose every block
before the last stands, plus one more block, and whether the tower stands
after it. Questions are drawn at every construction stage (``min_blocks`` to
``max_blocks`` blocks after the action, uniformly):

* the first block, of a random width, stands on the ground at x = 0;
* every further block but the last gets a random width and a uniformly random
  legal action (x on a ``resolution`` grid), redrawn until the static model
  says the tower still stands;
* the last block gets a random width and a random legal action (``random``
  questions) or, for a fraction ``near_critical`` of them, is moved to within
  ``window`` of the x where the static model's verdict flips (``near_critical``
  questions: the towers whose verdict is hardest to see).

The label is the world's reference physics (``tiered`` by default: the
full-window PyBullet verdicts). Each shard is balanced: within each kind, the
more common verdict is subsampled to the count of the other.

Shards are ``shard-00000.npz`` files in one directory, each with its seed and
the physics settings in ``meta``; :func:`generate` skips shards already on disk
with the same settings (so an interrupted run resumes) and refuses a directory
made with other settings. The ``manifest.json`` beside them records the
settings of the whole set.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable, Optional, Sequence

import numpy as np

from overhang_framework.geometry import WIDTHS, Action, Block, Geometry
from overhang_framework.results import atomic_output, atomic_write_json
from overhang_framework.rules import place, random_legal_action

FORMAT = 1
MAX_BLOCKS_STORED = 8


@dataclass(frozen=True)
class DataSpec:
    """What a data set holds; two sets with equal specs and seeds are identical."""

    seed: int = 0
    shards: int = 16
    shard_size: int = 2000
    min_blocks: int = 2
    max_blocks: int = 7
    near_critical: float = 0.3
    window: float = 0.05
    resolution: float = 0.01
    physics: str = "tiered"
    physics_params: dict = field(default_factory=dict)

    def __post_init__(self):
        def whole(name, low):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ValueError(f"{name} must be a whole number >= {low}, got {v!r}")

        whole("seed", 0)
        whole("shards", 1)
        whole("shard_size", 2)
        whole("min_blocks", 2)
        whole("max_blocks", self.min_blocks if isinstance(self.min_blocks, int) else 2)
        if self.max_blocks > MAX_BLOCKS_STORED:
            raise ValueError(f"max_blocks must be at most {MAX_BLOCKS_STORED}, got {self.max_blocks!r}")
        for name, lo, hi in (("near_critical", 0.0, 1.0), ("window", 0.0, 1.0), ("resolution", 1e-4, 1.0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v <= hi:
                raise ValueError(f"{name} must be a number in [{lo:g}, {hi:g}], got {v!r}")
        from overhang_framework.physics.factory import BACKENDS

        if self.physics not in BACKENDS:
            raise ValueError(f"unknown physics {self.physics!r}; allowed: {', '.join(BACKENDS)}")

    def settings(self) -> dict:
        """The spec as plain data, without the number of shards (a set may grow by more shards)."""
        d = asdict(self)
        d.pop("shards")
        d["format"] = FORMAT
        return json.loads(json.dumps(d))


# --------------------------------------------------------------------------------------------------
# Sampling


def _grow(rng: np.random.Generator, towers: list[Geometry], resolution: float) -> list[tuple[Geometry, float, Action]]:
    """One random (width, legal action) for the top of each tower: ``(tower, width, action)``."""
    out = []
    for g in towers:
        width = WIDTHS[rng.integers(len(WIDTHS))]
        out.append((g, width, random_legal_action(g, width, resolution, rng)))
    return out


def standing_prefixes(rng: np.random.Generator, sizes: Sequence[int], static, resolution: float,
                      max_tries: int = 50) -> list[Geometry]:
    """Towers of ``sizes[i]`` blocks each, every prefix standing by the ``static`` backend."""
    towers = [Geometry((Block(WIDTHS[rng.integers(len(WIDTHS))], 0.0, 0),)) for _ in sizes]
    sizes = np.asarray(sizes)
    for level in range(2, int(sizes.max(initial=1)) + 1):
        todo = np.flatnonzero(sizes >= level)
        for _ in range(max_tries):
            if not todo.size:
                break
            grown = [place(*t) for t in _grow(rng, [towers[i] for i in todo], resolution)]
            ok = np.asarray(static.stable_batch(grown), dtype=bool)
            for i, g, good in zip(todo, grown, ok):
                if good:
                    towers[i] = g
            todo = todo[~ok]
        if todo.size:  # rare: no standing extension found; start those towers again at this level
            for i in todo:
                towers[i] = standing_prefixes(rng, [level], static, resolution, max_tries)[0]
    return towers


def sample_questions(rng: np.random.Generator, n: int, spec: DataSpec, static) -> tuple[list[Geometry], np.ndarray]:
    """``n`` question towers and whether each is near-critical (before labelling and balancing)."""
    from overhang_framework.physics.towers import find_flips, last_block_interval, with_last_x

    sizes = rng.integers(spec.min_blocks, spec.max_blocks + 1, size=n)
    prefixes = standing_prefixes(rng, sizes - 1, static, spec.resolution)
    towers = [place(*t) for t in _grow(rng, prefixes, spec.resolution)]
    critical = np.zeros(n, dtype=bool)
    chosen = np.flatnonzero(rng.random(n) < spec.near_critical)
    if chosen.size:
        flips = find_flips([towers[i] for i in chosen], lambda gs: static.stable_batch(gs), tolerance=0.002)
        offsets = rng.uniform(-spec.window, spec.window, size=chosen.size)
        for i, flip, off in zip(chosen, flips, offsets):
            if flip is None:
                continue
            lo, hi = last_block_interval(towers[i])
            towers[i] = with_last_x(towers[i], float(np.clip(flip + off, lo, hi)))
            critical[i] = True
    return towers, critical


def balance(rng: np.random.Generator, stable: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Sorted indices keeping, within each group, equally many stable and unstable items."""
    keep = []
    for g in np.unique(groups):
        rows = np.flatnonzero(groups == g)
        pos, neg = rows[stable[rows]], rows[~stable[rows]]
        k = min(len(pos), len(neg))
        keep.extend(rng.choice(pos, k, replace=False))
        keep.extend(rng.choice(neg, k, replace=False))
    return np.sort(np.asarray(keep, dtype=int))


# --------------------------------------------------------------------------------------------------
# Shards


def to_arrays(geometries: Sequence[Geometry]) -> dict:
    """Geometries as padded arrays: ``widths``, ``xs``, ``layers`` ``(n, 8)`` and ``n_blocks``."""
    n = len(geometries)
    widths = np.zeros((n, MAX_BLOCKS_STORED), dtype=np.float32)
    xs = np.zeros((n, MAX_BLOCKS_STORED), dtype=np.float64)
    layers = np.zeros((n, MAX_BLOCKS_STORED), dtype=np.int8)
    counts = np.zeros(n, dtype=np.int8)
    for i, g in enumerate(geometries):
        arr = g.as_array()
        k = len(arr)
        widths[i, :k], xs[i, :k], layers[i, :k], counts[i] = arr[:, 0], arr[:, 1], arr[:, 2], k
    return {"widths": widths, "xs": xs, "layers": layers, "n_blocks": counts}


def from_arrays(data: dict, rows: Optional[Iterable[int]] = None) -> list[Geometry]:
    """The geometries of :func:`to_arrays` arrays (all rows, or ``rows``)."""
    rows = range(len(data["n_blocks"])) if rows is None else rows
    out = []
    for i in rows:
        k = int(data["n_blocks"][i])
        out.append(Geometry(tuple(Block(float(np.round(data["widths"][i, j], 6)), float(data["xs"][i, j]),
                                        int(data["layers"][i, j])) for j in range(k))))
    return out


def _margin_job(args) -> np.ndarray:
    from overhang_framework.physics.static_backend import StaticBackend

    data, margins = args
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    geometries = from_arrays(data)
    out = np.zeros((len(geometries), len(margins)), dtype=bool)
    for j, m in enumerate(margins):
        out[:, j] = np.asarray(StaticBackend(margin=float(m)).stable_batch(geometries), dtype=bool)
    return out


def margin_verdicts(data: dict, margins: Sequence[float], workers: int = 1) -> np.ndarray:
    """``(n, len(margins))``: the static model's verdict on every question of ``data`` with every contact
    shrunk by each margin (metres; a negative margin widens them), on ``workers`` processes.

    Stable under margin m means the loads pass at least m inside every edge that holds them, so the
    verdicts over a range of margins say how far a tower is from tipping, on either side.
    """
    n = len(data["n_blocks"])
    keys = ("widths", "xs", "layers", "n_blocks")
    parts = [{k: data[k][rows] for k in keys} for rows in np.array_split(np.arange(n), max(1, workers))]
    if workers > 1 and n > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(workers) as pool:
            results = pool.map(_margin_job, [(part, list(margins)) for part in parts])
    else:
        results = [_margin_job((part, list(margins))) for part in parts]
    return np.concatenate(results)


def shard_seed(seed: int, index: int) -> np.random.SeedSequence:
    return np.random.SeedSequence([int(seed), int(index)])


def make_reference(spec: DataSpec):
    """The labelling physics of ``spec`` (no cache: every question is a new tower)."""
    from overhang_framework.physics.factory import make_backend

    params = dict(spec.physics_params)
    return make_backend(spec.physics, **params)


def generate_shard(spec: DataSpec, index: int) -> dict:
    """Shard ``index`` of ``spec``: balanced, labelled questions as arrays, with their settings in ``meta``."""
    from overhang_framework.physics.static_backend import StaticBackend

    rng = np.random.default_rng(shard_seed(spec.seed, index))
    static = StaticBackend()
    reference = make_reference(spec)
    # Balancing keeps about 2 * min(p, 1 - p) of each kind; draw enough to fill the shard.
    want = int(np.ceil(spec.shard_size * 1.8))
    towers, critical = sample_questions(rng, want, spec, static)
    stable = np.asarray(reference.stable_batch(towers), dtype=bool)
    keep = balance(rng, stable, critical.astype(int))
    # Keep the shard balanced when trimming to shard_size: equal numbers of each verdict per kind.
    if len(keep) > spec.shard_size:
        kept = []
        for kind in (False, True):
            rows = keep[critical[keep] == kind]
            share = int(round(spec.shard_size * len(rows) / len(keep))) // 2
            for verdict in (True, False):
                r = rows[stable[rows] == verdict]
                kept.extend(r[:share])
        keep = np.sort(np.asarray(kept, dtype=int))
    data = to_arrays([towers[i] for i in keep])
    data["stable"] = stable[keep]
    data["near_critical"] = critical[keep]
    data["meta"] = json.dumps({**spec.settings(), "index": index})
    return data


def shard_path(directory: Path, index: int) -> Path:
    return Path(directory) / f"shard-{index:05d}.npz"


def write_shard(directory: Path, index: int, data: dict) -> Path:
    path = shard_path(directory, index)
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **data)
    return path


def read_shard(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as f:
        data = {k: f[k] for k in f.files}
    data["meta"] = json.loads(str(data["meta"]))
    return data


def _job(args):
    spec, index, directory = args
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    data = generate_shard(spec, index)
    write_shard(directory, index, data)
    return index, len(data["stable"])


def generate(spec: DataSpec, directory: Path | str, workers: int = 1, progress: bool = True) -> dict:
    """Write the shards of ``spec`` into ``directory`` (skipping those already there) and return the manifest.

    ``workers > 1`` generates shards on a process pool. Raises ``ValueError``
    when ``directory`` holds a set made with other settings.
    """
    from overhang_framework.progress import progress_bar

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    manifest_path = directory / "manifest.json"
    settings = spec.settings()
    if manifest_path.exists():
        old = json.loads(manifest_path.read_text())
        if old.get("settings") != settings:
            raise ValueError(f"{directory} holds a data set made with other settings; "
                             f"use another directory or remove it (theirs: {old.get('settings')})")
    todo = []
    for i in range(spec.shards):
        path = shard_path(directory, i)
        if path.exists():
            try:
                meta = read_shard(path)["meta"]
                if meta.get("index") == i and {k: v for k, v in meta.items() if k != "index"} == settings:
                    continue
            except Exception:
                pass
        todo.append(i)
    atomic_write_json(manifest_path, {"settings": settings, "shards": spec.shards, "complete": False})
    bar = progress_bar(total=spec.shards, initial=spec.shards - len(todo), desc="shards", unit="shard",
               disable=not progress)
    jobs = [(spec, i, directory) for i in todo]
    if workers > 1 and len(jobs) > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(workers) as pool:
            for _ in pool.imap_unordered(_job, jobs):
                bar.update(1)
    else:
        for job in jobs:
            _job(job)
            bar.update(1)
    bar.close()
    summary = summarize(load(directory))
    manifest = {"settings": settings, "shards": spec.shards, "complete": True, **summary}
    atomic_write_json(manifest_path, manifest)
    return manifest


def load(directory: Path | str, shards: Optional[Sequence[int]] = None) -> dict:
    """The shards of a data set directory concatenated (all ``shard-*.npz``, or ``shards``)."""
    directory = Path(directory)
    paths = sorted(directory.glob("shard-*.npz")) if shards is None else [shard_path(directory, i) for i in shards]
    if not paths:
        raise FileNotFoundError(f"no data set shards (shard-*.npz) in {directory}")
    parts = [read_shard(p) for p in paths]
    data = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k != "meta"}
    data["meta"] = [p["meta"] for p in parts]
    return data


def summarize(data: dict) -> dict:
    """Counts of a loaded data set: size, stable share, near-critical share, questions per block count."""
    stable, critical, counts = data["stable"], data["near_critical"], data["n_blocks"]
    return {
        "n": int(len(stable)),
        "stable_fraction": float(stable.mean()) if len(stable) else float("nan"),
        "near_critical": int(critical.sum()),
        "by_blocks": {int(k): int((counts == k).sum()) for k in np.unique(counts)},
    }
