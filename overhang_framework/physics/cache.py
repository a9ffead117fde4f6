"""A cache of stability verdicts.

Verdicts are keyed by the backend's name and parameters, the geometry's
canonical order-independent key (:attr:`Geometry.key`), and the gravity vector
and per-block friction when given (friction is reordered with the blocks, so a
permuted geometry with its permuted friction hits the same entry). The
backends decide a tower alike whatever the order of its blocks (the reference
simulates them in canonical order), so an entry does not depend on which
order asked first. One :class:`VerdictCache` can be shared by several
:class:`CachedBackend` wrappers so that everything asking within a run shares
its verdicts.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Hashable, Optional, Sequence

import numpy as np

from overhang_framework.geometry import KEY_DECIMALS, Geometry, canonical_key

FILE_FORMAT = "canonical-order"
"""Part of every key in a verdict file: the reference simulates each tower with its blocks in canonical
order, so its verdict does not depend on the order asked; files whose verdicts came from runs in the
order the blocks were listed have other keys and are not read."""


def verdict_key(geometry: Geometry, gravity=None, friction=None, context: Hashable = None) -> tuple:
    """The cache key of one check; ``context`` identifies the backend and its parameters.

    The geometry part is :func:`~overhang_framework.geometry.canonical_key`;
    with ``friction``, each block's friction travels with its block through the
    sort, so a permuted geometry with its friction permuted alike has the same key.
    """
    if friction is None:
        body = canonical_key(geometry.blocks)
    else:
        body = tuple(sorted((canonical_key((b,))[0], _rounded(f)) for b, f in zip(geometry.blocks, friction, strict=True)))
    grav = None if gravity is None else tuple(_rounded(v) for v in gravity)
    return (context, body, grav, friction is not None)


def _rounded(value) -> float:
    """``value`` rounded as :func:`canonical_key` rounds coordinates (``-0.0`` made ``0.0``)."""
    return round(float(value), KEY_DECIMALS) + 0.0


class VerdictCache:
    """Verdicts by key, least recently used evicted beyond ``maxsize`` (``None``: unbounded)."""

    def __init__(self, maxsize: Optional[int] = 1_000_000):
        self.maxsize = maxsize
        self._data: OrderedDict = OrderedDict()
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        return len(self._data)

    def get(self, key) -> Optional[bool]:
        """The stored verdict (counted as a hit) or ``None`` (counted as a miss)."""
        value = self._data.get(key)
        if value is None:
            self.misses += 1
            return None
        self.hits += 1
        self._data.move_to_end(key)
        return value

    def peek(self, key) -> Optional[bool]:
        """The stored verdict or ``None``, without counting a hit or a miss."""
        return self._data.get(key)

    def put(self, key, verdict: bool) -> None:
        self._data[key] = bool(verdict)
        self._data.move_to_end(key)
        if self.maxsize is not None and len(self._data) > self.maxsize:
            self._data.popitem(last=False)

    @property
    def hit_rate(self) -> float:
        asked = self.hits + self.misses
        return self.hits / asked if asked else 0.0

    def stats(self) -> dict:
        return {"hits": self.hits, "misses": self.misses, "size": len(self), "hit_rate": self.hit_rate}

    def clear(self) -> None:
        self._data.clear()
        self.hits = self.misses = 0


def backend_context(backend) -> Hashable:
    """What identifies a backend's verdicts: its name, parameters and early-stop override if any."""
    return (getattr(backend, "name", type(backend).__name__), repr(getattr(backend, "params", None)),
            getattr(backend, "early_stop", None))


