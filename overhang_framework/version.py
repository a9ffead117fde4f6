"""The framework's version and, when it runs from a git checkout, its commit: what records and results cite."""

from __future__ import annotations

import subprocess
from functools import lru_cache
from pathlib import Path

import overhang_framework

PACKAGE_DIR = Path(overhang_framework.__file__).resolve().parent


def _git(*args: str, cwd: Path = PACKAGE_DIR) -> subprocess.CompletedProcess:
    # safe.directory: a service user reads a checkout another user owns (git otherwise refuses it as of
    # "dubious ownership"); no optional locks: reading never writes the index, which that user cannot
    return subprocess.run(["git", "-c", "safe.directory=*", "--no-optional-locks", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=10)


def commit_of(directory: Path) -> str:
    """The git commit of the checkout that holds the package directory ``directory``, with ``-dirty`` when the
    package's files differ from it; '' when it is not in a checkout (or git is missing). Whoever owns the
    checkout, any user who can read it gets the same answer."""
    try:
        tracked = _git("ls-files", "--error-unmatch", "__init__.py", cwd=directory)
        if tracked.returncode != 0:
            return ""
        head = _git("rev-parse", "HEAD", cwd=directory)
        if head.returncode != 0:
            return ""
        changed = _git("status", "--porcelain", "--untracked-files=no", "--", ".", cwd=directory)
    except (OSError, subprocess.TimeoutExpired):
        return ""
    return head.stdout.strip() + ("-dirty" if changed.stdout.strip() else "")


@lru_cache(maxsize=1)
def commit() -> str:
    """The git commit of the checkout the framework runs from, with ``-dirty`` when its files differ from
    that commit; '' when it does not run from a checkout (an installed copy, or a checkout's ignored
    directory such as a virtual environment inside it)."""
    return commit_of(PACKAGE_DIR)


def version() -> str:
    """The framework's version number."""
    return overhang_framework.__version__


def versions() -> dict:
    """``{"framework_version": ..., "commit": ...}`` (commit null outside a checkout)."""
    return {"framework_version": version(), "commit": commit() or None}
