"""The figures in README.md and docs/ are registered with the commands that make them, and checked."""

import json
import sys
import textwrap
from pathlib import Path

import pytest

from overhang_framework.report import docfigures

ROOT = Path(__file__).resolve().parents[1]


def test_every_registered_figure_and_its_command_are_in_their_file():
    entries = docfigures.load_registry(ROOT / "docs" / "checks")
    assert entries and all(e.figures for e in entries)
    assert docfigures.check_texts(entries, ROOT) == []


def _registry(tmp_path, doc: str, figures: str, output: str = "stdout") -> Path:
    (tmp_path / "docs" / "checks").mkdir(parents=True)
    (tmp_path / "DOC.md").write_text(doc)
    command = "python -c \"import json; print('noise'); print(json.dumps({'x': 2.0, 'wall': 10, 'n': 1234}))\""
    (tmp_path / "docs" / "checks" / "doc.yaml").write_text(textwrap.dedent(f"""\
        - name: fake
          command: {json.dumps(command)}
          output: {output}
          minutes: 0.1
          figures:
        """) + textwrap.indent(textwrap.dedent(figures), "    "))
    return tmp_path / "docs" / "checks"


def test_a_figure_that_no_longer_matches_its_command_is_reported_stale(tmp_path, capsys):
    doc = ("Run python -c \"import json; print('noise'); print(json.dumps({'x': 2.0, 'wall': 10, 'n': 1234}))\": "
           "x is 1.000 over 1,234 towers, in about 12 s, and y is 2.0.")
    registry = _registry(tmp_path, doc, """\
        - file: DOC.md
          text: x is 1.000 over 1,234 towers
          template: "x is {x:.3f} over {n:,} towers"
        - file: DOC.md
          text: in about 12 s
          template: "in about {wall} s"
          tolerance: 0.5
        - file: DOC.md
          text: y is 2.0
          template: "y is {x:.1f}"
        """)
    assert docfigures.main(["--registry", str(registry)]) == 0
    assert docfigures.main(["--registry", str(registry), "--run"]) == 1
    out = capsys.readouterr().out
    assert "STALE DOC.md: says 'x is 1.000 over 1,234 towers'; the command makes 'x is 2.000 over 1,234 towers'" in out
    assert "ok    DOC.md: says 'in about 12 s'; the command makes 'in about 10 s' (within 50%)" in out
    assert "ok    DOC.md: says 'y is 2.0'" in out
    assert "2 figures agree, 1 stale, 0 could not be made, over 1 commands" in out


def test_a_timing_outside_its_tolerance_and_a_missing_text_are_reported(tmp_path, capsys):
    doc = "Run python -c \"import json; print('noise'); print(json.dumps({'x': 2.0, 'wall': 10, 'n': 1234}))\": 40 s."
    registry = _registry(tmp_path, doc, """\
        - file: DOC.md
          text: 40 s
          template: "{wall} s"
          tolerance: 0.5
        - file: DOC.md
          text: 99 towers
          template: "{n} towers"
        """)
    assert docfigures.main(["--registry", str(registry)]) == 1
    out = capsys.readouterr().out
    assert "missing: fake: DOC.md does not say '99 towers'" in out
    docfigures.main(["--registry", str(registry), "--run"])
    assert "STALE DOC.md: says '40 s'; the command makes '10 s' (40 is more than 50% from 10)" in capsys.readouterr().out


@pytest.mark.parametrize("text, error", [
    ("- name: a\n  command: x\n  output: stdout\n  minutes: 1\n  figures: []\n", "entry 'a': has no figures"),
    ("- name: a\n  command: x\n  output: csv\n  minutes: 1\n  figures: []\n",
     "entry 'a': output must be one of metrics.json, stdout or file:NAME, got 'csv'"),
    ("- name: a\n  command: x\n  output: file:r.json\n  minutes: 1\n  figures: []\n",
     "entry 'a': output file:r.json needs a 'run' command that writes into {out}"),
    ("- name: a\n  commnd: x\n", "entry 1: unknown keys commnd; allowed: command, figures, minutes, name, output, run"),
    ("name: a\n", "must be a list of entries, got dict"),
    ("- name: a\n  command: x\n  output: stdout\n  minutes: soon\n", "entry 'a': 'minutes' must be a int or float"),
    (": [\n", "not YAML"),
])
def test_a_malformed_registry_is_one_line_naming_the_file_and_the_fault(tmp_path, capsys, text, error):
    (tmp_path / "bad.yaml").write_text(text)
    assert docfigures.main(["--registry", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {tmp_path / 'bad.yaml'}") and error in err and err.count("\n") == 1


def test_unknown_entries_are_named_with_the_known_ones(capsys):
    assert docfigures.main(["--registry", str(ROOT / "docs" / "checks"), "--only", "main-jb"]) == 2
    assert "error: no entry named main-jb; entries: " in capsys.readouterr().err


def test_a_json_file_the_command_writes_is_read(tmp_path, capsys):
    registry = tmp_path / "docs" / "checks"
    registry.mkdir(parents=True)
    (tmp_path / "DOC.md").write_text("`python -m mytool --out DIR` found 7 towers.")
    run = "python -c \"import json, sys; open(sys.argv[1], 'w').write(json.dumps({'n': 7}))\" {out}/r.json"
    (registry / "doc.yaml").write_text(
        "- name: f\n  command: python -m mytool --out DIR\n  output: file:r.json\n  minutes: 0.1\n"
        f"  run: {json.dumps(run)}\n"
        "  figures:\n    - file: DOC.md\n      text: found 7 towers\n      template: 'found {n} towers'\n")
    assert docfigures.main(["--registry", str(registry), "--run"]) == 0
    assert "ok    DOC.md: says 'found 7 towers'" in capsys.readouterr().out


def test_the_command_runs_with_this_interpreter_and_its_own_run_directory(tmp_path):
    entry = docfigures.Entry("e", "python -m overhang_framework tasks=example", "metrics.json", 1,
                             [docfigures.Figure("README.md", "t", "t")])
    assert entry.argv(tmp_path) == [sys.executable, "-m", "overhang_framework", "tasks=example",
                                    f"hydra.run.dir={tmp_path}"]


@pytest.mark.slow
def test_the_quick_figures_of_the_docs_match_what_their_commands_print_now():
    """Reruns every registered command of at most 2 minutes; a stale figure fails with its text."""
    assert docfigures.main(["--registry", str(ROOT / "docs" / "checks"), "--run", "--minutes", "2"]) == 0
