"""The example plugins, installed as a user would: a fresh virtual environment with the framework and
``examples/com_margin_plugin`` and the 20-line plugin of docs/plugins.md (taken from its code blocks),
their own tests run there, listed, and run in one multirun beside a built-in, with no change to the core."""

import csv
import json
import re
import shutil
import subprocess
import sysconfig
import venv
from pathlib import Path

import pytest

from shell_env import user_env

ROOT = Path(__file__).resolve().parents[1]
COM_MARGIN = ROOT / "examples" / "com_margin_plugin"
DOC = ROOT / "docs" / "plugins.md"
IGNORE = shutil.ignore_patterns("__pycache__", "*.egg-info", "build", "dist", ".pytest_cache")


def doc_files() -> dict[str, str]:
    """The files of the 20-line plugin: every code block of docs/plugins.md whose first line is ``# <path>``."""
    blocks = re.findall(r"```(?:python|yaml|toml)\n# ([\w./-]+\.(?:py|yaml|toml))\n(.*?)```", DOC.read_text(), re.S)
    return {path: f"# {path}\n{body}" for path, body in blocks}


class Installed:
    def __init__(self, base: Path):
        self.base, self.src, self.env = base, base / "src", user_env()
        self.python = base / "venv" / "bin" / "python"

    def run(self, *args, cwd=None, check=True):
        proc = subprocess.run([str(self.python), *args], cwd=cwd or self.src, env=self.env,
                              capture_output=True, text=True)
        if check:
            assert proc.returncode == 0, f"{' '.join(args)}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
        return proc


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """A fresh venv holding a plain (non-editable) install of the framework, the com_margin plugin and the
    documented ``overhang-edge`` plugin, with the test run's dependencies; sources are copied first so that
    building them leaves the working tree untouched."""
    box = Installed(tmp_path_factory.mktemp("plugins"))
    framework = box.src / "framework"
    for name in ("overhang_framework", "plugins", "hydra_plugins"):
        shutil.copytree(ROOT / name, framework / name, ignore=IGNORE)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, framework / name)
    shutil.copytree(COM_MARGIN, box.src / "examples" / "com_margin_plugin", ignore=IGNORE)
    files = doc_files()
    assert set(files) == {"overhang_edge/__init__.py", "overhang_edge/conf/predictor/edge.yaml",
                          "pyproject.toml", "tests/test_edge.py"}, "docs/plugins.md names the plugin's files"
    edge = box.src / "overhang-edge"
    for path, text in files.items():
        (edge / path).parent.mkdir(parents=True, exist_ok=True)
        (edge / path).write_text(text)
    (edge / "overhang_edge" / "conf" / "__init__.py").write_text("")
    body = files["overhang_edge/__init__.py"].splitlines()
    assert len([line for line in body if line.strip() and not line.startswith("#")]) <= 25

    venv.EnvBuilder(with_pip=True).create(box.base / "venv")
    # The three packages are installed into the venv as a user would (plain, with their entry points); their
    # dependencies (torch, and the rest of the test extra) are those of the test run, reached through a path
    # file after the venv's own site-packages, rather than copied again. The venv's own installs come first,
    # and importlib.metadata takes the first distribution of a name, so the test run's overhang-framework
    # (an editable install, whose path hooks a path file does not run) is not seen.
    inner = box.run("-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])").stdout.strip()
    outer = sorted({sysconfig.get_paths()[k] for k in ("purelib", "platlib")})
    (Path(inner) / "zz_test_run_dependencies.pth").write_text("".join(f"{d}\n" for d in outer))
    box.run("-m", "pip", "install", "-q", "--no-compile", "--no-deps", str(framework),
            str(box.src / "examples" / "com_margin_plugin"), str(edge), cwd=box.base)
    missing = box.run("-m", "pip", "check", check=False)
    assert "overhang" not in missing.stdout, missing.stdout
    return box


def test_the_installed_plugins_are_listed_with_their_versions(installed):
    listing = installed.run("-m", "overhang_framework", "plugins").stdout
    assert "com_margin  (overhang-com-margin 0.1.0)\n  predictors  com_margin\n" \
           "  configs     pkg://overhang_com_margin.conf" in listing
    assert "edge  (overhang-edge 0.1.0)\n  predictors  edge\n" in listing
    assert "builtins  (overhang-framework 0.1.0)\n" in listing
    rows = {row["plugin"]: row for row in json.loads(installed.run("-m", "overhang_framework", "plugins",
                                                                  "--json").stdout)}
    assert rows["com_margin"]["registers"] == {"predictor": ["com_margin"]}
    # an unknown name lists the plugins' names beside the built-ins'
    proc = installed.run("-m", "overhang_framework", "predictor=nope", check=False)
    assert proc.returncode != 0
    from overhang_framework.plugins import Registry

    names = ", ".join(sorted(set(Registry().names("predictor")) | {"com_margin", "edge"}))
    assert f"error: unknown predictor 'nope'; installed predictors: {names}" in proc.stderr


def test_the_plugins_pass_their_own_tests_in_the_installed_environment(installed):
    for tests in ("examples/com_margin_plugin/tests", "overhang-edge/tests"):
        out = installed.run("-m", "pytest", "-q", "-p", "no:cacheprovider", tests).stdout
        assert re.search(r"\d+ passed", out) and "skipped" not in out and "failed" not in out, out[-2000:]
    # the classes under test come from the installed packages, not from the copied sources
    where = installed.run("-c", "import overhang_com_margin, overhang_edge, overhang_framework; "
                                "print(overhang_com_margin.__file__, overhang_edge.__file__, "
                                "overhang_framework.__file__)").stdout
    assert where.count(str(installed.base / "venv")) == 3


@pytest.mark.slow
def test_a_multirun_runs_the_plugins_beside_a_built_in(installed):
    sweep = installed.base / "sweep"
    installed.run("-m", "overhang_framework", "-m", "predictor=veridical,com_margin,edge",
                  "world.physics=static", "tasks=example", "progress=false", f"hydra.sweep.dir={sweep}")
    with open(sweep / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["predictor"], r["status"]) for r in rows] == [
        ("veridical", "complete"), ("com_margin", "complete"), ("edge", "complete")]
    for row in rows:
        assert row["episodes"] == row["episodes_expected"] == "1"
        assert float(row["reward_mean"]) >= 0
        config = (sweep / row["job"] / ".hydra" / "config.yaml").read_text()
        assert f"name: {row['predictor']}" in config
    assert "scale: 0.05\n  bias: 0.0" in (sweep / "1" / ".hydra" / "config.yaml").read_text()
