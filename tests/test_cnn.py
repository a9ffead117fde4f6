"""The CNN: data set, training app, shipped checkpoint, evaluation app and the ``cnn`` predictor."""

import json
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from overhang_framework.cnn import data as cnn_data
from overhang_framework.cnn.model import DEFAULT_CHECKPOINT, StabilityModel, read_checkpoint
from overhang_framework.geometry import Action, Block, Geometry
from overhang_framework.interfaces import State
from overhang_framework.plugins import ConfigError, Registry
from overhang_framework.testing.contracts import PredictorContract

ROOT = Path(__file__).resolve().parents[1]


def static_world():
    return Registry().create("world", {"name": "overhang", "physics": "static"})


# ------------------------------------------------------------------ data set

TINY = cnn_data.DataSpec(seed=3, shards=2, shard_size=24, physics="static", near_critical=0.5)


def test_shards_are_balanced_labelled_and_reproducible(tmp_path):
    manifest = cnn_data.generate(TINY, tmp_path, progress=False)
    data = cnn_data.load(tmp_path)
    assert manifest["complete"] and manifest["n"] == len(data["stable"]) > 0
    assert data["stable"].sum() * 2 == len(data["stable"])  # balanced
    assert data["near_critical"].any() and (~data["near_critical"]).any()
    # labels are the reference physics' verdicts of the stored towers
    from overhang_framework.physics.factory import make_backend

    towers = cnn_data.from_arrays(data)
    np.testing.assert_array_equal(make_backend("static").stable_batch(towers), data["stable"])
    # every tower but its last block stands, by the static model used to grow it
    prefixes = [Geometry(g.blocks[:-1]) for g in towers]
    assert make_backend("static").stable_batch(prefixes).all()
    assert set(data["n_blocks"]) <= set(range(TINY.min_blocks, TINY.max_blocks + 1))
    again = cnn_data.generate_shard(TINY, 0)
    first = cnn_data.read_shard(cnn_data.shard_path(tmp_path, 0))
    np.testing.assert_array_equal(again["xs"], first["xs"])
    assert first["meta"]["seed"] == 3 and first["meta"]["physics"] == "static"


def test_generation_resumes_and_refuses_other_settings(tmp_path, monkeypatch):
    cnn_data.generate(TINY, tmp_path, progress=False)
    made = []
    original = cnn_data.generate_shard
    monkeypatch.setattr(cnn_data, "generate_shard", lambda spec, i: made.append(i) or original(spec, i))
    cnn_data.shard_path(tmp_path, 1).unlink()
    cnn_data.generate(TINY, tmp_path, progress=False)
    assert made == [1]
    from dataclasses import replace

    with pytest.raises(ValueError, match="other settings"):
        cnn_data.generate(replace(TINY, window=0.1), tmp_path, progress=False)


def test_bad_data_settings_are_refused():
    with pytest.raises(ValueError, match="near_critical must be a number in"):
        cnn_data.DataSpec(near_critical=2)
    with pytest.raises(ValueError, match="unknown physics 'newton'; allowed"):
        cnn_data.DataSpec(physics="newton")
    with pytest.raises(ValueError, match="max_blocks must be at most 8"):
        cnn_data.DataSpec(max_blocks=9)


def test_margin_verdicts_say_how_far_a_tower_is_from_tipping():
    # a 0.6 block whose centre is 5 cm inside the right edge of the 1.8 block below it
    near_edge = Geometry((Block(1.8, 0.0, 0), Block(0.6, 0.85, 1)))
    beyond = Geometry((Block(1.8, 0.0, 0), Block(0.6, 0.97, 1)))  # 7 cm beyond the edge
    data = cnn_data.to_arrays([near_edge, beyond])
    v = cnn_data.margin_verdicts(data, [-0.1, -0.05, 0.0, 0.03, 0.08])
    assert v.tolist() == [[True, True, True, True, False], [True, False, False, False, False]]
    # on random questions: stable with a larger margin implies stable with a smaller one
    shard = cnn_data.generate_shard(TINY, 0)
    margins = [-0.08, -0.02, 0.0, 0.02, 0.08]
    v = cnn_data.margin_verdicts(shard, margins)
    assert (v[:, 1:] <= v[:, :-1]).all()
    assert 0 < v.mean() < 1
    assert np.array_equal(cnn_data.margin_verdicts(shard, margins, workers=2), v)


# ------------------------------------------------------------------ training


def train_cfg(tmp_path, *overrides, small_images=True):
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from overhang_framework.cnn import train

    GlobalHydra.instance().clear()
    conf = str(Path(train.__file__).parent / "conf")
    with initialize_config_dir(conf, version_base=None):
        return compose("train", overrides=[
            "data.shards=3", "data.shard_size=16", "data.physics=static", f"data.dir={tmp_path / 'data'}",
            "epochs=2", "batch_size=8", "workers=1", "threads=1", "progress=false",
            *(["renderer.size=[24,48]"] if small_images else []), f"out_dir={tmp_path / 'run'}", *overrides])


def interrupt_while_validating_epoch_2(monkeypatch, cfg) -> None:
    """Run the training ``cfg`` until it validates its second epoch, and stop it there with Ctrl-C."""
    from overhang_framework.cnn import train

    original = train.evaluate_arrays
    metrics = Path(cfg.out_dir) / "metrics.jsonl"

    def interrupt(*args, **kwargs):
        if metrics.exists() and len(metrics.read_text().splitlines()) == 1:  # validating epoch 2
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(train, "evaluate_arrays", interrupt)
    with pytest.raises(KeyboardInterrupt):
        train.train(cfg)
    monkeypatch.setattr(train, "evaluate_arrays", original)


