"""``python -m overhang_framework.check``: towers in as JSON Lines, verdicts out, as a user types it."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TOWERS = [
    [[1.8, 0.0, 0], [1.2, 0.1, 1]],  # stands
    [[0.6, 0.0, 0], [1.8, 0.8, 1]],  # falls
    [[1.8, 0.0, 0], [1.8, 0.9, 1]],  # balanced exactly on an edge: falls in the full window
]


def check(args, stdin=None):
    return subprocess.run([sys.executable, "-m", "overhang_framework.check", *args], cwd=ROOT,
                          capture_output=True, text=True, input=stdin, timeout=300)


@pytest.mark.parametrize("overrides", [[], ["world.physics=pybullet", "world.pybullet.early_stop=false"],
                                       ["world.physics=static"]], ids=["default", "reference", "static"])
def test_round_trip_in_input_order(tmp_path, overrides):
    path = tmp_path / "towers.jsonl"
    path.write_text("".join(json.dumps({"blocks": b}) + "\n" for b in TOWERS))
    proc = check([str(path), "--quiet", *overrides])
    assert proc.returncode == 0, proc.stderr
    out = [json.loads(line) for line in proc.stdout.splitlines()]
    assert out == [{"stable": True}, {"stable": False}, {"stable": False}]


def test_standard_input_and_blank_lines():
    text = json.dumps({"blocks": TOWERS[1]}) + "\n\n" + json.dumps({"blocks": TOWERS[0]}) + "\n"
    proc = check(["-", "--quiet", "world.physics=static"], stdin=text)
    assert proc.returncode == 0, proc.stderr
    assert [json.loads(line)["stable"] for line in proc.stdout.splitlines()] == [False, True]


@pytest.mark.parametrize("line, expected", [
    ('{"blocks": [[1.8, 0.0, 0], [1.3, 0.2, 1]]}', "line 2: block 2: illegal block width 1.3"),
    ('{"blocks": [[1.8, 0.0, 0], [1.2, 0.2]]}', "line 2: block 2 must be [width, x, layer]"),
    ('{"blocks": [[1.8, 0.0, 0], [1.2, "a", 1]]}', "line 2: block 2 must hold three finite numbers"),
    ('{"blocks": [[1.2, 0.2, 1]]}', "line 2: the first block must be the ground block (layer 0)"),
    ('{"towers": []}', 'line 2: expected an object {"blocks"'),
    ('{"blocks": [[1.8, 0.0, 0]', "line 2: not JSON: the line ends at column 25 before its value does"),
    ('{"blocks": [[1.8, 0.0, 0]] x}', "line 2: not JSON (Expecting ',' delimiter at column 28)"),
])
def test_a_malformed_line_fails_with_its_file_and_number(tmp_path, line, expected):
    path = tmp_path / "towers.jsonl"
    path.write_text(json.dumps({"blocks": TOWERS[0]}) + "\n" + line + "\n")
    proc = check([str(path), "world.physics=static"])
    assert proc.returncode == 2
    err = [l for l in proc.stderr.splitlines() if l.strip()]
    assert len(err) == 1 and err[0].startswith(f"error: {path} {expected}"), err
    assert proc.stdout == ""
    cut = tmp_path / "cut.jsonl"  # the same line as the file's last, without its newline
    cut.write_text(json.dumps({"blocks": TOWERS[0]}) + "\n" + line)
    assert check([str(cut), "world.physics=static"]).stderr.startswith(f"error: {cut} {expected}")
    piped = subprocess.run([sys.executable, "-m", "overhang_framework.check", "-", "world.physics=static"],
                           input=path.read_text(), capture_output=True, text=True)
    assert piped.returncode == 2 and piped.stderr.startswith(f"error: standard input {expected}")


def test_missing_file_and_bad_override(tmp_path):
    proc = check([str(tmp_path / "nope.jsonl")])
    assert proc.returncode == 2
    assert proc.stderr == f"error: {tmp_path / 'nope.jsonl'}: cannot read it (No such file or directory)\n"
    path = tmp_path / "towers.jsonl"
    path.write_text(json.dumps({"blocks": TOWERS[0]}) + "\n")
    proc = check([str(path), "world.physics=nope"])
    assert proc.returncode == 2
    lines = [l for l in proc.stderr.splitlines() if l.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "nope" in lines[0]
