"""The adversarial sample of the "stands for sure" stage: legal, seeded, biased to heavy loads on a narrow base, near
the tilt's margin; its replay in the reference; and the kept figures of docs/physics.md."""

import json
from pathlib import Path

import numpy as np
import pytest

from overhang_framework.geometry import Action, Geometry, WIDTHS
from overhang_framework.physics import adversarial
from overhang_framework.physics.tiered import TieredBackend, TieredParams
from overhang_framework.rules import is_legal

ROOT = Path(__file__).resolve().parents[1]
KEPT = ROOT / "docs" / "figures" / "tilt_adversarial.json"


def test_the_drawn_towers_are_legal_towers_of_the_task():
    for tower in adversarial.adversarial_towers(500, seed=4):
        first, *rest = tower.blocks
        assert first.layer == 0 and first.x == 0.0 and first.width in WIDTHS
        for i, block in enumerate(rest, 1):
            assert block.width in WIDTHS
            assert is_legal(Geometry(tower.blocks[:i]), block.width, Action(block.x, block.layer)), tower


def test_the_same_seed_draws_the_same_towers_and_another_seed_others():
    assert adversarial.adversarial_towers(200, seed=7) == adversarial.adversarial_towers(200, seed=7)
    assert adversarial.adversarial_towers(200, seed=7) != adversarial.adversarial_towers(200, seed=8)


def test_the_draw_is_biased_to_heavy_blocks_high_on_a_narrow_base():
    mix = adversarial.composition(adversarial.adversarial_towers(2000, seed=0))
    assert mix["ground_0.6"] > 0.7
    assert mix["heavy_at_layer_2_plus"] > 0.75
    assert mix["heavy_high_on_narrow"] > 0.6
    assert 0.4 < mix["on_0.1_grid"] < 0.65  # about half on the tasks' grid


def test_the_stage_at_its_own_tilt_is_what_classify_calls_sure():
    towers = adversarial.adversarial_towers(400, seed=2)
    backend = TieredBackend()
    assert (backend.stands_for_sure(towers) == (backend.classify(towers) == 1)).all()
    wider = TieredBackend(TieredParams(stable_tilt=0.05))
    assert (backend.stands_for_sure(towers, 0.05) == wider.stands_for_sure(towers)).all()
    per_tower = np.where(np.arange(len(towers)) % 2, 0.05, 0.04)
    assert (backend.stands_for_sure(towers, per_tower)
            == np.where(per_tower == 0.05, wider.stands_for_sure(towers), backend.stands_for_sure(towers))).all()


def test_the_margin_tilt_is_where_the_stage_stops_calling_a_tower_standing():
    backend = TieredBackend()
    towers = adversarial.adversarial_towers(3000, seed=5)
    tilts = adversarial.margin_tilts(backend, towers, 0.04, 0.06, tolerance=1e-4)
    near = np.flatnonzero((tilts > 0.04) & (tilts <= 0.06))
    assert near.size > 5
    subset = [towers[i] for i in near]
    assert not backend.stands_for_sure(subset, tilts[near]).any()
    assert backend.stands_for_sure(subset, tilts[near] - 1e-4).all()
    sure = backend.stands_for_sure(towers)
    assert (tilts[~sure] == 0.04).all() and (tilts[sure] > 0.04).all()


def test_the_kept_towers_are_the_distinct_ones_nearest_the_margin():
    backend = TieredBackend()
    sample = adversarial.draw_near_margin(20, 3, backend, 0.06, batch=5000)
    assert len(sample.towers) == 20 and sample.near_margin >= 80 and sample.rounds >= 1
    assert len({g.key for g in sample.towers}) == 20
    assert (np.diff(sample.tilts) >= 0).all() and sample.tilts[0] > 0.04 and sample.tilts[-1] <= 0.06
    assert backend.stands_for_sure(sample.towers).all()
    assert not backend.stands_for_sure(sample.towers, 0.06).any()
    again = adversarial.draw_near_margin(20, 3, backend, 0.06, batch=5000)
    assert again.towers == sample.towers
    with pytest.raises(ValueError, match="rank_tilt must be larger"):
        adversarial.draw_near_margin(5, 0, backend, 0.04)


