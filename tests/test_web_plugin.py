"""The jsPsych plugin's own tests (Jest with @jspsych/test-utils, ``web/plugin-overhang-tower/src/index.spec.js``),
run from pytest so that the project's one test command runs them too.

They need npm and the workspace's development dependencies in ``web/node_modules``. Without npm the test is
skipped, and without the dependencies it asks for ``npm ci`` in ``web/``; under CI both fail, and missing
dependencies are installed with ``npm ci`` first.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess

import pytest

from overhang_framework.experiment.settings import REPO_WEB


def _missing(what: str) -> None:
    if os.environ.get("CI"):
        pytest.fail(f"{what}; under CI the plugin's Jest tests run, never skip")
    pytest.skip(f"{what}: the plugin's Jest tests need it")


def test_plugin_jest_suite_passes():
    npm = shutil.which("npm")
    if npm is None:
        _missing("npm is missing (Debian: apt-get install nodejs npm)")
    if not (REPO_WEB / "node_modules" / "jest").is_dir() or not (REPO_WEB / "node_modules" / "@jspsych" / "test-utils").is_dir():
        if not os.environ.get("CI"):
            _missing(f"the front end's development dependencies are not installed (run 'npm ci' in {REPO_WEB})")
        installed = subprocess.run([npm, "ci", "--no-audit", "--no-fund"], cwd=REPO_WEB, capture_output=True, text=True)
        assert installed.returncode == 0, f"npm ci in {REPO_WEB} failed:\n{installed.stdout}\n{installed.stderr}"

    done = subprocess.run([npm, "test"], cwd=REPO_WEB, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "CI": "1"})
    output = f"{done.stdout}\n{done.stderr}"
    assert done.returncode == 0, f"the plugin's Jest tests failed (npm test in {REPO_WEB}):\n{output}"
    counts = re.search(r"Tests:\s+(\d+) passed, (\d+) total", output)
    assert counts, f"Jest printed no test count:\n{output}"
    passed, total = map(int, counts.groups())
    assert passed == total > 0, output
