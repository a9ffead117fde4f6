"""The long runs kept in docs/simulations: each CSV of per-participant measures reads back, is listed in the
README, and has beside it the run whose participants it measures (same cohort name and seed as its name says)."""

from __future__ import annotations

import json
import re
import tarfile
from pathlib import Path

import pytest

from overhang_framework.behaviour.calibrate import read_people

KEPT = Path(__file__).resolve().parents[1] / "docs" / "simulations"
CSVS = sorted(KEPT.glob("*.csv"))


def test_there_are_kept_runs():
    assert CSVS, f"no CSV in {KEPT}"


@pytest.mark.parametrize("csv", CSVS, ids=[c.stem for c in CSVS])
def test_a_kept_run_reads_back_and_its_run_holds_the_same_participants(csv):
    people = read_people(csv)
    assert people["participant"].is_unique
    readme = (KEPT / "README.md").read_text()
    assert f"`{csv.name}`" in readme or f"`{csv.name.split('seed')[0]}seed{{" in readme, f"{csv.name} is not in README"
    archive = csv.with_suffix(".tar.gz")
    assert archive.exists(), f"{archive.name} is missing beside {csv.name}"
    seen, config = set(), None
    with tarfile.open(archive) as tar:
        for member in tar.getmembers():
            name = Path(member.name)
            if name.name == "run.json":
                config = json.load(tar.extractfile(member))["config"]
            elif name.suffix == ".jsonl" and (name.name == "log.jsonl" or name.parent.name == "parts"):
                for line in tar.extractfile(member).read().decode().splitlines():
                    seen.add(json.loads(line)["participant"])
    assert config is not None, f"{archive.name} has no run.json"
    assert csv.name.startswith(config["cohort"]["name"] + "-")
    seed = re.search(r"seed(\d+)", csv.name)
    assert seed and int(seed.group(1)) == config["seed"]
    assert set(people["participant"]) <= seen  # every measured participant's records are kept


def test_the_figure_of_the_kept_runs_puts_each_runs_mean_beside_the_papers(tmp_path, capsys):
    from overhang_framework.behaviour.calibrate import METRICS, TARGETS, main, measured_figure, measured_people

    runs = [KEPT / f"paper_people-time_limited-seed{s}.csv" for s in (0, 1)] + \
        [KEPT / "paper_people-unconstrained-seed0.csv"]
    assert main(["measure", *map(str, runs), "--figure", str(tmp_path / "m.png")]) == 0
    assert (tmp_path / "m.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    results = [measured_people(read_people(r)) for r in runs]
    fig = measured_figure(results, [r.stem for r in runs], tmp_path / "again.png")
    axes = fig.axes
    assert len(axes) == 2 * len(METRICS)  # a row per condition
    for ax, (condition, metric) in zip(axes, [(c, m) for c in TARGETS for m in METRICS]):
        points = ax.containers[0].lines[0].get_ydata()
        want = [r[condition][metric][0] for r in results if condition in r]
        assert list(points) == pytest.approx(want), (condition, metric)
        # the paper's mean is drawn across the panel
        assert any(list(line.get_ydata()) == [TARGETS[condition][metric][0]] * 2 for line in ax.lines)
    assert [t.get_text() for t in axes[0].get_xticklabels()] == ["seed0", "seed1"]