def test_training_runs_end_to_end_and_resumes_where_it_stopped(tmp_path, monkeypatch):
    from overhang_framework.cnn import train

    full = train.train(train_cfg(tmp_path / "a"))
    assert full["best"]["epoch"] in (1, 2)
    lines = (tmp_path / "a" / "run" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(line)["epoch"] for line in lines] == [1, 2]
    best = read_checkpoint(tmp_path / "a" / "run" / "best.pt")
    assert best["renderer"]["size"] == [24, 48] and best["backbone"] == "mobilenetv3_small_050"
    # validation scored a single image and mirror averaging, and the checkpoint records the better one
    row = json.loads(lines[best["epoch"] - 1])
    chosen = row["val_accuracy_mirror"] if row["mirror"] else row["val_accuracy_single"]
    assert row["val_accuracy"] == chosen == best["metrics"]["accuracy"]
    assert best["mirror"] is row["mirror"] is (row["val_accuracy_mirror"] > row["val_accuracy_single"])

    # the same training, interrupted during epoch 2, then run again: it resumes after epoch 1
    interrupt_while_validating_epoch_2(monkeypatch, train_cfg(tmp_path / "b"))
    lines = (tmp_path / "b" / "run" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(line)["epoch"] for line in lines] == [1]
    resumed = train.train(train_cfg(tmp_path / "b"))
    lines = (tmp_path / "b" / "run" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(line)["epoch"] for line in lines] == [1, 2]
    a = read_checkpoint(tmp_path / "a" / "run" / "last.pt")["state_dict"]
    b = read_checkpoint(tmp_path / "b" / "run" / "last.pt")["state_dict"]
    for k in a:
        assert np.allclose(a[k].numpy(), b[k].numpy(), atol=1e-5), k
    assert resumed["best"]["val_accuracy"] == pytest.approx(full["best"]["val_accuracy"])

    # another config in the same out_dir is refused
    with pytest.raises(ValueError, match="another config"):
        train.train(train_cfg(tmp_path / "b", "optim.lr=0.1"))


@pytest.mark.slow
def test_training_with_auxiliary_margin_targets_keeps_the_verdict_first(tmp_path):
    from overhang_framework.cnn import train

    train.train(train_cfg(tmp_path, "aux.margins=[-0.02,0.02]", "epochs=1"))
    best = read_checkpoint(tmp_path / "run" / "best.pt")
    assert best["outputs"] == 3 and best["state_dict"]["classifier.weight"].shape[0] == 3
    model = StabilityModel(str(tmp_path / "run" / "best.pt"), device="cpu")
    probs = model.probabilities([Geometry((Block(1.8, 0.0, 0), Block(0.6, x, 1))) for x in (0.0, 1.0)])
    assert probs.shape == (2,) and ((probs > 0) & (probs < 1)).all()


# a training run of its own (31 s on a busy machine); the training tests that stay in the default suite train and resume too
@pytest.mark.slow
def test_training_keeps_a_moving_average_of_the_weights_and_resumes_it(tmp_path, monkeypatch):
    from overhang_framework.cnn import train

    original = train.evaluate_arrays
    for winner in ("ema", "trained"):
        calls = []

        def scored(net, *args, **kwargs):  # each epoch scores the trained weights, then their average
            calls.append(net)
            result = dict(original(net, *args, **kwargs))
            result["accuracy"] += 0.5 if (len(calls) % 2 == 0) == (winner == "ema") else 0.0
            return result

        monkeypatch.setattr(train, "evaluate_arrays", scored)
        train.train(train_cfg(tmp_path / winner, "ema=0.9", "epochs=1"))
        monkeypatch.setattr(train, "evaluate_arrays", original)
        assert len(calls) == 2 and calls[0] is not calls[1]
        row = json.loads((tmp_path / winner / "run" / "metrics.jsonl").read_text())
        best, last = (read_checkpoint(tmp_path / winner / "run" / name) for name in ("best.pt", "last.pt"))
        averaged = {k[len("module."):]: v for k, v in last["ema_state"].items() if k.startswith("module.")}
        assert averaged.keys() == last["state_dict"].keys()
        assert any(not np.allclose(v.numpy(), last["state_dict"][k].numpy()) for k, v in averaged.items())
        # validation scored both sets of weights, and best.pt keeps the better one and says which
        assert row["weights"] == best["weights"] == winner
        assert row["val_accuracy"] == max(row["val_accuracy_ema"], row["val_accuracy_trained"])
        kept = averaged if winner == "ema" else last["state_dict"]
        for k, v in best["state_dict"].items():
            assert np.array_equal(v.numpy(), kept[k].numpy()), k
        model = StabilityModel(str(tmp_path / winner / "run" / "best.pt"), device="cpu")
        assert model.probabilities([Geometry((Block(1.8, 0.0, 0), Block(0.6, 0.5, 1)))]).shape == (1,)

    # interrupted while validating epoch 2 and run again, it resumes the average too
    train.train(train_cfg(tmp_path / "c", "ema=0.9"))
    interrupt_while_validating_epoch_2(monkeypatch, train_cfg(tmp_path / "b", "ema=0.9"))
    train.train(train_cfg(tmp_path / "b", "ema=0.9"))
    whole, resumed = (read_checkpoint(tmp_path / d / "run" / "last.pt")["ema_state"] for d in ("c", "b"))
    for k, v in whole.items():
        assert np.allclose(v.numpy(), resumed[k].numpy(), atol=1e-5), k


def test_a_training_without_an_average_is_resumed_as_before(tmp_path):
    from overhang_framework.cnn import train

    # run directories from before ema existed record no ema key, and still resume with the default
    assert "ema" not in train.config_record(train_cfg(tmp_path))
    assert train.config_record(train_cfg(tmp_path, "ema=0.99"))["ema"] == 0.99
    train.train(train_cfg(tmp_path, "epochs=1"))
    (tmp_path / "run" / "config.json").unlink()  # past the config check, last.pt has no average to resume
    with pytest.raises(ValueError, match="last.pt holds no moving average of the weights to resume"):
        train.train(train_cfg(tmp_path, "epochs=1", "ema=0.9"))


