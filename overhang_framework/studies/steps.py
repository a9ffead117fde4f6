"""A study's ``steps.json``: each finished step with the digest of what it was made from, and its seconds."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Optional

from overhang_framework.results import atomic_write_json


def _digest(*paths: Path, extra: Any = None) -> str:
    h = hashlib.sha256(json.dumps(extra, sort_keys=True, default=str).encode())
    for path in paths:
        h.update(path.read_bytes())
    return h.hexdigest()


class Steps:
    """``steps.json``: each finished step with the digest of what it was made from, and its seconds."""

    def __init__(self, out: Path):
        self.path = out / "steps.json"
        self.done = json.loads(self.path.read_text()) if self.path.exists() else {}

    def current(self, name: str, digest: str) -> bool:
        return self.done.get(name, {}).get("digest") == digest

    def finish(self, name: str, digest: str, seconds: float) -> None:
        self.done[name] = {"digest": digest, "seconds": seconds}
        atomic_write_json(self.path, self.done)

    def seconds(self, name: str) -> Optional[float]:
        return self.done.get(name, {}).get("seconds")