def test_the_bound_is_the_exact_one_sided_clopper_pearson_bound():
    assert adversarial.upper_bound(0, 2000) == pytest.approx(1 - 0.05 ** (1 / 2000), rel=1e-9)
    assert adversarial.upper_bound(0, 2000) == pytest.approx(3 / 2000, rel=0.01)  # the rule of three
    from scipy.stats import binom

    bound = adversarial.upper_bound(3, 1000)
    assert binom.cdf(3, 1000, bound) == pytest.approx(0.05, rel=1e-6)
    assert adversarial.upper_bound(5, 5) == 1.0


@pytest.mark.parametrize("args, message", [
    (["--n", "0"], "error: --n must be at least 1, got 0"),
    (["--seed", "-1"], "error: --seed must be >= 0, got -1"),
    (["--workers", "0"], "error: --workers must be at least 1, got 0"),
    (["--rank-tilt", "1.0"], "error: --rank-tilt must be in (0, pi/4) rad, got 1.0"),
])
def test_bad_arguments_are_one_line_errors(tmp_path, capsys, args, message):
    assert adversarial.main([*args, "--out", str(tmp_path / "x.json")]) == 2
    err = capsys.readouterr().err
    assert err.strip() == message
    assert not (tmp_path / "x.json").exists()


def test_a_rank_tilt_not_above_the_stages_tilt_is_a_one_line_error(tmp_path, capsys):
    assert adversarial.main(["--rank-tilt", "0.03", "--out", str(tmp_path / "x.json"), "--quiet"]) == 2
    assert capsys.readouterr().err.strip() == "error: rank_tilt must be larger than the stage's tilt 0.04, got 0.03"


@pytest.mark.slow
def test_a_smaller_adversarial_sample_stands_in_the_reference(tmp_path):
    """200 towers nearest the margin of 0.04 rad, drawn from a fixed seed, all stand in the full-window reference."""
    pytest.importorskip("pybullet")
    tiered, static, pybullet = adversarial.world_params()
    assert tiered.stable_tilt == 0.04 and pybullet.early_stop is False
    backend = TieredBackend(tiered, static=static, pybullet=pybullet)
    sample = adversarial.draw_near_margin(200, 11, backend, 0.06)
    assert len(sample.towers) == 200
    # adversarial: each "stands for sure" at 0.04 and not at 0.06; mostly heavy blocks high on a narrow base
    assert backend.stands_for_sure(sample.towers).all()
    assert not backend.stands_for_sure(sample.towers, 0.06).any()
    assert (backend.classify(sample.towers) == 1).all()
    assert adversarial.composition(sample.towers)["heavy_high_on_narrow"] > 0.5
    assert sample.tilts.max() < 0.05  # the nearest of about 800 in the band
    stands, moved = adversarial.replay(sample.towers, backend.reference_params)
    errors = [adversarial.tower_text(g) for g, s in zip(sample.towers, stands) if not s]
    assert not errors, errors
    assert (moved <= pybullet.threshold).all()


def test_the_kept_file_has_the_figures_docs_physics_md_quotes():
    """docs/figures/tilt_adversarial.json is the file the documented command wrote; every figure registered for it
    (docs/checks/physics.yaml) is what docs/physics.md says."""
    from overhang_framework.report import docfigures

    data = json.loads(KEPT.read_text())
    assert data["seed"] == 0 and data["n"] == data["kept"] == 2000 and data["stable_tilt"] == 0.04
    assert data["params"]["tiered"]["stable_tilt"] == 0.04 and data["params"]["reference"]["early_stop"] is False
    assert data["errors"] == len(data["error_towers"])
    assert data["error_rate_upper"] == pytest.approx(adversarial.upper_bound(data["errors"], data["kept"]), rel=1e-9)
    assert data["stable_tilt"] < data["margin_tilt"]["min"] <= data["margin_tilt"]["max"] <= data["rank_tilt"]
    entry = next(e for e in docfigures.load_registry(ROOT / "docs" / "checks") if e.name == "physics-tilt-adversarial")
    assert entry.output == "file:tilt_adversarial.json" and "--out docs/figures/tilt_adversarial.json" in entry.command
    text = " ".join((ROOT / "docs" / "physics.md").read_text().split())
    for figure in entry.figures:
        made = docfigures.render(figure, data)
        ok, why = docfigures.matches(figure, made)
        assert ok, (figure.text, made, why)
        assert " ".join(figure.text.split()) in text
