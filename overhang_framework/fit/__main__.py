"""Model fitting: ``python -m overhang_framework.fit LOG [LOG ...] --out DIR [OVERRIDES ...]``.

Fits every model of the model space (``conf/space/default.yaml`` through ``conf/fit.yaml``: predictor
families x depths; ``space=explanations`` for the explanations of people's errors, docs/people.md) to
every participant of the behaviour logs, and to each condition pooled, and writes into ``DIR``:
``fits.csv`` (one row per participant x model: parameters, log-likelihood, k, n, BIC, AIC),
``comparison.md`` / ``comparison.csv`` / ``comparison.png`` (what was found, in
sentences; winners, summed BIC, random-effects BMS, parameters between conditions;
for simulated participants their true models and parameters beside the fitted ones,
from the ``participants.csv`` next to the log or ``--truth CSV``) and ``fit.json``
(what was fitted: each log's path and the SHA-256 of its bytes, the models, the world).
``cv=K`` also fits each model on K - 1 of K folds of each participant's trials
and scores the fold left out: ``fits.csv`` gets the held-out log-likelihood, and ``comparison.md``
sets the winners by it beside those by BIC. Hydra overrides choose the model space (``depths=[1,2,3]``,
``models.ipe.sigma=[0.02,0.04]``, ``models.hybrid.switch=4``, ``~models.cnn``); ``-m shard=0,1,2,3 shards=4``
spreads the participants over the jobs of a multirun (any launcher), which share
the score cache and leave one ``fits.csv``. docs/fitting.md describes it all.

Examples::

    python -m overhang_framework.fit runs/sim/log.jsonl --out runs/sim/fit
    python -m overhang_framework.fit runs/sim/log.jsonl --out runs/sim/fit '~models.hybrid' depths=[1,2,3]
    python -m overhang_framework.fit runs/sim/log.jsonl --out runs/sim/fit_cv cv=5
    python -m overhang_framework.fit runs/sim/log.jsonl --out runs/sim/explained space=explanations
    python -m overhang_framework.fit runs/sim/log.jsonl --out runs/sim/fit -m shard=0,1 shards=2 \\
        hydra/launcher=joblib hydra.launcher.n_jobs=2
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from overhang_framework.config import CONFIG_PATH, enable_plugin_configs
from overhang_framework.errors import ConfigError, OverhangError, closest

enable_plugin_configs()
log = logging.getLogger("overhang_framework.fit")
CONFIG_NAME = "fit"
TOP = ("world", "value", "logs", "out", "models", "depths", "cache", "shard", "shards", "pooled", "progress",
       "states", "jobs", "truth", "cv", "motor")


def _plain(node) -> Any:
    return OmegaConf.to_container(node, resolve=True) if node is not None else None


def _whole(cfg, key: str, minimum: int) -> int:
    value = cfg.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ConfigError(f"{key} must be a whole number >= {minimum}, got {value!r}")
    return value


def check_settings(cfg: DictConfig) -> dict:
    """Every value of ``cfg`` checked that can be without reading the logs (a command before its logs exist)."""
    from overhang_framework.fit.space import model_space
    from overhang_framework.preflight import check_writable

    extra = [k for k in cfg if k not in TOP and k != "hydra"]
    if extra:
        close = closest(str(extra[0]), TOP)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise ConfigError(f"unknown config key '{extra[0]}'{hint}; top-level keys: {', '.join(sorted(TOP))}")
    logs = _plain(cfg.logs) or []
    if not logs:
        raise ConfigError("no behaviour log given: python -m overhang_framework.fit LOG [LOG ...] --out DIR")
    if not cfg.get("out"):
        raise ConfigError("no results directory given: add --out DIR")
    check_writable(cfg.out, "--out DIR")
    shard, shards = _whole(cfg, "shard", 0), _whole(cfg, "shards", 1)
    _whole(cfg, "jobs", 1)
    cv = cfg.get("cv")
    if isinstance(cv, bool) or not isinstance(cv, int) or cv < 0 or cv == 1:
        raise ConfigError(f"cv must be 0 (no cross-validation) or a number of folds >= 2, got {cv!r}")
    if shard >= shards:
        raise ConfigError(f"shard must be from 0 to shards - 1 = {shards - 1}, got {shard}")
    for key in ("pooled", "progress"):
        if not isinstance(cfg.get(key), bool):
            raise ConfigError(f"{key} must be true or false, got {cfg.get(key)!r}")
    from overhang_framework.fit.fitting import STATES

    if cfg.get("states") not in STATES:
        raise ConfigError(f"states must be one of {', '.join(STATES)}, got {cfg.get('states')!r}")
    from overhang_framework.fit.motor import Motor

    motor = Motor.from_config(_plain(cfg.get("motor")))
    if motor is not None and cfg.get("states") != "logged":
        raise ConfigError("motor needs states=logged: a placement's x is where it went on the logged tower, which "
                          "a grid replay does not keep")
    depths = _plain(cfg.depths)
    if not isinstance(depths, list):
        depths = [depths]
    model_space(_plain(cfg.models) or {}, depths, check_only=True)  # a bad setting stops the command here
    return {"logs": logs, "depths": depths, "shard": shard, "shards": shards, "motor": motor}


def check_config(cfg: DictConfig) -> dict:
    """Every value of ``cfg`` checked, the logs read and the models built (nothing fitted)."""
    from overhang_framework.behaviour.log import read_log, require_records
    from overhang_framework.fit.compare import read_truth
    from overhang_framework.fit.space import model_space
    from overhang_framework.plugins import Registry

    checked = check_settings(cfg)
    logs, depths, shard, shards, motor = (checked[k] for k in ("logs", "depths", "shard", "shards", "motor"))
    truth = truth_files(_plain(cfg.get("truth")), logs)
    read_truth(truth, {})  # a file that is not a participants.csv stops the command here
    df = require_records(read_log([str(p) for p in logs]), logs)
    blocks = max((len(s) for s in df["sequence"]), default=None) if len(df) else None
    space = model_space(_plain(cfg.models) or {}, depths, blocks)
    registry = Registry()
    world = registry.create("world", _plain(cfg.world))
    value = registry.create("value", _plain(cfg.value), world=world)
    built = set()
    for index in space:  # a setting a predictor refuses stops the command here
        for model in index.variants:
            if repr(sorted(model.predictor.items())) not in built:
                built.add(repr(sorted(model.predictor.items())))
                registry.create("predictor", dict(model.predictor), world=world)
    return {"df": df, "space": space, "world": world, "value": value, "registry": registry, "shard": shard,
            "shards": shards, "logs": [str(Path(p).resolve()) for p in logs], "truth": truth, "motor": motor}


def model_entry(model, predictor: Mapping) -> list:
    """A model as fit.json lists it: its label and predictor config, and its risk and percept when it has them."""
    entry = [model.label, predictor]
    extra = {}
    if model.risk:
        extra.update(risk=model.risk, risk_form=model.risk_form)
    if model.percept:
        extra.update(percept=model.percept)
    if extra:
        entry.append(extra)
    return entry


def truth_files(truth: Any, logs: Sequence[str]) -> list[Path]:
    """The ``participants.csv`` files that hold the simulated participants' true parameters: ``truth``
    (a path or a list of them), or when it is null the one next to each log that has one."""
    from overhang_framework.fit.compare import TRUTH

    if truth is None:
        return [Path(p).parent / TRUTH for p in logs if (Path(p).parent / TRUTH).is_file()]
    paths = truth if isinstance(truth, list) else [truth]
    if not paths or not all(isinstance(p, str) and p for p in paths):
        raise ConfigError(f"truth must be a participants.csv file, a list of them, or null (the one next to each "
                          f"log), got {truth!r}")
    for p in paths:
        if not Path(p).is_file():
            raise ConfigError(f"truth: no file {p} (the participants.csv the participants command writes next "
                              "to its log.jsonl)")
    return [Path(p) for p in paths]


def run(cfg: DictConfig) -> dict:
    """Fit this job's share of the units; write its part, and the aggregate when every part is there."""
    from overhang_framework.fit.compare import comparison, read_truth
    from overhang_framework.fit import adequacy
    from overhang_framework.fit.fitting import log_placements
    from overhang_framework.fit.run import (FitJournal, Predictors, aggregate, check_directory, fit_units,
                                            journal_path, log_hashes, logs_digest, shard_units, units_of,
                                            write_part)
    from overhang_framework.fit.scores import ENGINE_KEYS, ScoreCache, _strip
    from overhang_framework.progress import progress_bar

    # hashed before they are read: a log that changes in between is recorded as it was, and refused next time
    hashes = log_hashes(_plain(cfg.logs) or [])
    checked = check_config(cfg)
    out = Path(cfg.out)
    world, value, space = checked["world"], checked["value"], checked["space"]
    context = {"world": _plain(cfg.world), "value": _plain(cfg.value)}
    # the models as their tables are keyed: settings of how they are computed (ENGINE_KEYS) left out
    description = {"logs": checked["logs"], "log_sha256": hashes,
                   "models": [model_entry(m, _strip(dict(m.predictor), ENGINE_KEYS)) for i in space for m in i.variants],
                   "context": context, "pooled": cfg.pooled, "shards": checked["shards"],
                   "states": cfg.states, "cv": cfg.cv}
    if checked["motor"] is not None:  # a fit without one keeps the description it had
        description["motor"] = checked["motor"].describe()
    check_directory(out, description)
    units = units_of(log_placements(checked["df"]), cfg.pooled)
    shards = shard_units(units, checked["shards"])  # every job's: jobs sharing a cache split the tables they need
    mine = shards[checked["shard"]]
    cache = ScoreCache(cfg.cache)
    build = Predictors(checked["registry"], world)
    journal = FitJournal(journal_path(out, checked["shard"], checked["shards"]), logs_digest(hashes))

    bar = progress_bar(total=len(mine) * len(space), desc="fits", unit="fit", disable=not cfg.progress,
                       miniters=1, mininterval=0.5, dynamic_ncols=True)
    table_bar = progress_bar(desc="score tables", unit="table", disable=not cfg.progress,
                             miniters=1, mininterval=0.5, dynamic_ncols=True)

    def set_total(n):
        table_bar.total = n
        table_bar.refresh()

    def on_unit(label, unit):
        bar.set_postfix_str(f"{label} {unit.name}")
        bar.update(1)

    try:
        result = fit_units(mine, world, value, context, space, cache, build, on_unit, cfg.states, cfg.jobs,
                           lambda: table_bar.update(1), set_total, cfg.cv, journal,
                           shards, checked["shard"], checked["motor"])
    finally:
        table_bar.close()
        bar.close()
        cache.close()
    part = write_part(out, checked["shard"], checked["shards"], result.fits)
    journal.remove()
    fits = aggregate(out, checked["shards"])
    if fits is not None:
        families = {i.family: str(i.variants[0].judged_by.get("name")) for i in space}
        truth = read_truth(checked["truth"], families, checked["df"]) if checked["truth"] else None
        try:
            fitness = adequacy.run(out, cfg.cache, progress=cfg.progress, records=checked["df"])
        except OverhangError as err:  # the fits are kept; the comparison is written without the check
            log.warning("whether any model describes the participants was not checked: %s", err)
            print(f"warning: whether any model describes the participants was not checked: {err}", file=sys.stderr)
            fitness = None
        comparison(fits, out, truth=truth, adequacy=fitness,
                   motor=None if checked["motor"] is None else checked["motor"].describe())
    stats = {label: vars(s) for label, s in result.stats.items()}
    log.info("fitted %d units x %d models in %.1f s: %s", len(mine), len(space), result.seconds, stats)
    return {"part": str(part), "complete": fits is not None, "seconds": result.seconds, "tables": stats,
            "units": len(mine), "models": len(space), "resumed": result.resumed}


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name=CONFIG_NAME)
def app(cfg: DictConfig) -> Optional[dict]:
    from overhang_framework.preflight import job_result

    summary = job_result(lambda: run(cfg), lambda: f"interrupted: the score tables computed so far are kept in "
                         f"{cfg.cache} and the finished fits in {Path(cfg.out) / 'parts'}; run the same command to "
                         "continue from them", log)
    if summary is None:
        return None
    out = Path(cfg.out)
    total = sum(t["computed"] for t in summary["tables"].values())
    cached = sum(t["cached"] for t in summary["tables"].values())
    print(f"{summary['units']} participants and pooled conditions x {summary['models']} models in "
          f"{summary['seconds']:.1f} s ({total} score tables computed, {cached} from the cache"
          + (f"; {summary['resumed']} fits from the journal of a stopped run" if summary["resumed"] else "") + ")")
    if summary["complete"]:
        print(f"wrote {out / 'fits.csv'} and {out / 'comparison.md'}")
    else:
        print(f"wrote {summary['part']}; fits.csv is written when every shard is done")
    return summary


