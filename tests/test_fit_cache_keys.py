"""Caches keyed by content: a score table's key holds the code's versions, the physics' identity and the CNN's
weights by their bytes; a fit's journal and fit.json know each log by its content, so a log simulated again at
the same path, another physics or another checkpoint under the same name never reuses a table or a fit."""

from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path

import pandas as pd
import pytest

from overhang_framework.errors import OverhangError
from overhang_framework.fit import scores
from overhang_framework.fit.run import FitJournal, log_hashes, logs_digest
from overhang_framework.fit.scores import Model, file_sha256

CONTEXT = {"world": {"name": "overhang", "physics": "static"}, "value": {"name": "overhang"}}
IPE = {"name": "ipe", "K": 10, "sigma": 0.03}
FIT = ["world.physics=static", "~models.cnn", "~models.hybrid", "models.ipe.K=10", "models.ipe.sigma=[0.03]",
       "depths=[1]", "progress=false", "pooled=false"]


def _fit(log: Path, out: Path, cache: Path) -> dict:
    """The fit command's run, in this process."""
    from overhang_framework.config import compose_config
    from overhang_framework.fit.__main__ import CONFIG_NAME, command_words, run

    return run(compose_config([*command_words([str(log), "--out", str(out)]), *FIT, f"cache={cache}"],
                              config_name=CONFIG_NAME))


def _simulate(where: Path, sequences: str) -> Path:
    from search_fixtures import simulated_log

    shutil.rmtree(where, ignore_errors=True)
    return simulated_log(where, sequences)


def test_a_log_simulated_again_at_the_same_path_is_never_given_the_old_fits(tmp_path, monkeypatch):
    sim, cache = tmp_path / "sim", tmp_path / "scores.sqlite"
    log = _simulate(sim, "[[1.2,0.6,1.2],[0.6,1.2,0.6]]")
    old_hash = file_sha256(log)
    # the old log's fit, its journal kept as a stopped run would leave it
    monkeypatch.setattr(FitJournal, "remove", lambda self: None)
    first = tmp_path / "first"
    _fit(log, first, cache)
    old_journal = first / "parts" / "shard-0-of-1.fits.jsonl"
    old_fits = pd.read_csv(first / "fits.csv")
    assert old_journal.read_text().count("\n") == len(old_fits) == 4
    monkeypatch.undo()

    again = _simulate(sim, "[[1.8,0.6,0.6],[0.6,0.6,1.2]]")  # the same path, other tasks: other content
    assert again == log and file_sha256(log) != old_hash
    # the old fits' directory refuses the changed log in one line that names it and says what to do
    with pytest.raises(OverhangError) as err:
        _fit(log, first, cache)
    message = str(err.value)
    assert "\n" not in message and f"holds fits of {log} as it was before it changed" in message
    assert "use another --out" in message
    pd.testing.assert_frame_equal(pd.read_csv(first / "fits.csv"), old_fits)

    # a directory holding only the old log's journal (no fit.json): none of its fits is taken
    second = tmp_path / "second"
    (second / "parts").mkdir(parents=True)
    shutil.copy(old_journal, second / "parts" / old_journal.name)
    result = _fit(log, second, cache)
    assert result["resumed"] == 0
    new_fits = pd.read_csv(second / "fits.csv")
    assert not new_fits["loglik"].isin(old_fits["loglik"]).any()
    # the same content fitted afresh: the same fits, every table from the cache
    third = _fit(log, tmp_path / "third", cache)
    assert sum(t["computed"] for t in third["tables"].values()) == 0
    pd.testing.assert_frame_equal(new_fits, pd.read_csv(tmp_path / "third" / "fits.csv"))


def test_a_journal_takes_only_fits_of_the_logs_content_it_was_written_for(tmp_path):
    from overhang_framework.fit.fitting import ModelFit

    fit = ModelFit("p1", "time_limited", "ipe/myopic", "ipe", 1, 0.03, 2.0, 0.05, -12.5, 3, 20, 0)
    path = tmp_path / "journal.jsonl"
    logs = tmp_path / "a.jsonl"
    logs.write_text('{"x": 1}\n')
    digest = logs_digest(log_hashes([logs]))
    FitJournal(path, digest).add(fit)
    assert FitJournal(path, digest).get(fit.label, fit.participant) == fit
    logs.write_text('{"x": 2}\n')
    assert FitJournal(path, logs_digest(log_hashes([logs]))).get(fit.label, fit.participant) is None
    # a line without the logs' digest (a journal of an earlier version) is not taken either
    path.write_text(__import__("json").dumps(dataclasses.asdict(fit)) + "\n")
    assert FitJournal(path, digest).get(fit.label, fit.participant) is None