class CachedBackend:
    """A :class:`~overhang_framework.physics.PhysicsBackend` answering from ``cache`` before asking ``backend``.

    Misses of a batch are sent to ``backend.stable_batch`` together, each
    distinct key once.
    """

    def __init__(self, backend, cache: Optional[VerdictCache] = None):
        self.backend = backend
        self.cache = cache if cache is not None else VerdictCache()
        self.name = backend.name
        self._context = backend_context(backend)

    @property
    def params(self):
        return getattr(self.backend, "params", None)

    def stable(self, geometry: Geometry, gravity=None, friction=None) -> bool:
        key = verdict_key(geometry, gravity, friction, self._context)
        verdict = self.cache.get(key)
        if verdict is None:
            verdict = bool(self.backend.stable(geometry, gravity, friction))
            self.cache.put(key, verdict)
        return verdict

    def stable_batch(self, geometries: Sequence[Geometry], gravity=None, friction=None) -> np.ndarray:
        geometries = list(geometries)
        out = np.zeros(len(geometries), dtype=bool)
        todo: dict = {}
        for i, g in enumerate(geometries):
            key = verdict_key(g, None if gravity is None else gravity[i],
                              None if friction is None else friction[i], self._context)
            verdict = self.cache.get(key)
            if verdict is None:
                todo.setdefault(key, []).append(i)
            else:
                out[i] = verdict
        if todo:
            first = [idx[0] for idx in todo.values()]
            verdicts = self.backend.stable_batch(
                [geometries[i] for i in first],
                None if gravity is None else np.asarray(gravity, dtype=float)[first],
                None if friction is None else [friction[i] for i in first],
            )
            for (key, idx), v in zip(todo.items(), verdicts):
                self.cache.put(key, bool(v))
                out[idx] = bool(v)
        return out

    def stats(self) -> dict:
        """The cache's counters, and the wrapped backend's own under ``backend`` when it keeps any."""
        inner = getattr(self.backend, "stats", None)
        return {**self.cache.stats(), "backend": inner()} if inner else self.cache.stats()

    def close(self) -> None:
        """Close the wrapped backend (a process pool, say) if it can be closed."""
        close = getattr(self.backend, "close", None)
        if close is not None:
            close()


class DiskCachedBackend:
    """A backend whose verdicts are also kept in an SQLite file, for every later run and process to reuse.

    Verdicts are keyed like :class:`CachedBackend`'s (the backend's name and parameters, the canonical
    geometry, gravity and friction, with :data:`FILE_FORMAT`), so a file serves any run with the same
    physics and never answers for other parameters. Each batch is looked up in one query and its misses
    written in one transaction; several processes (the jobs of a sweep) can share one file. Meant for
    verdicts that are dear (the full-window reference), not for microsecond static checks.
    """

    def __init__(self, backend, path):
        import sqlite3
        from pathlib import Path

        self.backend = backend
        self.name = getattr(backend, "name", type(backend).__name__)
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._context = backend_context(backend)
        self._db = sqlite3.connect(str(self.path), timeout=60, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("CREATE TABLE IF NOT EXISTS verdicts (key TEXT PRIMARY KEY, stable INTEGER NOT NULL)")
        self._db.commit()
        self.hits = 0
        self.misses = 0

    @property
    def params(self):
        return getattr(self.backend, "params", None)

    def _key(self, geometry, gravity, friction) -> str:
        import hashlib

        return hashlib.blake2b(repr((FILE_FORMAT, verdict_key(geometry, gravity, friction, self._context))).encode(),
                               digest_size=16).hexdigest()

    def stable(self, geometry: Geometry, gravity=None, friction=None) -> bool:
        return bool(self.stable_batch([geometry], None if gravity is None else [gravity],
                                      None if friction is None else [friction])[0])

    def stable_batch(self, geometries: Sequence[Geometry], gravity=None, friction=None) -> np.ndarray:
        geometries = list(geometries)
        keys = [self._key(g, None if gravity is None else gravity[i], None if friction is None else friction[i])
                for i, g in enumerate(geometries)]
        known: dict = {}
        for start in range(0, len(keys), 500):
            chunk = keys[start:start + 500]
            rows = self._db.execute(f"SELECT key, stable FROM verdicts WHERE key IN ({','.join('?' * len(chunk))})",
                                    chunk).fetchall()
            known.update((k, bool(v)) for k, v in rows)
        out = np.zeros(len(geometries), dtype=bool)
        todo = [i for i, k in enumerate(keys) if k not in known]
        self.hits += len(keys) - len(todo)
        self.misses += len(todo)
        if todo:
            verdicts = self.backend.stable_batch(
                [geometries[i] for i in todo],
                None if gravity is None else np.asarray(gravity, dtype=float)[todo],
                None if friction is None else [friction[i] for i in todo])
            with self._db:
                self._db.executemany("INSERT OR REPLACE INTO verdicts VALUES (?, ?)",
                                     [(keys[i], int(bool(v))) for i, v in zip(todo, verdicts)])
            known.update((keys[i], bool(v)) for i, v in zip(todo, verdicts))
        for i, k in enumerate(keys):
            out[i] = known[k]
        return out

    def stats(self) -> dict:
        return {"disk_hits": self.hits, "disk_misses": self.misses, "file": str(self.path)}

    def close(self) -> None:
        close = getattr(self.backend, "close", None)
        if close is not None:
            close()
        self._db.close()

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_db"] = None
        return state

    def __setstate__(self, state):
        import sqlite3

        self.__dict__.update(state)
        self._db = sqlite3.connect(str(self.path), timeout=60, check_same_thread=False)
