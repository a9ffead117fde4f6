"""The physics benchmark's smoke run ends with one JSON line holding every figure the docs quote."""

import json
import subprocess
import sys

import pytest

KEYS = {"towers", "agreement_early_stop", "agreement_static", "agreement_static_critical",
        "speedup_early_stop", "speedup_static", "static_checks_per_s", "pool_speedup"}


@pytest.mark.slow
def test_quick_benchmark_prints_its_json_line(tmp_path):
    out = tmp_path / "bench.json"
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.bench", "--quick", "--quiet",
                           "--workers", "2", "--out", str(out)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    figures = json.loads(proc.stdout.strip().splitlines()[-1])
    assert KEYS <= set(figures)
    assert figures["towers"] == 30
    for key in ("agreement_early_stop", "agreement_static", "agreement_static_critical"):
        assert 0.0 <= figures[key] <= 1.0
    assert figures["speedup_static"] > 1 and figures["static_checks_per_s"] > 0
    assert json.loads(out.read_text())["towers"] == 30