def test_a_fit_json_without_log_hashes_is_refused_in_one_line(tmp_path):
    import json

    from overhang_framework.fit.run import check_directory

    description = {"logs": ["/x/log.jsonl"], "log_sha256": ["ab"], "models": [], "context": {}, "states": "logged",
                   "cv": 0}
    (tmp_path / "fit.json").write_text(json.dumps({k: v for k, v in description.items() if k != "log_sha256"}))
    with pytest.raises(OverhangError, match="does not record") as err:
        check_directory(tmp_path, description)
    assert "\n" not in str(err.value)
    (tmp_path / "fit.json").unlink()
    check_directory(tmp_path, description)
    check_directory(tmp_path, description)  # the same logs' content: accepted
    with pytest.raises(OverhangError, match=r"holds fits of /x/log.jsonl as it was before it changed"):
        check_directory(tmp_path, {**description, "log_sha256": ["cd"]})


def test_another_physics_gives_another_table_key(monkeypatch):
    model = Model(IPE, 2)
    key = model.key(CONTEXT)
    assert key == Model(dict(IPE), 2).key({k: dict(v) for k, v in CONTEXT.items()})  # the same: the same key
    # a world setting of the static backend the IPE simulates on, and the world's physics itself
    assert model.key({**CONTEXT, "world": {**CONTEXT["world"], "static": {"margin": 0.002}}}) != key
    assert model.key({**CONTEXT, "world": {**CONTEXT["world"], "physics": "tiered"}}) != key
    # the IPE's own override of its backend's parameters
    assert Model({**IPE, "backend_params": {"friction_scale": 0.7}}, 2).key(CONTEXT) != key
    # the same config, but a backend's default changed in the code: another physics, another key
    from overhang_framework.physics import factory

    original = factory.backend_params

    def other_default(name, **params):
        return original(name, **({"friction_scale": 0.7, **params} if name == "static" else params))

    monkeypatch.setattr(factory, "backend_params", other_default)
    scores._physics.cache_clear()
    try:
        assert model.key(CONTEXT) != key
    finally:
        monkeypatch.undo()
        scores._physics.cache_clear()
    assert model.key(CONTEXT) == key


def test_another_version_of_the_code_or_of_a_predictors_plugin_gives_another_key(monkeypatch):
    model = Model(IPE, 1)
    key = model.key(CONTEXT)
    assert scores.code_identity(IPE)["plugins"]["ipe"].startswith("overhang-framework ")
    monkeypatch.setattr(scores, "SCORES_VERSION", scores.SCORES_VERSION + 1)
    assert model.key(CONTEXT) != key
    monkeypatch.undo()
    monkeypatch.setattr("overhang_framework.version.version", lambda: "99.0")
    assert model.key(CONTEXT) != key
    monkeypatch.undo()
    monkeypatch.setattr(scores, "_distribution", lambda name: "overhang-framework 99.0")
    assert model.key(CONTEXT) != key
    monkeypatch.undo()
    assert model.key(CONTEXT) == key


def _write(path: Path, data: bytes) -> None:
    """``data`` into ``path`` as a new file in its place (as a checkpoint written again would be)."""
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def test_another_checkpoint_under_the_same_name_gives_another_key_and_the_same_bytes_the_same(tmp_path):
    from overhang_framework.cnn.model import DEFAULT_CHECKPOINT

    weights = DEFAULT_CHECKPOINT.read_bytes()
    net = tmp_path / "net.pt"
    _write(net, weights)
    cnn = Model({"name": "cnn", "checkpoint": str(net)}, 2)
    hybrid = Model({"name": "hybrid", "early": "ipe", "late": "cnn", "switch": 4, "early_params": {"K": 10},
                    "late_params": {"checkpoint": str(net)}}, 2)
    hand = Model(scores.with_hand(hybrid.predictor, 0.02), 2)
    keys = [m.key(CONTEXT) for m in (cnn, hybrid, hand)]
    assert len(set(keys)) == 3
    # the shipped network's bytes at another path: the path is in the key, and so are the bytes, the same
    assert scores.content_identity(cnn.predictor) == scores.content_identity({"name": "cnn"})
    # one byte changed, the same file name: every model that loads it gets another key
    changed = bytearray(weights)
    changed[len(changed) // 2] ^= 0xFF
    _write(net, bytes(changed))
    assert [m.key(CONTEXT) for m in (cnn, hybrid, hand)] == \
        [m.key(CONTEXT) for m in (cnn, hybrid, hand)]  # remembered, and stable
    assert all(m.key(CONTEXT) != k for m, k in zip((cnn, hybrid, hand), keys))
    # the same bytes written again: the same keys, so a warm cache still hits
    _write(net, weights)
    assert [m.key(CONTEXT) for m in (cnn, hybrid, hand)] == keys
    # a hybrid's default late part is the shipped CNN: keyed by its bytes too
    default = Model({"name": "hybrid", "early": "ipe", "late": "cnn", "switch": 4, "early_params": {},
                     "late_params": {}}, 2)
    shipped = file_sha256(DEFAULT_CHECKPOINT)
    assert scores.content_identity(default.predictor) == [["cnn", {"checkpoint_sha256": shipped}]]