# two training processes (42 s on a busy machine); one-process training and resuming stay in the default suite
@pytest.mark.slow
def test_training_on_two_processes_is_reproducible_and_resumes(tmp_path, capsys):
    from overhang_framework.cnn import train

    cfg = lambda name, *more: train_cfg(tmp_path / name, "processes=2", f"data.dir={tmp_path / 'data'}", *more)  # noqa: E731
    full = train.train(cfg("a"))
    assert full["processes"] == 2 and full["best"]["epoch"] in (1, 2)
    rows = [json.loads(line) for line in (tmp_path / "a" / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [1, 2]
    last = read_checkpoint(tmp_path / "a" / "run" / "last.pt")
    n_train = last["data_size"]["train"]
    assert rows[0]["images_per_s"] * rows[0]["seconds"] == pytest.approx(n_train // 8 * 8)  # both shares counted
    # the same config in a new out_dir gives the same weights
    train.train(cfg("b"))
    again = read_checkpoint(tmp_path / "b" / "run" / "last.pt")
    for k, v in last["state_dict"].items():
        assert np.array_equal(v.numpy(), again["state_dict"][k].numpy()), k
    # rerun in place: both processes load last.pt, find nothing left to do and agree on the best epoch
    capsys.readouterr()
    resumed = train.train(cfg("a"))
    assert resumed["best"] == full["best"]
    assert read_checkpoint(tmp_path / "a" / "run" / "last.pt")["epoch"] == 2
    # a batch that does not split evenly is refused before any work
    with pytest.raises(ValueError, match=r"batch_size \(9\) must be a multiple of processes \(2\)"):
        train.train(cfg("d", "batch_size=9"))


def test_a_failed_training_process_is_one_clear_error(tmp_path):
    from omegaconf import OmegaConf

    from overhang_framework.cnn import train

    cfg = OmegaConf.to_container(train_cfg(tmp_path, "processes=2"), resolve=True)
    cfg["backbone"]["name"] = "no_such_backbone"  # past the checks: it fails inside the processes
    job = {"cfg": cfg, "record": {}, "spec": {}, "train": {}, "val": {}, "aux": None, "data_seconds": 0.0}
    with pytest.raises(train.TrainingProcessFailed, match="a training process failed .*no_such_backbone.*"
                                                          "last.pt keeps the finished epochs, rerun to resume"):
        train.fit_in_processes(2, job)


def test_training_can_start_from_a_checkpoint_and_records_it(tmp_path):
    from overhang_framework.cnn import train

    first = tmp_path / "a" / "run" / "best.pt"
    train.train(train_cfg(tmp_path / "a", "aux.margins=[0.02]", "epochs=1"))
    # one step at learning rate 0: the second training's weights are the first's, and it says where from
    train.train(train_cfg(tmp_path / "b", "aux.margins=[0.02]", "epochs=1", f"init={first}", "optim.lr=0",
                          "data.shards=2", "data.val_shards=1", "batch_size=64"))
    a, b = read_checkpoint(first), read_checkpoint(tmp_path / "b" / "run" / "best.pt")
    for k, v in a["state_dict"].items():
        if "running" not in k and "num_batches" not in k:  # batch norm statistics still move in training mode
            assert np.array_equal(v.numpy(), b["state_dict"][k].numpy()), k
    assert b["init_from"]["path"] == str(first) and b["init_from"]["epoch"] == 1
    assert b["init_from"]["train_config"]["aux"]["margins"] == [0.02]
    # a checkpoint made for another network is refused in one line naming what differs
    with pytest.raises(ValueError, match="init checkpoint .* has outputs 2 but this training has 1"):
        train.train(train_cfg(tmp_path / "c", "aux.margins=[]", f"init={first}"))
    with pytest.raises(ValueError, match="init checkpoint .* has renderer"):
        train.train(train_cfg(tmp_path / "d", "aux.margins=[0.02]", f"init={first}", "renderer.size=[24,64]"))


def test_the_renderer_channels_are_recorded_in_the_checkpoint_and_set_the_network_input(tmp_path):
    from overhang_framework.cnn import train

    train.train(train_cfg(tmp_path, "renderer.channels=[x,fill]", "epochs=1"))
    best = read_checkpoint(tmp_path / "run" / "best.pt")
    assert best["renderer"]["channels"] == ["x", "fill"]
    model = StabilityModel(str(tmp_path / "run" / "best.pt"), device="cpu")
    assert model.renderer.channel_names == ("x", "fill") and model.renderer.shape == (2, 24, 48)
    assert model.probabilities([Geometry((Block(1.8, 0.0, 0),))]).shape == (1,)


@pytest.mark.slow
def test_the_renderer_options_compose(tmp_path):
    from overhang_framework.cnn import train

    cfg = train_cfg(tmp_path / "pb", "renderer=pybullet", "renderer.size=[24,48]", "epochs=1", "data.shard_size=8",
                    small_images=False)
    assert cfg.renderer.name == "pybullet" and "channels" not in cfg.renderer
    train.train(cfg)  # trains on PyBullet's images, and the checkpoint loads with its renderer
    model = StabilityModel(str(tmp_path / "pb" / "run" / "best.pt"), device="cpu")
    assert model.renderer.name == "pybullet"
    assert model.probabilities([Geometry((Block(1.8, 0.0, 0),))]).shape == (1,)
    assert train.renderer_of(train_cfg(tmp_path)).channel_names == ("fill", "bevel", "x")


def test_bad_training_settings_are_refused(tmp_path):
    from overhang_framework.cnn import train

    with pytest.raises(ValueError, match="inception_v4 needs inputs of at least 75x75"):
        train.check(train_cfg(tmp_path, "backbone.name=inception_v4"))
    with pytest.raises(ValueError, match="unknown timm backbone 'resnet9000'"):
        train.check(train_cfg(tmp_path, "backbone.name=resnet9000"))
    with pytest.raises(ValueError, match="data.val_shards must be"):
        train.check(train_cfg(tmp_path, "data.val_shards=3"))
    with pytest.raises(ValueError, match=r"aux.margins must be numbers of metres in \(-1, 1\), got 2"):
        train.check(train_cfg(tmp_path, "aux.margins=[0.01,2]"))
    with pytest.raises(ValueError, match="aux.weight must be a number >= 0"):
        train.check(train_cfg(tmp_path, "aux.weight=-1"))
    for bad in ("1.5", "0", "true"):
        with pytest.raises(ValueError, match="ema must be null or a decay between 0 and 1"):
            train.check(train_cfg(tmp_path, f"ema={bad}"))


def test_the_inception_option_sets_a_large_enough_input(tmp_path):
    from overhang_framework.cnn import train

    cfg = train_cfg(tmp_path, "backbone=inception_v4", small_images=False)
    assert cfg.backbone.name == "inception_v4" and min(cfg.renderer.size) >= 75
    train.check(cfg)


# ------------------------------------------------------------------ shipped checkpoint


def test_the_shipped_checkpoint_is_small_and_records_how_it_was_made():
    assert DEFAULT_CHECKPOINT.stat().st_size <= 20 * 2**20
    info = read_checkpoint(DEFAULT_CHECKPOINT)
    assert info["renderer"]["name"] == "raster"
    assert info["data"]["seed"] == 0 and info["data"]["physics"] == "tiered"
    assert (DEFAULT_CHECKPOINT.parent / "default.md").is_file()


@pytest.fixture(scope="module")
def fresh_accuracy():
    """The shipped model's accuracy on 160 fresh random questions (seed 777, never used in training)."""
    model = StabilityModel("default", device="cpu")
    spec = cnn_data.DataSpec(seed=777, shards=1, shard_size=160, near_critical=0.0)
    data = cnn_data.generate_shard(spec, 0)
    probs = model.probabilities(cnn_data.from_arrays(data))
    return float(((probs >= 0.5) == data["stable"]).mean())


def test_the_shipped_checkpoint_loads_offline(monkeypatch):
    def no_network(*args, **kwargs):
        raise AssertionError("loading the checkpoint touched the network")

    monkeypatch.setattr(socket.socket, "connect", no_network)
    monkeypatch.setattr(socket, "create_connection", no_network)
    model = StabilityModel("default", device="cpu")
    assert model.probabilities([Geometry((Block(1.8, 0.0, 0), Block(0.6, 0.0, 1)))]).shape == (1,)


def test_the_shipped_checkpoint_scores_at_least_95_percent_on_fresh_towers(fresh_accuracy):
    # 98.7% on the 1,594 random-placement questions of the seed-1000 held-out set (docs/cnn.md)
    assert fresh_accuracy >= 0.95, fresh_accuracy


# ------------------------------------------------------------------ the predictor


class TestCNNContract(PredictorContract):
    @pytest.fixture
    def world(self):
        return static_world()

    @pytest.fixture
    def predictor(self, world):
        return Registry().create("predictor", {"name": "cnn", "device": "cpu"}, world=world)


def test_cnn_predictor_scores_all_candidates_at_once_and_caches():
    world = static_world()
    predictor = Registry().create("predictor", {"name": "cnn", "device": "cpu"}, world=world)
    calls = []
    original = predictor.model.probabilities
    predictor.model.probabilities = lambda gs: calls.append(len(gs)) or original(gs)
    state = State(Geometry((Block(1.8, 0.0, 0),)), (1.2,))
    actions = world.legal_actions(state)
    p = predictor.predict(state, actions, np.random.default_rng(0))
    assert calls == [len(actions)]
    again = predictor.predict(state, actions[:5], np.random.default_rng(1))
    assert calls == [len(actions)]  # all cached
    np.testing.assert_array_equal(again, p[:5])
    assert predictor.stats()["cache_hits"] == 5
    # a block centred on the base stands; one hanging 1.1 m beyond its edge falls
    centred, hanging = predictor.predict(state, [Action(0.0, 1), Action(2.0, 1)], np.random.default_rng(0))
    assert centred > 0.5 > hanging


def test_mirror_averaging_is_the_mean_logit_of_a_tower_and_its_mirror_image():
    towers = [Geometry((Block(1.8, 0.0, 0), Block(0.6, x, 1), Block(1.2, x + 0.3, 2))) for x in (-0.7, 0.2, 0.8)]
    mirrored = [Geometry(tuple(Block(b.width, -b.x, b.layer) for b in g.blocks)) for g in towers]
    plain = StabilityModel("default", device="cpu", mirror=False)
    both = StabilityModel("default", device="cpu", mirror=True, batch_size=4)  # 2 towers a pass
    logit = lambda p: np.log(p / (1 - p))  # noqa: E731
    a, b = logit(plain.probabilities(towers)), logit(plain.probabilities(mirrored))
    assert not np.allclose(a, b)  # the network alone is not mirror-symmetric
    np.testing.assert_allclose(logit(both.probabilities(towers)), (a + b) / 2, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(both.probabilities(towers), both.probabilities(mirrored), atol=1e-5)
    # auto follows the checkpoint's record from validation, else whether it trained on mirrored images
    from overhang_framework.cnn.model import trained_mirrored

    assert trained_mirrored({"mirror": False, "train_config": {"augment": {"mirror": 0.5}}}) is False
    assert trained_mirrored({"mirror": True, "train_config": {"augment": {"mirror": 0.0}}}) is True
    assert trained_mirrored({"train_config": {"augment": {"mirror": 0.5}}}) is True
    assert trained_mirrored({"train_config": {"augment": {"mirror": 0.0}}}) is False
    shipped = read_checkpoint(DEFAULT_CHECKPOINT)
    assert StabilityModel("default", device="cpu").mirror is trained_mirrored(shipped)
    world = static_world()
    predictor = Registry().create("predictor", {"name": "cnn", "device": "cpu", "mirror": False}, world=world)
    assert predictor.model.mirror is False
    state = State(Geometry((Block(1.8, 0.0, 0),)), (1.2,))
    predictor.predict(state, world.legal_actions(state)[:7], np.random.default_rng(0))
    assert predictor.stats()["images"] == 7


# ------------------------------------------------------------------ inference: folded, batched, ONNX Runtime


@pytest.fixture(scope="module")
def unfused_and_fused():
    """The shipped network as trained, folded and run by torch, and folded and run by ONNX Runtime."""
    return (StabilityModel("default", device="cpu", fused=False),
            StabilityModel("default", device="cpu", runtime="torch"),
            StabilityModel("default", device="cpu"))


@pytest.mark.slow
def test_the_fused_network_gives_the_trained_networks_probabilities(unfused_and_fused):
    import torch

    from overhang_framework.physics.towers import random_towers

    unfused, folded, onnx = unfused_and_fused
    assert unfused.runtime == folded.runtime == "torch" and onnx.runtime == "onnxruntime"
    n_bn = sum(isinstance(m, torch.nn.BatchNorm2d) for m in unfused.net.modules())
    assert unfused.folded == 0 and folded.folded == n_bn > 0
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.net.modules())
    # 3,000 towers of 2-7 blocks and 600 near-critical ones (the last block at its static flip +- 5 cm)
    data = cnn_data.generate_shard(cnn_data.DataSpec(seed=31, shards=1, shard_size=600, near_critical=1.0,
                                                             physics="static"), 0)
    towers = random_towers(3000, seed=5) + cnn_data.from_arrays(data)
    reference = unfused.probabilities(towers)
    for model in (folded, onnx):
        p = model.probabilities(towers)
        # measured: at most 1.5e-5 (float32 rounding of the folded weights and of other kernels)
        assert np.abs(p - reference).max() < 1e-4
        assert ((p >= 0.5) == (reference >= 0.5)).mean() >= 0.999


def test_folding_keeps_any_timm_networks_output_and_needs_eval_mode():
    import timm
    import torch

    from overhang_framework.cnn.model import fold_batch_norm

    torch.manual_seed(0)
    for backbone in ("resnet10t", "regnetx_002"):
        net = timm.create_model(backbone, pretrained=False, num_classes=2).eval()
        for m in net.modules():  # batch norms that are far from the identity
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-1, 1), m.running_var.uniform_(0.5, 2), m.weight.data.uniform_(0.5, 1.5)
        x = torch.rand(3, 3, 48, 48)
        with torch.inference_mode():
            before = net(x)
        assert fold_batch_norm(net) > 0
        with torch.inference_mode():
            torch.testing.assert_close(net(x), before, rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="needs a network in eval mode"):
        fold_batch_norm(timm.create_model("resnet10t", pretrained=False).train())


def test_mirrored_images_equal_the_images_of_mirrored_towers():
    from overhang_framework.physics.towers import random_towers
    from overhang_framework.render import RasterRenderer, block_arrays

    widths, xs, layers, mask = block_arrays(random_towers(200, seed=2))
    for channels in (("fill", "bevel", "x"), ("x", "top"), ("fill", "bevel", "top")):
        renderer = RasterRenderer(channels=channels)
        images = renderer.render_arrays(widths, xs, layers, mask)
        drawn = renderer.render_arrays(widths, -xs, layers, mask)
        assert not np.allclose(images, drawn)
        np.testing.assert_allclose(renderer.mirror_images(images), drawn, atol=1e-5)


def test_score_tables_with_the_fused_batched_cnn_are_the_tables_of_the_trained_network():
    """Choices and likelihoods of a score table do not change beyond float rounding, in fewer, larger calls."""
    from overhang_framework.fit.scores import Model, ScoreTables
    from overhang_framework.search import ChoiceRule

    world = static_world()
    registry = Registry()
    value = registry.create("value", {"name": "overhang"}, world=world)
    new = registry.create("predictor", {"name": "cnn", "device": "cpu"}, world=world)
    old = registry.create("predictor", {"name": "cnn", "device": "cpu", "fused": False}, world=world)
    assert new.batched and not old.batched
    passes = {}
    for label, predictor in (("new", new), ("old", old)):
        original = predictor.model.probabilities
        predictor.model.probabilities = lambda gs, f=original, k=label: passes.setdefault(k, []).append(len(gs)) or f(gs)
    states = [State(Geometry((Block(1.8, 0.0, 0),)), (1.2, 0.6, 1.2)),
              State(Geometry((Block(1.8, 0.0, 0), Block(1.2, 0.5, 1))), (0.6, 1.8))]
    rule = ChoiceRule("softmax", beta=10.0)
    for depth in (1, 2):
        for state in states:
            passes.clear()
            model = Model({"name": "cnn"}, depth)
            tables = {}
            for label, predictor in (("new", new), ("old", old)):
                predictor.clear_cache()
                tables[label] = ScoreTables(world, value, predictor, model, {"test": 1}).table(state)
            assert len(tables["new"]) == len(world.legal_actions(state)) > 10
            assert np.abs(tables["new"] - tables["old"]).max() < 1e-4
            # Mirror-image placements on a centred tower score the same up to rounding, so the best
            # action of one table is among the best of the other, not always the same index.
            assert tables["old"][np.argmax(tables["new"])] > tables["old"].max() - 1e-4
            assert tables["new"][np.argmax(tables["old"])] > tables["new"].max() - 1e-4
            np.testing.assert_allclose(rule.probabilities(tables["new"]), rule.probabilities(tables["old"]),
                                       atol=1e-4)
            assert sum(passes["new"]) == sum(passes["old"])  # the same towers
            if depth == 2:  # the root's children in one call, not one call each
                assert len(passes["new"]) == 2 < len(passes["old"])


def test_a_hybrid_is_batched_when_its_cnn_is_and_empties_its_cnns_cache():
    world = static_world()
    hybrid = Registry().create("predictor", {"name": "hybrid"}, world=world)
    reference = Registry().create("predictor", {"name": "hybrid", "late_params": {"fused": False}}, world=world)
    assert hybrid.batched and not reference.batched
    state = State(Geometry((Block(1.8, 0.0, 0), Block(1.2, 0.3, 1), Block(0.6, 0.1, 2))), (1.2,))
    hybrid.predict(state, world.legal_actions(state)[:4], np.random.default_rng(0))  # 4 blocks: the CNN
    assert len(hybrid.late._cache) == 4
    hybrid.clear_cache()
    assert len(hybrid.late._cache) == 0


@pytest.mark.slow
def test_the_exported_network_is_kept_between_processes(tmp_path, monkeypatch):
    from overhang_framework.cnn import model as cnn_model

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(cnn_model, "_ONNX_MODELS", {})
    monkeypatch.setattr(cnn_model, "_ONNX_SHARED", {})
    exports = []
    original = cnn_model.export_onnx
    monkeypatch.setattr(cnn_model, "export_onnx", lambda *a: exports.append(1) or original(*a))
    tower = [Geometry((Block(1.8, 0.0, 0), Block(0.6, 0.7, 1)))]
    first = StabilityModel("default", device="cpu").probabilities(tower)
    kept = list((tmp_path / "overhang_framework" / "onnx").glob("*.onnx"))
    assert len(exports) == 1 and len(kept) == 1
    monkeypatch.setattr(cnn_model, "_ONNX_MODELS", {})  # as a new process
    monkeypatch.setattr(cnn_model, "_ONNX_SHARED", {})
    np.testing.assert_array_equal(StabilityModel("default", device="cpu").probabilities(tower), first)
    assert len(exports) == 1
    kept[0].write_bytes(b"not a model")  # a damaged file is exported again and replaced
    monkeypatch.setattr(cnn_model, "_ONNX_MODELS", {})
    monkeypatch.setattr(cnn_model, "_ONNX_SHARED", {})
    np.testing.assert_array_equal(StabilityModel("default", device="cpu").probabilities(tower), first)
    assert len(exports) == 2 and kept[0].read_bytes() != b"not a model"


def test_bad_inference_settings_are_refused():
    world = static_world()
    with pytest.raises(ConfigError, match="runtime must be one of onnxruntime, torch, got 'tensorrt'"):
        Registry().create("predictor", {"name": "cnn", "runtime": "tensorrt"}, world=world)
    with pytest.raises(ConfigError, match="fused must be true or false, got 'yes'"):
        Registry().create("predictor", {"name": "cnn", "fused": "yes"}, world=world)


@pytest.mark.slow
def test_the_fit_benchmark_compares_the_tables_with_the_code_before_and_as_a_fit_computes_them(capsys, tmp_path):
    from overhang_framework.bench import fit

    # the hybrid's reference is the code before for both its parts: the IPE's objects and the unfused CNN
    assert fit.main(["--scale", "0.02", "--states", "4", "--depths", "2", "--families", "hybrid", "--compare",
                     "--trials", "0", "--world", "world.physics=static", "--json", str(tmp_path / "b.json")]) == 0
    out = capsys.readouterr().out
    assert "before:" in out and "x faster; scores differ by at most" in out
    assert "the same best action in 4 of 4 tables" in out
    assert "in a fit: the hybrid's 6 switch points together" in out
    row = json.loads((tmp_path / "b.json").read_text())["tables"][0]
    assert row["max_score_difference"] < 1e-4
    in_fit = row["in_fit"]
    # every switch point the paper's tasks allow (2 to 7); at depth 2 at most one of a state's tables is neither
    # the CNN's nor the IPE's, so the others are not computed again
    assert in_fit["switch_points"] == 6 and in_fit["states"] == 4
    assert in_fit["computed_per_state"] <= 1
    # the same numbers as the model's table computed alone, in states where its IPE judges some towers too
    assert in_fit["states_compared"] == 4 and in_fit["states_with_early_part"] >= 1
    assert in_fit["max_score_difference"] < 1e-4


def test_the_fit_benchmark_names_an_unknown_space_in_one_line(capsys):
    from overhang_framework.bench import fit

    from overhang_framework.config import group_options

    spaces = group_options("space")
    assert {"default", "explanations"} <= set(spaces)
    for bad in ("nope", "default,explanations", "null"):
        assert fit.main(["--space", bad, "--states", "1"]) == 2
        assert capsys.readouterr().err == f"error: --space: unknown space {bad!r}; available: {', '.join(spaces)}\n"


def test_mirror_settings_parse_from_words_and_booleans():
    from overhang_framework.cnn.model import parse_mirror

    assert [parse_mirror(v) for v in ("auto", "true", "False", " TRUE ", True, False)] == \
        ["auto", True, False, True, True, False]
    for bad in ("sometimes", 1, None):
        with pytest.raises(ValueError, match="mirror must be auto, true or false"):
            parse_mirror(bad)


def test_bad_cnn_settings_are_refused():
    world = static_world()
    with pytest.raises(ConfigError, match="no CNN checkpoint at"):
        Registry().create("predictor", {"name": "cnn", "checkpoint": "/nonexistent/model.pt"}, world=world)
    with pytest.raises(ConfigError, match="device must be auto, cpu, cuda"):
        Registry().create("predictor", {"name": "cnn", "device": "abacus"}, world=world)
    with pytest.raises(ConfigError, match="cache_size must be"):
        Registry().create("predictor", {"name": "cnn", "cache_size": -1}, world=world)
    with pytest.raises(ConfigError, match="mirror must be auto, true or false, got 'sometimes'"):
        Registry().create("predictor", {"name": "cnn", "mirror": "sometimes"}, world=world)


@pytest.mark.slow
def test_evaluate_app_prints_one_json_line(tmp_path):
    out = subprocess.run([sys.executable, "-m", "overhang_framework.cnn.evaluate", "n=200", "shard_size=100",
                          "workers=1", f"data_dir={tmp_path}", "progress=false", "mirror=true"],
                         cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert {"accuracy", "accuracy_near_critical", "n", "images_per_s", "towers_per_s"} <= set(result)
    assert result["mirror"] is True and result["images_per_s"] == pytest.approx(2 * result["towers_per_s"])
    assert result["n"] > 0 and 0 <= result["accuracy"] <= 1


def test_evaluate_app_refuses_the_training_seed():
    out = subprocess.run([sys.executable, "-m", "overhang_framework.cnn.evaluate", "seed=0"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and "seed 0 is the seed of the checkpoint's training data" in out.stderr


def test_evaluate_app_explains_itself(capsys):
    from overhang_framework.cnn import evaluate

    evaluate.main(["--help"])
    text = capsys.readouterr().out
    assert text.startswith("Score a CNN checkpoint") and "seed=1000" in text and "mirror=auto" in text
    with pytest.raises(SystemExit) as stop:
        evaluate.main(["sead=3"])
    assert stop.value.code == 2 and "bad argument 'sead=3'" in capsys.readouterr().err


def test_bench_prints_towers_and_images_per_second(capsys):
    from overhang_framework.cnn import bench

    both = bench.main(["--threads", "1", "--batches", "16", "--images", "40", "--mirror", "true"])
    one = bench.main(["--threads", "1", "--batches", "16", "--images", "40", "--mirror", "false",
                      "--inference", "unfused"])
    assert both["mirror"] is True and one["mirror"] is False
    assert both["inference"] == "onnxruntime" and one["inference"] == "unfused"
    rate = both["render_and_forward"]["threads=1,batch=16"]
    assert rate["images_per_s"] == pytest.approx(2 * rate["towers_per_s"])
    plain = one["predict_legal_actions"]["threads=1"]
    assert plain["images_per_s"] == pytest.approx(plain["towers_per_s"]) and plain["actions_per_call"] > 1
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["mirror"] is False


def test_bench_measures_the_default_setting_beside_others_with_a_busy_core(capsys):
    from overhang_framework.cnn import bench

    out = bench.main(["--threads", "default,2", "--batches", "16", "--images", "20", "--busy", "1"])
    assert out["busy"] == 1
    assert set(out["predict_legal_actions"]) == {"threads=default (1)", "threads=2"}
    assert "threads=default (1),batch=16" in out["render_and_forward"]
    assert "1 other process busy on a core each" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="--threads takes 'default' or whole numbers >= 1, got 'two'"):
        bench.main(["--threads", "two"])


@pytest.mark.parametrize("overrides", [["predictor=cnn"], ["predictor=hybrid"]])
def test_the_cnn_runs_on_one_torch_thread_by_default(overrides):
    """Two threads collapse when another job holds a core; the default must be the setting that never does."""
    import torch

    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        predictor = build_models(compose_config([*overrides, "world.physics=static"]))["predictor"]
        assert torch.get_num_threads() == 1
        network = getattr(predictor, "late", predictor).model.net  # ONNX Runtime's threads too
        assert network.session.get_session_options().intra_op_num_threads == 1
        torch.set_num_threads(2)
        build_models(compose_config([*overrides, "world.physics=static", "predictor.threads=null"]
                                    if overrides == ["predictor=cnn"] else
                                    [*overrides, "world.physics=static", "+predictor.late_params.threads=2"]))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_the_cnn_can_be_made_over_or_underconfident_on_the_logit_scale():
    world = static_world()
    state = State(Geometry((Block(1.8, 0.0, 0),)), (1.2,))
    actions = world.legal_actions(state)
    made = {kw: Registry().create("predictor", {"name": "cnn", "device": "cpu", **dict(kw)}, world=world)
            for kw in [(), (("bias", 2.0),), (("temperature", 0.5),), (("temperature", 2.0),)]}
    p = {kw: pred.predict(state, actions, np.random.default_rng(0)) for kw, pred in made.items()}
    plain = p[()]
    logit = np.log(np.clip(plain, 1e-9, 1 - 1e-9)) - np.log1p(-np.clip(plain, 1e-9, 1 - 1e-9))
    np.testing.assert_allclose(p[(("bias", 2.0),)], 1 / (1 + np.exp(-(logit + 2.0))), rtol=1e-9)
    assert np.all(p[(("bias", 2.0),)] >= plain) and np.any(p[(("bias", 2.0),)] > plain + 0.05)
    sharp, flat = p[(("temperature", 0.5),)], p[(("temperature", 2.0),)]
    assert np.all(np.abs(sharp - 0.5) >= np.abs(plain - 0.5) - 1e-12)  # overconfident: further from 0.5
    assert np.all(np.abs(flat - 0.5) <= np.abs(plain - 0.5) + 1e-12)
    # the cache keeps the network's own answers: a second call with a hit gives the same calibrated answer
    biased = made[(("bias", 2.0),)]
    np.testing.assert_allclose(biased.predict(state, actions, np.random.default_rng(1)), p[(("bias", 2.0),)])
    for bad, allowed in (({"temperature": 0}, "temperature must be a number > 0"),
                         ({"bias": "high"}, "bias must be a finite number")):
        with pytest.raises(ConfigError, match=allowed):
            Registry().create("predictor", {"name": "cnn", "device": "cpu", **bad}, world=world)


# ------------------------------------------------------------------ torch and torchvision that do not match

def test_the_matching_torchvision_is_named_with_its_platform():
    from overhang_framework.cnn.model import matching_torchvision

    assert matching_torchvision("2.14.1+cpu", None) == (
        "pip install torch==2.14.1+cpu torchvision==0.29.1+cpu, with the --index-url that PyTorch's install page "
        "gives for cpu")
    assert matching_torchvision("2.7.0", "12.6").startswith(
        "pip install torch==2.7.0+cu126 torchvision==0.22.0+cu126, with the --index-url that PyTorch's install "
        "page gives for cu126")
    assert "--force-reinstall torch torchvision, with" in matching_torchvision("3.0.0", None)  # no known pairing


def test_a_torchvision_that_does_not_load_is_one_error_checked_once(monkeypatch):
    import overhang_framework.cnn.model as model

    model._torch_problem.cache_clear()
    # its import fails, as a CUDA build's does beside a CPU torch
    monkeypatch.setitem(sys.modules, "torchvision", None)
    try:
        with pytest.raises(ConfigError, match=r"^torchvision [\d.]+\S* does not work with torch [\d.]+\S* "
                                              r"\((ModuleNotFound|Import)Error: .*\); install the pair that "
                                              r"matches: pip install torch==\S+ torchvision==\S+, with the "
                                              r"--index-url that PyTorch's install page gives for "):
            StabilityModel("default", device="cpu")
        monkeypatch.delitem(sys.modules, "torchvision")
        with pytest.raises(ConfigError, match="does not work with torch"):  # the answer is kept for the process
            model.check_torch()
    finally:
        model._torch_problem.cache_clear()
    model.check_torch()


MISMATCH_COMMANDS = {
    "predictor=cnn": ["-m", "overhang_framework", "predictor=cnn", "tasks=custom", "tasks.sequences=[[1.2,0.6]]",
                      "world.physics=static", "progress=false", "hydra.run.dir={tmp}/run"],
    "predictor=hybrid": ["-m", "overhang_framework", "predictor=hybrid", "tasks=custom",
                         "tasks.sequences=[[1.2,0.6]]", "world.physics=static", "progress=false",
                         "hydra.run.dir={tmp}/run"],
    "analyze": ["-m", "overhang_framework.analyze", "{log}", "--out", "{tmp}/out", "--world", "world.physics=static",
                "--only", "prediction", "--predictors", "cnn", "--quiet"],
    "fit": ["-m", "overhang_framework.fit", "{log}", "--out", "{tmp}/out", "depths=[1]"],
}


# about 6 s each: the main command's case runs in the default suite, the others with the slow tests
@pytest.mark.parametrize("command", [c if c == "predictor=cnn" else pytest.param(c, marks=pytest.mark.slow)
                                     for c in MISMATCH_COMMANDS])
def test_a_torchvision_built_for_another_torch_stops_each_command_in_one_line(tmp_path, command):
    import os

    from overhang_framework.behaviour.log import write_log

    fake = tmp_path / "site" / "torchvision"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text('raise RuntimeError("operator torchvision::nms does not exist")\n')
    log = tmp_path / "log.jsonl"
    write_log([{"log_version": 1, "participant": "p", "condition": "unconstrained", "task_id": "t",
                "sequence": [1.2, 0.6], "trial": 1, "step": 1, "width": 0.6, "x": 0.0, "layer": 1,
                "tower_before": [[1.2, 0.0, 0]], "stable": True, "overhang": 0.6, "reward": 0.6,
                "decision_time": 1.0, "timed_out": False, "source": "human"}], log)
    args = [a.format(tmp=tmp_path, log=log) for a in MISMATCH_COMMANDS[command]]
    env = dict(os.environ, PYTHONPATH=str(tmp_path / "site"))
    proc = subprocess.run([sys.executable, *args], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert proc.returncode == 2, proc.stderr[-2000:]
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith("error: torchvision ") and "does not work with torch" in line
    assert "RuntimeError: operator torchvision::nms does not exist" in line and " torchvision==0." in line
    assert not (tmp_path / "out").exists()


def test_the_readmes_cpu_install_pins_a_matching_pair():
    import re

    from overhang_framework.cnn.model import matching_torchvision

    readme = (ROOT / "README.md").read_text()
    (pair,) = re.findall(r"pip install torch==(\S+) torchvision==(\S+) --index-url URL", readme)
    torch_version, torchvision_version = pair
    assert f"torchvision=={torchvision_version}+cpu" in matching_torchvision(torch_version, None)


def test_networks_built_at_once_in_threads_export_one_at_a_time_and_once(tmp_path, monkeypatch):
    """A pilot's concurrent participants each build the CNN: torch.export is not thread-safe, so exports wait for
    each other, and the threads that waited take the model the first one exported."""
    import threading
    import time

    import torch

    from overhang_framework.cnn import model as cnn_model

    net = torch.nn.Sequential(torch.nn.Conv2d(1, 2, 3), torch.nn.Flatten(), torch.nn.Linear(2 * 6 * 6, 1)).eval()
    exported = cnn_model.export_onnx(net, (1, 8, 8))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(cnn_model, "_ONNX_MODELS", {})
    inside, most, calls = [0], [0], []

    def slow_export(*args):
        inside[0] += 1
        most[0] = max(most[0], inside[0])
        calls.append(1)
        time.sleep(0.3)
        inside[0] -= 1
        return exported

    monkeypatch.setattr(cnn_model, "export_onnx", slow_export)
    built, errors = [], []

    def build(key):
        try:
            built.append(cnn_model.onnx_network(net, (1, 8, 8), 1, key))
        except Exception as err:  # noqa: BLE001 (a thread's error is the test's)
            errors.append(err)

    threads = [threading.Thread(target=build, args=("k" if i % 2 else None,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(built) == 8
    assert most[0] == 1  # never two exports at once
    assert len(calls) == 1 + 4  # the keyed network once, the four without a key each time
    images = np.zeros((3, 1, 8, 8), dtype=np.float32)
    expected = net(torch.from_numpy(images)).detach().numpy()
    for network in built:
        np.testing.assert_allclose(np.asarray(network(images)).reshape(expected.shape), expected, rtol=1e-5, atol=1e-6)


def test_networks_built_at_once_in_threads_are_built_one_at_a_time_and_shared(tmp_path, monkeypatch):
    """A pilot's participants build their CNN predictors in threads at the same moment: torch.fx's folding and
    torch.export patch torch while they trace, so the builds take turns, and the exported network is built once
    and shared (each thread's predictor scores as one built alone)."""
    import threading

    from overhang_framework.cnn import model as cnn_model

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(cnn_model, "_ONNX_MODELS", {})
    monkeypatch.setattr(cnn_model, "_ONNX_SHARED", {})
    inside, most, folds = [0], [0], []
    original = cnn_model.fold_batch_norm

    def watched(net):
        inside[0] += 1
        most[0] = max(most[0], inside[0])
        folds.append(1)
        try:
            return original(net)
        finally:
            inside[0] -= 1

    monkeypatch.setattr(cnn_model, "fold_batch_norm", watched)
    built, errors = [], []
    gate = threading.Barrier(4)

    def build():
        try:
            gate.wait()
            built.append(StabilityModel("default", device="cpu"))
        except Exception as err:  # noqa: BLE001 (a thread's error is the test's)
            errors.append(err)

    threads = [threading.Thread(target=build) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(built) == 4
    assert most[0] == 1 and len(folds) == 1  # one build, the others waited for it
    assert len({id(m.net) for m in built}) == 1 and {m.folded for m in built} == {built[0].folded}
    tower = [Geometry((Block(1.8, 0.0, 0), Block(0.6, 0.7, 1)))]
    monkeypatch.setattr(cnn_model, "_ONNX_SHARED", {})
    alone = StabilityModel("default", device="cpu").probabilities(tower)
    for m in built:
        np.testing.assert_array_equal(m.probabilities(tower), alone)
