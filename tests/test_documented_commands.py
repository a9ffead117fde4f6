"""Every command README.md and docs/ name (``python -m overhang_framework...``) answers ``--help``: exit status 0, a
usage or a description that names the command, no traceback. A command that moved keeps its name."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

from commands import run_each

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def documented() -> list[str]:
    """The modules the docs run with ``python -m``, placeholders (``overhang_framework.X``) left out."""
    named = {m.rstrip(".") for f in DOCS for m in re.findall(r"python -m (overhang_framework[\w.]*)", f.read_text())}
    return sorted(m for m in named if not m.endswith(".X") and not m.endswith(".Y"))


def test_the_docs_name_only_commands_that_exist():
    names = documented()
    assert len(names) > 40 and {"overhang_framework", "overhang_framework.study", "overhang_framework.graded",
                                "overhang_framework.participants", "overhang_framework.fit"} <= set(names)
    missing = [m for m in names if importlib.util.find_spec(m) is None]
    assert not missing, f"the docs run modules that do not exist: {missing}"


def test_every_documented_command_answers_help():
    names = documented()
    procs = run_each([[sys.executable, "-m", m, "--help"] for m in names], timeout=300)
    failed = {m: (p.returncode, p.stderr[-500:]) for m, p in zip(names, procs)
              if p.returncode != 0 or "Traceback" in p.stderr or not p.stdout.strip()}
    assert not failed, failed
    for module, proc in zip(names, procs):
        text = proc.stdout
        if text.startswith("usage:"):
            assert text.split()[:4] == ["usage:", "python", "-m", module], (module, text[:200])
        else:  # a description (the module's first lines), or Hydra's help of the app
            short = module.rsplit(".", 1)[-1]
            assert short in text or "overhang-framework" in text, (module, text[:300])


def test_the_pilot_commands_of_the_docs_give_the_options_the_pilot_requires():
    """Each ``experiment pilot`` the docs show parses as the pilot's command line (``--out`` is required)."""
    import shlex

    from overhang_framework.experiment.pilot import parser

    for doc in (ROOT / "docs" / "people.md", ROOT / "docs" / "experiment.md"):
        text = doc.read_text().replace("\\\n", " ")
        for line in re.findall(r"^python -m overhang_framework\.experiment pilot (.*)$", text, flags=re.M):
            words = shlex.split(line.split("#")[0])
            args = parser().parse_args(words)
            assert args.out, (doc.name, line)
