"""A non-editable ``pip install .`` into a fresh virtual environment works, configs included."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_wheel_install_runs_the_main_job(tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    subprocess.run([str(py), "-m", "pip", "install", "-q", str(ROOT)], check=True, cwd=tmp_path)
    out = subprocess.run(
        [str(py), "-m", "overhang_framework", "tasks=custom", "tasks.sequences=[[1.2,0.6]]",
         "progress=false", f"hydra.run.dir={tmp_path / 'run'}"],
        capture_output=True, text=True, cwd=tmp_path,
    )
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "run" / "episodes.jsonl").exists()
    listing = subprocess.run([str(py), "-m", "overhang_framework", "plugins"],
                             capture_output=True, text=True, cwd=tmp_path, check=True).stdout
    assert "builtins  (overhang-framework 0.1.0)" in listing
    site = subprocess.run([str(py), "-c", "import overhang_framework.conf as c; print(c.__file__)"],
                          capture_output=True, text=True, cwd=tmp_path, check=True).stdout
    assert str(venv) in site
