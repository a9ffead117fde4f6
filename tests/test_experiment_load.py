"""The experiment load test's machinery, briefly: every acknowledged placement stored exactly once.

A handful of participants for a few seconds against a real uvicorn server process, on loopback,
with many retries of identical requests (after the answer and while the first is still served).
Timing is not asserted: the machine may be shared.
"""

import pytest

pytest.importorskip("httpx")
pytest.importorskip("uvicorn")
pytest.importorskip("pybullet")


@pytest.mark.parametrize("physics_processes", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_every_acknowledged_placement_is_stored_once(tmp_path, physics_processes):
    from overhang_framework.bench.experiment_load import LoadConfig, run_load, table

    cfg = LoadConfig(participants=4, pace=0.3, duration=5.0, retry=0.3, seed=1)
    figures = run_load(cfg, database=f"sqlite:///{tmp_path / 'load.sqlite'}", quiet=True,
                       physics_processes=physics_processes, overrides=["tasks.only=[paper00,paper01,paper02]"])
    check = figures["integrity"]
    assert figures["placements"] > 10, table(figures)
    assert check["ok"], check
    assert check["acknowledged"] == check["stored_keys"] == check["stored_rows"]
    assert check["missing"] == check["stored_twice"] == check["stored_differently"] == 0
    assert figures["retries"].get("identical", 0) > 0
    assert figures["retries"].get("different answer", 0) == 0 and figures["retries"].get("refused", 0) == 0
    assert not figures["errors"], figures["error_samples"]
    assert "integrity    OK" in table(figures)
