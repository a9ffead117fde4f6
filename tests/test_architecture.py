"""The layers of docs/architecture.md, as import-linter's contracts in pyproject.toml state them: kept by the code,
broken by an import that runs upward, and naming every module (a module in no layer would be checked by none)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

grimp = pytest.importorskip("grimp")
pytest.importorskip("importlinter")

ROOT = Path(__file__).resolve().parents[1]
LINT = str(Path(sys.executable).with_name("lint-imports"))
#: Packages whose modules are placed in different layers one by one; their ``__init__`` is in none.
SPLIT = {"overhang_framework", "overhang_framework.cnn", "overhang_framework.envs"}


def contracts() -> list[dict]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]


def layers() -> list[list[str]]:
    found = next(c for c in contracts() if c["type"] == "layers")
    return [[m.strip() for m in line.replace("|", ":").split(":")] for line in found["layers"]]


def lint(cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([LINT, "--no-cache"], cwd=cwd, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "NO_COLOR": "1", "COLUMNS": "200", **(env or {})})


def test_the_contracts_are_kept_and_none_ignores_an_import():
    assert all("ignore_imports" not in c for c in contracts())
    proc = lint(ROOT)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert f"Contracts: {len(contracts())} kept, 0 broken." in proc.stdout


def test_every_module_is_in_exactly_one_layer():
    graph = grimp.build_graph("overhang_framework", "overhang_builtins", cache_dir=None)
    named = [m for line in layers() for m in line]
    assert len(named) == len(set(named)), "a module is named in two layers"
    def homes(module: str) -> list[str]:
        return [n for n in named if module == n or module.startswith(n + ".")]
    placed = {m: homes(m) for m in graph.modules if m not in SPLIT}
    assert not [m for m, h in placed.items() if not h], "modules in no layer (add each to its line in pyproject.toml)"
    assert not [m for m, h in placed.items() if len(h) > 1]


def test_an_import_that_runs_upward_breaks_the_layers(tmp_path):
    """A copy of the code in which a foundation (geometry) reaches up to a command (the study), inside a function as
    a dodge would: lint-imports fails and names the import."""
    for package in ("overhang_framework", "plugins/overhang_builtins"):
        shutil.copytree(ROOT / package, tmp_path / Path(package).name,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pt", "*.onnx", "*.zip", "data", "checkpoints"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    geometry = tmp_path / "overhang_framework" / "geometry.py"
    geometry.write_text(geometry.read_text() + "\n\ndef _study():\n    from overhang_framework import study\n\n"
                        "    return study\n")
    proc = lint(tmp_path, {"PYTHONPATH": str(tmp_path)})
    assert proc.returncode != 0
    said = " ".join(proc.stdout.split())
    assert re.search(r"Layers: .*? BROKEN", said)
    assert "overhang_framework.geometry is not allowed to import overhang_framework.study" in said
    assert "overhang_framework.geometry -> overhang_framework.study" in said
