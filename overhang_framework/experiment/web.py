"""The experiment's front end (``web/`` at the repository root): where its build is, and building it.

``web/`` is an npm workspace: the jsPsych task plugin and the experiment page.
``npm ci && npm run build`` there writes ``web/dist/``, which the server
serves at ``/``. The build is not kept in the repository; :func:`ensure_built`
makes it when it is missing.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Optional

from overhang_framework.errors import ConfigError
from overhang_framework.experiment.settings import REPO_WEB


def dist_dir(web_dir: Optional[Path] = None) -> Path:
    return Path(web_dir) if web_dir is not None else REPO_WEB / "dist"


def _sources_changed(dist: Path) -> bool:
    """Whether a source of the front end in ``web/`` is newer than the build in ``dist``."""
    built = (dist / "index.html").stat().st_mtime
    for path in REPO_WEB.rglob("*"):
        if "node_modules" in path.parts or dist in path.parents or not path.is_file():
            continue
        if path.stat().st_mtime > built:
            return True
    return False


def ensure_built(web_dir: Optional[Path] = None, force: bool = False) -> Path:
    """The front end's build directory; built from ``web/`` first when it has no ``index.html``, when a source
    in ``web/`` is newer than the build, or with ``force``."""
    dist = dist_dir(web_dir)
    if (dist / "index.html").exists() and not force and (web_dir is not None or not _sources_changed(dist)):
        return dist
    if web_dir is not None:
        raise ConfigError(f"web_dir {dist} has no index.html; build the front end there or leave web_dir null")
    if not (REPO_WEB / "package.json").exists():
        raise ConfigError(f"the front end's sources are not at {REPO_WEB}; run from a clone of the repository or "
                          "set web_dir to a built front end")
    unwritable = [p for p in (REPO_WEB, REPO_WEB / "node_modules", dist) if p.exists() and not os.access(p, os.W_OK)]
    if unwritable:
        why = "has no build" if not (dist / "index.html").exists() else "is older than its sources"
        raise ConfigError(f"the front end {why}, and this user cannot write {unwritable[0]} to build it: run "
                          "python -m overhang_framework.experiment build as the checkout's owner first (or set web_dir "
                          "to a built front end)")
    npm = shutil.which("npm")
    if npm is None:
        raise ConfigError("npm is not installed; the front end needs Node.js 18 or later with npm "
                          "(Debian: apt-get install nodejs npm)")
    for args in ([npm, "ci", "--no-audit", "--no-fund"], [npm, "run", "build"]):
        print(f"building the front end: {' '.join(args[1:])} (in {REPO_WEB})", file=sys.stderr)
        done = subprocess.run(args, cwd=REPO_WEB, stdout=sys.stderr)
        if done.returncode != 0:
            raise ConfigError(f"'npm {' '.join(args[1:])}' in {REPO_WEB} failed with exit code {done.returncode}")
    return dist
