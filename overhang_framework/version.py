"""The framework's version and, when it runs from a git checkout, its commit: what records and results cite."""

from __future__ import annotations

import subprocess
from functools import lru_cache
from pathlib import Path

import overhang_framework

PACKAGE_DIR = Path(overhang_framework.__file__).resolve().parent


def _git(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=PACKAGE_DIR, capture_output=True, text=True, timeout=10)


@lru_cache(maxsize=1)
def commit() -> str:
    """The git commit of the checkout the framework runs from, with ``-dirty`` when its files differ from
    that commit; '' when it does not run from a checkout (an installed copy, or a checkout's ignored
    directory such as a virtual environment inside it)."""
    try:
        tracked = _git("ls-files", "--error-unmatch", "__init__.py")
        if tracked.returncode != 0:
            return ""
        head = _git("rev-parse", "HEAD")
        if head.returncode != 0:
            return ""
        changed = _git("status", "--porcelain", "--untracked-files=no", "--", ".")
    except (OSError, subprocess.TimeoutExpired):
        return ""
    return head.stdout.strip() + ("-dirty" if changed.stdout.strip() else "")


def version() -> str:
    """The framework's version number."""
    return overhang_framework.__version__


def versions() -> dict:
    """``{"framework_version": ..., "commit": ...}`` (commit null outside a checkout)."""
    return {"framework_version": version(), "commit": commit() or None}