def command_words(args: Sequence[str]) -> list[str]:
    """``LOG ... --out DIR [--truth CSV] OVERRIDES`` as Hydra words: the rest, then ``logs=[...]``,
    ``out=DIR`` and ``truth=[...]``."""
    logs, rest, out, truth = [], [], None, []
    it = iter(args)
    for word in it:
        if word == "--out":
            out = next(it, None)
            if out is None:
                raise ConfigError("--out needs a directory")
        elif word.startswith("--out="):
            out = word.split("=", 1)[1]
        elif word == "--truth" or word.startswith("--truth="):
            path = next(it, None) if word == "--truth" else word.split("=", 1)[1]
            if not path:
                raise ConfigError("--truth needs a participants.csv file")
            truth.append(str(Path(path).resolve()))
        elif word.startswith("-") or "=" in word or word.startswith("~") or word.startswith("+"):
            rest.append(word)
        else:
            logs.append(word)
    words = list(rest)
    if logs:
        quoted = ",".join("'" + str(Path(p).resolve()).replace("'", "\\'") + "'" for p in logs)
        words.append(f"logs=[{quoted}]")
    if out is not None:
        words.append(f"out='{Path(out).resolve()}'")
    if truth:
        quoted = ",".join("'" + p.replace("'", "\\'") + "'" for p in truth)
        words.append(f"truth=[{quoted}]")
    return words


def preflight(words: Sequence[str]) -> None:
    from overhang_framework.preflight import check_flags, compose_checked, split_flags, sweep_variants

    check_flags(words)
    flags, overrides = split_flags(words)
    for variant in sweep_variants(overrides, "-m" in flags or "--multirun" in flags):
        check_config(compose_checked(variant, config_name=CONFIG_NAME))


def main(argv: Optional[Sequence[str]] = None) -> None:
    from overhang_framework.preflight import run_app_command

    run_app_command(argv, app, None, None, __doc__, check=preflight, words=command_words)


if __name__ == "__main__":
    main()
