"""The distilled student network: its architecture, the distillation app, the shipped student and its
agreement with the teacher."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from overhang_framework.cnn.model import SHIPPED, StabilityModel, read_checkpoint, resolve_checkpoint

ROOT = Path(__file__).resolve().parents[1]


def quick_config(tmp_path, *extra):
    return [f"data.dir={tmp_path / 'data'}", f"out_dir={tmp_path / 'out'}", "data.questions=600",
            "data.part_size=300", "data.tasks=2", "data.val_tasks=1", "data.depth=1", "epochs=2",
            "batch_size=64", "progress=false", *extra]


def run_distill(args, cwd=ROOT):
    return subprocess.run([sys.executable, "-m", "overhang_framework.cnn.distill", *args], capture_output=True,
                          text=True, cwd=cwd)


# ------------------------------------------------------------------ the architecture


def test_a_student_is_built_by_name_and_its_onnx_answers_equal_torchs(tmp_path):
    import torch

    from overhang_framework.cnn.model import build_model, save_checkpoint
    from overhang_framework.cnn.student import STUDENT_RENDERER
    from overhang_framework.physics.towers import random_towers

    torch.manual_seed(0)
    net = build_model("layerconv_s", 1, 2, (8, 160))
    path = save_checkpoint(tmp_path / "s.pt", net, STUDENT_RENDERER, "layerconv_s", outputs=1, mirror=False)
    towers = random_towers(300, seed=5)
    onnx = StabilityModel(str(path), device="cpu", threads=1).probabilities(towers)
    plain = StabilityModel(str(path), device="cpu", threads=1, fused=False).probabilities(towers)
    assert np.abs(onnx - plain).max() < 1e-5
    assert onnx.std() > 0  # the towers get different answers
    with pytest.raises(ValueError, match="unknown student architecture 'layerconv_xl'; known: layerconv_s"):
        from overhang_framework.cnn.student import build_student

        build_student("layerconv_xl", 1, 2, (8, 160))


def test_the_student_picture_holds_one_row_per_layer():
    from overhang_framework.cnn.student import STUDENT_RENDERER
    from overhang_framework.geometry import Block, Geometry
    from overhang_framework.render import make_renderer

    r = make_renderer(STUDENT_RENDERER)
    g = Geometry((Block(1.8, 0.0, 0), Block(0.6, 0.65, 1)))
    img = r.render(g)
    assert img.shape == (2, 8, 160)
    fill = img[0]
    # the ground block fills 36 columns of the bottom row, the second 12 of the row above, nothing else
    assert fill[7].sum() == pytest.approx(36, abs=1e-4) and fill[6].sum() == pytest.approx(12, abs=1e-4)
    assert fill[:6].sum() == 0


def test_shipped_names_resolve_and_an_unknown_one_is_a_path():
    assert resolve_checkpoint("teacher") == resolve_checkpoint("default") == SHIPPED["teacher"]
    assert resolve_checkpoint("student") == SHIPPED["student"]
    with pytest.raises(ValueError, match="no CNN checkpoint at .*; use checkpoint=teacher, student or a .pt file"):
        StabilityModel("no-such.pt")


# ------------------------------------------------------------------ the distillation app


def test_keys_of_the_predictor_cache_round_trip_to_the_towers():
    from overhang_framework.physics.towers import random_towers
    from overhang_framework.cnn.data import from_arrays
    from overhang_framework.cnn.distill import keys_to_arrays

    towers = random_towers(50, seed=2)
    back = from_arrays(keys_to_arrays([g.key for g in towers]))
    assert [g.key for g in back] == [g.key for g in towers]


def test_distillation_runs_end_to_end_resumes_and_loads_as_a_predictor(tmp_path):
    done = run_distill(quick_config(tmp_path))
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    rows = [json.loads(line) for line in (tmp_path / "out" / "metrics.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [1, 2]
    assert set(rows[0]) >= {"questions", "visited", "train_loss"}
    assert rows[-1]["train_loss"] < rows[0]["train_loss"]
    assert summary["best"]["epoch"] in (1, 2)
    record = read_checkpoint(tmp_path / "out" / "best.pt")
    assert record["backbone"] == "layerconv_s" and record["renderer"]["size"] == [8, 160]
    import hashlib

    assert record["teacher"] == "teacher" and record["mirror"] is False
    assert record["teacher_sha256"] == hashlib.sha256(SHIPPED["teacher"].read_bytes()).hexdigest()
    parts = sorted(p.name for p in (tmp_path / "data").glob("*.npz"))
    assert parts == ["questions-0000.npz", "questions-0001.npz", "visited-" + parts[2][8:], parts[3]]
    # the teacher's answers are stored beside every tower: they are the teacher's, recomputed
    from overhang_framework.cnn.distill import read_part, teacher_logits

    part = read_part(tmp_path / "data" / "questions-0000.npz")
    teacher = StabilityModel("teacher", device="cpu", threads=1)
    np.testing.assert_allclose(part["logits"][:40], teacher_logits(teacher, {k: v[:40] for k, v in part.items()
                                                                             if k != "meta"}), atol=1e-5)
    # another config into the same folder is refused, and starts again with overwrite=true, from the parts on disk
    refused = run_distill(quick_config(tmp_path, "epochs=1"))
    assert refused.returncode == 2 and "holds a distillation with another config" in refused.stderr
    more = run_distill(quick_config(tmp_path, "epochs=1", "overwrite=true"))
    assert more.returncode == 0, more.stderr[-2000:]
    assert len((tmp_path / "out" / "metrics.jsonl").read_text().splitlines()) == 1
    from overhang_framework.plugins import Registry

    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    predictor = Registry().create("predictor", {"name": "cnn", "checkpoint": str(tmp_path / "out" / "best.pt")},
                                  world=world)
    from overhang_framework.interfaces import State
    from overhang_framework.geometry import Block, Geometry

    state = State(Geometry((Block(1.2, 0.0, 0),)), (1.2, 0.6))
    actions = world.legal_actions(state)
    p = predictor.predict(state, actions, np.random.default_rng(0))
    assert p.shape == (len(actions),) and ((p >= 0) & (p <= 1)).all()


def compose_distill(overrides):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "overhang_framework" / "cnn" / "conf"), version_base=None):
        return compose(config_name="distill", overrides=list(overrides))


def test_an_interrupted_distillation_resumes_after_its_last_finished_epoch(tmp_path, monkeypatch):
    from overhang_framework.cnn import distill

    whole = compose_distill(quick_config(tmp_path / "whole", "epochs=3"))
    distill.distill(whole)
    parted = compose_distill(quick_config(tmp_path / "parted", "epochs=3", f"data.dir={tmp_path / 'whole' / 'data'}"))
    calls = []
    original = distill.agreement

    def stop_in_the_second_epoch(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:  # two held-out sets an epoch: the second epoch's first
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(distill, "agreement", stop_in_the_second_epoch)
    with pytest.raises(KeyboardInterrupt):
        distill.distill(parted)
    assert len((tmp_path / "parted" / "out" / "metrics.jsonl").read_text().splitlines()) == 1
    monkeypatch.setattr(distill, "agreement", original)
    distill.distill(parted)
    rows = [json.loads(x) for x in (tmp_path / "parted" / "out" / "metrics.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [1, 2, 3]
    a = read_checkpoint(tmp_path / "whole" / "out" / "last.pt")["state_dict"]
    b = read_checkpoint(tmp_path / "parted" / "out" / "last.pt")["state_dict"]
    for k in a:  # the same weights as the training that was never stopped
        np.testing.assert_array_equal(a[k].numpy(), b[k].numpy())


@pytest.mark.parametrize("override, message", [
    ("architecture=resnet", "unknown architecture 'resnet'; known: layerconv_s, layerconv_m"),
    ("epochs=0", "epochs must be a whole number >= 1, got 0"),
    ("clip=-1", r"clip must be a number in \[0.1, 100\], got -1"),
    ("data.val_parts=9", "hold out everything"),
])
def test_bad_distillation_settings_are_one_line(tmp_path, override, message):
    args = quick_config(tmp_path, override)
    if override.startswith("data.val_parts"):
        args.append("data.val_tasks=2")
    done = run_distill(args)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ")
    import re

    assert re.search(message, lines[0]), lines[0]


# ------------------------------------------------------------------ calibration measures


def test_auc_and_calibration_measures_are_the_textbook_ones():
    from overhang_framework.cnn.evaluate import auc, calibration

    rng = np.random.default_rng(0)
    p = rng.random(300)
    y = rng.random(300) < p
    pairs = [(a > b) + 0.5 * (a == b) for a in p[y] for b in p[~y]]
    assert auc(p, y) == pytest.approx(np.mean(pairs))
    assert auc(np.where(y, 0.9, 0.1), y) == 1.0
    c = calibration(p, y)
    assert c["brier"] == pytest.approx(np.mean((p - y) ** 2))
    assert c["ece"] < 0.1  # drawn calibrated
    assert calibration(np.full(300, 0.9), y)["ece"] == pytest.approx(abs(0.9 - y.mean()))


def test_a_fits_tables_are_the_teachers_byte_for_byte_whichever_name_chooses_it():
    """The fit's CNN family keeps the teacher (checkpoint: default); naming it teacher changes no table
    (tests/test_cnn.py checks that a table asks for the same towers as the network as trained)."""
    from overhang_framework.fit.scores import Model, ScoreTables
    from overhang_framework.geometry import Block, Geometry
    from overhang_framework.interfaces import State
    from overhang_framework.plugins import Registry

    registry = Registry()
    world = registry.create("world", {"name": "overhang", "physics": "static"})
    value = registry.create("value", {"name": "overhang"}, world=world)
    state = State(Geometry((Block(1.8, 0.0, 0), Block(1.2, 0.5, 1))), (0.6, 1.8, 1.2))
    tables, towers = {}, {}
    for name in ("default", "teacher", "student"):
        predictor = registry.create("predictor", {"name": "cnn", "checkpoint": name}, world=world)
        tables[name] = ScoreTables(world, value, predictor, Model({"name": "cnn", "checkpoint": name}, 2),
                                   {"test": 1}).table(state)
        towers[name] = predictor.stats()["towers"]
    assert tables["default"].tobytes() == tables["teacher"].tobytes()
    assert towers["default"] == towers["teacher"]
    assert not np.array_equal(tables["student"], tables["teacher"])
    from overhang_framework.config import compose_config

    assert compose_config(["predictor=cnn"]).predictor.checkpoint == "default"  # the teacher stays the default
