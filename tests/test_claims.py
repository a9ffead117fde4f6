"""Every figure a docs page quotes from a kept file is recomputed from that file and found in the page's text.

The figures are registered in docs/checks/*.yaml (``python -m overhang_framework.docfigures``) with the command
that recomputes them from what docs/simulations keeps; the entries named here take seconds, so the default
suite runs them."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from overhang_framework.report import docfigures

ROOT = Path(__file__).resolve().parents[1]
#: The registry's entries whose figures come from kept files, recomputed in seconds.
KEPT = ["fitting-paper-comparison", "fitting-own-noise-pilot", "fitting-own-noise-pilot-fixed-k50",
        "fitting-own-noise-pilot-fixed-k10", "fitting-agreement", "fitting-adequacy-inspace", "fitting-adequacy-cvar",
        "fitting-adequacy-edge", "fitting-motor-grid", "fitting-motor-motor", "people-graded-sizes",
        "fitting-risk-recovery-own-noise", "fitting-risk-recovery-fixed-k50", "fitting-risk-recovery-fixed-k10",
        "fitting-k-recovery", "people-risk-own-noise", "people-risk-fixed-k50", "people-risk-fixed-k10",
        "people-k-own-noise", "fidelity-table2-40",
        "people-paper-own-noise", "people-paper-like-own-noise", "people-graded-k-adapt", "people-graded-k-fixed",
        "people-graded-k-adapt-power", "people-graded-k-fixed-power"]


def test_every_figure_from_a_kept_file_is_what_the_file_gives_today():
    entries = {e.name: e for e in docfigures.load_registry(ROOT / "docs" / "checks")}
    assert set(KEPT) <= set(entries), sorted(set(KEPT) - set(entries))
    assert docfigures.main(["--registry", str(ROOT / "docs" / "checks"), "--run", "--only", *KEPT]) == 0


@pytest.mark.parametrize("entry, figure, edited", [
    ("fitting-paper-comparison", "is the best model's for 79 of 81", "is the best model's for 78 of 81"),
    ("fitting-own-noise-pilot", "the risk the true one for 4 of 8", "the risk the true one for 5 of 8"),
    ("fitting-adequacy-edge", "-1.13 (-1.32 to -0.89)", "-1.03 (-1.32 to -0.89)"),
])
def test_a_figure_edited_in_its_page_fails_the_check(tmp_path, entry, figure, edited):
    """A copy of the page with one figure changed, checked against the same kept files: the check fails."""
    (tmp_path / "docs" / "checks").mkdir(parents=True)
    shutil.copy(ROOT / "docs" / "checks" / "fitting.yaml", tmp_path / "docs" / "checks" / "fitting.yaml")
    shutil.copytree(ROOT / "docs" / "simulations", tmp_path / "docs" / "simulations")
    page = (ROOT / "docs" / "fitting.md").read_text()
    assert figure in page
    (tmp_path / "docs" / "fitting.md").write_text(page.replace(figure, edited, 1))
    registry = str(tmp_path / "docs" / "checks")
    assert docfigures.main(["--registry", registry, "--only", entry]) == 1  # the registered text is gone
    # and the page's new text is not what the kept files give
    entries = [e for e in docfigures.load_registry(tmp_path / "docs" / "checks") if e.name == entry]
    for e in entries:
        for f in e.figures:
            f.text = f.text.replace(figure, edited)
    report = docfigures.run_checks(entries, tmp_path, log=lambda *a: None)
    assert not report.ok and any(not r.ok for r in report.results)
