"""What a study's records come from: the settings that decide what participants see and how they are scored,
their hashes, and the differences between two sets of them.

The study's settings are recorded in its database when its server first starts (``study`` in
:mod:`~overhang_framework.experiment.store`). Every placement carries the framework's version and commit
and the hashes of the settings and of the task set it was made under; a server restarted on the study
with other such settings is refused unless ``allow_settings_change=true``, and then the change is
recorded. Where the server listens, its processes, the database and the admin token are not among them:
they change nothing a participant sees; nor do the world's cache and worker processes.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any, Mapping

from overhang_framework.experiment.settings import Settings


def digest(value: Any) -> str:
    """The SHA-256 of ``value`` as canonical JSON (sorted keys, no spaces), in hex."""
    return hashlib.sha256(json.dumps(value, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def task_set(settings: Settings) -> list:
    """The main tasks, ``[id, [widths...]]`` each, in the order the settings give them."""
    return [[t.id, list(t.sequence)] for t in settings.tasks]


#: Keys of the world's config that change how fast its verdicts come, not what they are.
WORLD_SPEED_KEYS = ("cache", "verdict_file", "workers")


def study_settings(settings: Settings) -> dict:
    """The settings that change what participants see or how they are scored (plain JSON data)."""
    return {
        "world": {k: v for k, v in settings.world.items() if k not in WORLD_SPEED_KEYS},
        "tasks": task_set(settings),
        "practice": [{"id": p.task.id, "sequence": list(p.task.sequence), "pass_reward": p.pass_reward,
                      "shown_reward": p.shown_reward, "tolerance": p.tolerance} for p in settings.practice],
        "practice_threshold": settings.practice_threshold,
        "practice_max_attempts": settings.practice_max_attempts,
        "conditions": list(settings.conditions),
        "time_limit": settings.time_limit,
        **({"time_limits": dict(settings.time_limits)} if settings.time_limits else {}),
        "time_grace": settings.time_grace,
        "bonus_per_unit": settings.bonus_per_unit,
        "currency": settings.currency,
        "mouse_hz": settings.mouse_hz,
        "animation_fps": settings.animation_fps,
        "seed": settings.seed,
        "completion_url": settings.completion_url,
        "screen_out_url": settings.screen_out_url,
        "decline_url": settings.decline_url,
        "consent_version": settings.consent_version,
        "source": settings.source,
    }


def hashes(settings: Settings) -> dict:
    """``settings_hash`` (of :func:`study_settings`, the task set included) and ``tasks_hash``."""
    return {"settings_hash": digest(study_settings(settings)), "tasks_hash": digest(task_set(settings))}


def differences(old: Mapping, new: Mapping, prefix: str = "") -> list[str]:
    """What changed from ``old`` to ``new``, one ``key: old -> new`` per changed leaf (dotted keys)."""
    out = []
    for key in sorted(set(old) | set(new)):
        name = f"{prefix}{key}"
        a, b = old.get(key, "(none)"), new.get(key, "(none)")
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            out.extend(differences(a, b, f"{name}."))
        elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b) and a != b \
                and all(isinstance(v, (Mapping, list)) for v in (*a, *b)):  # a list of records: item by item
            for i, (x, y) in enumerate(zip(a, b)):  # a list's changed items, each by its id where both share it
                if x == y:
                    continue
                item = _item_id(x, y, i)
                if isinstance(x, Mapping) and isinstance(y, Mapping):
                    out.extend(differences(x, y, f"{name}[{item}]."))
                else:
                    out.append(f"{name}[{item}]: {' -> '.join(_shown(x, y))}")
        elif a != b:
            out.append(f"{name}: {' -> '.join(_shown(a, b))}")
    return out


def _item_id(x: Any, y: Any, index: int) -> Any:
    """What names a changed list item: the ``id`` (a mapping's) or first string (a list's) both sides share, else
    its index."""
    if isinstance(x, Mapping) and isinstance(y, Mapping) and x.get("id") is not None and x.get("id") == y.get("id"):
        return x["id"]
    if isinstance(x, list) and isinstance(y, list) and x and y and isinstance(x[0], str) and x[0] == y[0]:
        return x[0]
    return index


#: Characters of a changed value shown on each side of ``->``.
SHOWN = 60


def _shown(a: Any, b: Any) -> tuple[str, str]:
    """``a`` and ``b`` as text, each cut to about :data:`SHOWN` characters around where they first differ, so that
    two long values (a task list, say) show their difference, not the start they share."""
    ta, tb = (v if isinstance(v, str) else json.dumps(v) for v in (a, b))
    if len(ta) <= SHOWN and len(tb) <= SHOWN:
        return ta, tb
    same = 0
    while same < min(len(ta), len(tb)) and ta[same] == tb[same]:
        same += 1
    start = max(0, same - 20)

    def cut(text: str) -> str:
        part = text[start:start + SHOWN - 6]
        return ("..." if start else "") + part + ("..." if start + len(part) < len(text) else "")

    return cut(ta), cut(tb)
