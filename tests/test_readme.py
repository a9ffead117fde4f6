"""README.md's commands do what it says, typed where it says: in the root of a fresh clone.

The two fresh-machine commands are read from README.md itself and run in a copy
of the repository's files (what a clone holds) with a new virtual environment,
so a README edit that breaks them fails here. The test command runs among the slow tests
(``pytest -m slow``): CI runs it itself, from a fresh clone.
"""

import json
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from shell_env import user_env

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def fresh_machine_commands() -> tuple[str, str]:
    """The two commands of README's "On a fresh machine" section: install-and-run, install-and-test."""
    section = README.split("## On a fresh machine", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```bash\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 2, "the section must show exactly two bash commands"
    run, test = (b.strip() for b in blocks)
    assert "\n" not in run and "\n" not in test, "each must be one command a user can paste"
    return run, test


def clone_files(dest: Path) -> Path:
    """Copy what a fresh clone of the working tree holds (tracked and new, unignored files) to ``dest``."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                            cwd=ROOT, capture_output=True, check=True).stdout.decode().split("\0")
    for rel in filter(None, listed):
        src = ROOT / rel
        if src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)
    return dest


def test_ci_runs_the_readme_commands():
    run, test = fresh_machine_commands()
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert test in ci, ".ci/run must run README's test command as written"
    assert run in ci, ".ci/run must run README's run command as written"
    assert ci.index(run) < ci.index(test), "the plain install and main job first, then the development install"


def test_the_readme_says_how_to_run_the_postgresql_tests_as_ci_does():
    line = 'url="$(bash deploy/test-database.sh)"'  # a failing script stops the command (an empty eval would not)
    assert f'`{line} && eval "$url" && .venv/bin/python -m pytest -q`' in README and "OVERHANG_TEST_POSTGRES_URL" in README
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert line in ci and ci[ci.index(line) + 1] == 'eval "$url"' and "set -euo pipefail" in ci
    script = (ROOT / "deploy" / "test-database.sh").read_text()
    assert 'echo "export OVERHANG_TEST_POSTGRES_URL=' in script  # the line the eval runs


NEEDS_GIT = pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(),
                               reason="needs a git checkout")


# CI runs the run command itself, from the root of a fresh clone, before the tests (test_ci_runs_the_readme_commands);
# this test also checks what the run left behind, and runs among the slow tests
@pytest.mark.slow
@NEEDS_GIT
def test_the_fresh_machine_run_command_works_from_the_repository_root(tmp_path):
    run, _ = fresh_machine_commands()
    clone = clone_files(tmp_path / "clone")
    env = user_env()

    # install and run the main job, exactly as written
    proc = subprocess.run(["bash", "-c", run], cwd=clone, env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "terminal reward" in proc.stdout and "Traceback" not in proc.stderr
    (metrics_file,) = clone.glob("outputs/*/*/metrics.json")
    metrics = json.loads(metrics_file.read_text())
    assert metrics["complete"] and metrics["episodes"] == metrics["episodes_expected"] == 20
    venv = clone / ".venv"
    where = subprocess.run([str(venv / "bin" / "python"), "-c",
                            "import overhang_framework.conf as c; print(c.__file__)"],
                           cwd=tmp_path, env=env, capture_output=True, text=True, check=True).stdout
    assert str(venv) in where, "the plain install carries the config tree"
    listing = subprocess.run([str(venv / "bin" / "overhang-framework"), "plugins"], cwd=tmp_path, env=env,
                             capture_output=True, text=True, check=True).stdout
    assert "builtins  (overhang-framework " in listing

    # the plain install brings the launcher the README's sweep uses, and the console script
    sweep = subprocess.run(
        [str(venv / "bin" / "overhang-framework"), "-m", "tasks=custom", "tasks.sequences=[[1.2,0.6]]",
         "seed=1,2", "world.physics=static", "progress=false", "hydra/launcher=joblib",
         "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={tmp_path / 'sweep'}"],
        cwd=tmp_path, env=env, capture_output=True, text=True)
    assert sweep.returncode == 0, sweep.stderr[-3000:]
    assert sorted(p.name for p in (tmp_path / "sweep").iterdir() if p.name.isdigit()) == ["0", "1"]


# CI runs the test command itself, from a fresh clone (test_ci_runs_the_readme_commands), so the
# default suite does not run it a second time inside itself
@pytest.mark.slow
@NEEDS_GIT
def test_the_fresh_machine_test_command_works_from_the_repository_root(tmp_path):
    _, test = fresh_machine_commands()
    clone = clone_files(tmp_path / "clone")
    env = user_env()
    # install for development and run the tests, exactly as written; the nested run is
    # narrowed to one quick test file through pytest's own environment variable
    env_tests = dict(env, PYTEST_ADDOPTS="tests/test_rules.py -p no:cacheprovider")
    proc = subprocess.run(["bash", "-c", test], cwd=clone, env=env_tests, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert re.search(r"\d+ passed", proc.stdout)


def error_examples() -> list[tuple[str, str]]:
    """``$ command`` / ``error: ...`` pairs of README's example error block."""
    pairs = re.findall(r"^\$ (python -m overhang_framework [^\n#]*)\n(error: [^\n]*)$", README, flags=re.M)
    pairs = [(c, e) for c, e in pairs if "hydra.run.dir" not in c]  # those need an earlier run
    assert len(pairs) >= 4
    return pairs


@pytest.mark.parametrize("command, expected", error_examples(), ids=lambda v: v[:60])
def test_readme_error_examples_print_what_the_readme_shows(tmp_path, command, expected):
    words = shlex.split(command)[1:]
    if not any(w.startswith("hydra.run.dir=") for w in words):
        words.append(f"hydra.run.dir={tmp_path}")
    proc = subprocess.run([sys.executable, *words], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [expected.replace("runs/main", str(tmp_path))]


def test_the_test_command_summary_lists_failures_errors_and_skips(tmp_path):
    """The project's pytest options name every failed, erroring and skipped test in the short summary."""
    (tmp_path / "test_outcomes.py").write_text(
        "import pytest\n\n"
        "@pytest.fixture\n"
        "def broken():\n"
        "    raise RuntimeError('fixture fails')\n\n"
        "def test_fails():\n"
        "    assert False\n\n"
        "def test_errors(broken):\n"
        "    pass\n\n"
        "def test_skipped():\n"
        "    pytest.skip('not here')\n")
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           "-c", str(ROOT / "pyproject.toml"), "--rootdir", str(tmp_path),
                           str(tmp_path / "test_outcomes.py")],
                          cwd=tmp_path, capture_output=True, text=True)
    summary = proc.stdout.split("short test summary info", 1)[-1]
    assert re.search(r"^FAILED .*test_fails", summary, flags=re.M), proc.stdout
    assert re.search(r"^ERROR .*test_errors", summary, flags=re.M), proc.stdout
    assert re.search(r"^SKIPPED .*not here", summary, flags=re.M), proc.stdout
