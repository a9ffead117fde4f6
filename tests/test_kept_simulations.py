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
