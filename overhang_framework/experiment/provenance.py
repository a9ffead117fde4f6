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
        "durations": dict(settings.durations),
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
        elif a != b:
            out.append(f"{name}: {_short(a)} -> {_short(b)}")
    return out


def _short(value: Any) -> str:
    text = value if isinstance(value, str) else json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."
