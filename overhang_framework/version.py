"""The framework's version and, when it runs from a git checkout, its commit: what records and results cite."""

from __future__ import annotations

import os
import subprocess
from functools import lru_cache
from pathlib import Path
from typing import Optional

#: The release (pyproject.toml's ``version``).
__version__ = "0.1.0"
PACKAGE_DIR = Path(__file__).resolve().parent


def _checkout_top(directory: Path) -> Optional[Path]:
    """The top of the git checkout that holds ``directory`` (where ``.git`` is), or None."""
    here = Path(directory).resolve()
    return next((d for d in (here, *here.parents) if (d / ".git").exists()), None)


def _git(*args: str, cwd: Path = PACKAGE_DIR) -> subprocess.CompletedProcess:
    """git in ``cwd``, reading only: no optional locks (the index is not written, which a service user cannot),
    no fsmonitor hook. A checkout root owns is trusted by any reader (the deployment's case: the service's
    user reads the code root installed), though git refuses a checkout of another owner ("dubious
    ownership"); one of another unprivileged user is not (its configuration could run code as the reader)."""
    words = ["git", "-c", "core.fsmonitor=false", "--no-optional-locks"]
    top = _checkout_top(cwd)
    if top is not None:
        try:
            owner = (top / ".git").stat().st_uid
        except OSError:
            owner = None
        if owner == 0 and os.geteuid() != 0:
            words[1:1] = ["-c", f"safe.directory={top}"]
    return subprocess.run([*words, *args], cwd=cwd, capture_output=True, text=True, timeout=10)


def commit_of(directory: Path) -> str:
    """The git commit of the checkout that holds the package directory ``directory``, with ``-dirty`` when the
    package's files differ from it; '' when it is not in a checkout, git is missing, or the checkout belongs to
    another unprivileged user (:func:`_git`)."""
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
    return __version__


def versions() -> dict:
    """``{"framework_version": ..., "commit": ...}`` (commit null outside a checkout)."""
    return {"framework_version": version(), "commit": commit() or None}
