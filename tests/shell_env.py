"""The environment of a user's shell, for tests that run the project as a user would."""

import os
import sys
from pathlib import Path


def user_env() -> dict:
    """A user's shell: no virtual environment of the test run, no test-run settings."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("PYTEST", "VIRTUAL_ENV", "PYTHON", "HYDRA", "COV_"))}
    venv_bin = str(Path(sys.prefix) / "bin")
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep) if p != venv_bin)
    return env
