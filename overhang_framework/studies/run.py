"""A study's steps (simulation, analysis, fit, findings, predictive check), each kept with the digest of what it
was made from and continued where it stopped (``steps.json``)."""

from __future__ import annotations

import hashlib
import json
import math
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import pandas as pd

from overhang_framework.errors import ConfigError, OverhangError
from overhang_framework.results import atomic_write_text
from overhang_framework.studies.findings import (ANALYSES, FINDINGS, GRADED, MULTIPLES, PEOPLE, STUDIES,
                                                 TARGET_POWER, diagnostics, evaluate, expected, participant_table,
                                                 power)
from overhang_framework.studies.gather import gather
from overhang_framework.studies.power import replaced
from overhang_framework.studies.report import _check_line, _size, report
from overhang_framework.studies.steps import Steps, _digest


# --- the command ---------------------------------------------------------------------------------------

def _compose(words: Sequence[str], config_name: str, what: str):
    """The config ``config_name`` with ``words``, or a one-line :class:`ConfigError` naming the step."""
    from overhang_framework.config import compose_config

    try:
        return compose_config(list(words), config_name=config_name)
    except OverhangError:
        raise
    except Exception as err:  # Hydra's composition errors: the first line says what is wrong
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"{what}: {first}") from None


def check_settings(study: str, out: Path, scale: float = 1.0, pool: float = 2.0, n_tasks: Optional[int] = None,
                   jobs: int = 1, depths: Sequence[int] = (1, 2), resamples: int = 1000, replicas: int = 39,
                   seed: int = 0, world: Sequence[str] = (), participants: Sequence[str] = (),
                   fit: Sequence[str] = (), progress: bool = True, sims: Sequence[str | Path] = (),
                   logs: Sequence[str | Path] = ()) -> dict:
    """The settings of :func:`run` checked and both its configs (the participants' and the fit's) composed, before
    any work and without writing anything; a one-line :class:`ConfigError` otherwise."""
    from omegaconf import OmegaConf

    if study not in STUDIES:
        raise ConfigError(f"unknown study {study!r}; studies: {', '.join(STUDIES)}")
    if not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale <= 0:
        raise ConfigError(f"--scale must be a number > 0, got {scale!r}")
    if not isinstance(pool, (int, float)) or not math.isfinite(pool) or pool < 1:
        raise ConfigError(f"--pool must be a number >= 1, got {pool!r}")
    for name, value, low in (("--jobs", jobs, 1), ("--resamples", resamples, 0), ("--replicas", replicas, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ConfigError(f"{name} must be a whole number >= {low}, got {value!r}")
    if logs and sims:
        raise ConfigError("--log takes people's data and --sim simulated participants; give one of them")
    if logs and (scale != 1.0 or pool != 2.0 or n_tasks is not None or participants):
        raise ConfigError("--log takes people's data; --scale, --pool, --tasks and --participants are for simulating "
                          "participants: leave them out")
    if sims and (scale != 1.0 or pool != 2.0 or n_tasks is not None or participants):
        raise ConfigError("--sim takes participants already simulated; --scale, --pool, --tasks and --participants "
                          "are for simulating them: leave them out")
    cohort, model, planted = STUDIES[study]
    out = Path(out)
    base = _compose([f"cohort={cohort}"], "participants", "--participants")
    counts = {str(k): int(v) for k, v in OmegaConf.to_container(base.cohort.participants).items()}
    sizes = {k: max(1, round(v * scale)) for k, v in counts.items()}
    simulated = {k: max(n, round(n * pool)) for k, n in sizes.items()}
    words = [f"cohort={cohort}", *model, *world, f"seed={seed}", f"jobs={jobs}", f"progress={str(progress).lower()}",
             *[f"cohort.participants.{k}={n}" for k, n in simulated.items()]]
    if n_tasks is not None:
        words.append(f"cohort.n_tasks={int(n_tasks)}")
    words += list(participants)

    fit_words = [*world, f"jobs={jobs}", f"cache={out / 'scores.sqlite'}", f"progress={str(progress).lower()}",
                 f"depths=[{','.join(str(int(d)) for d in depths)}]", *fit]
    from overhang_framework.behaviour.simulation import CONFIG_NAME

    sim_cfg = _compose(words, CONFIG_NAME, "--participants")  # both configs checked before any work
    fit_cfg = _compose(fit_words, "fit", "--fit")
    from overhang_framework.fit.space import model_space

    try:  # a misspelt model setting is refused now, not after the simulation
        model_space(OmegaConf.to_container(fit_cfg.models, resolve=True) or {}, [int(d) for d in depths],
                    check_only=True)
    except OverhangError as err:
        raise ConfigError(f"--fit: {err}") from None

    return {"cohort": cohort, "model": model, "planted": planted, "base": base, "counts": counts, "sizes": sizes,
            "simulated": simulated, "sim_cfg": sim_cfg, "fit_words": fit_words}


def run(study: str, out: Path, scale: float = 1.0, pool: float = 2.0, n_tasks: Optional[int] = None,
        jobs: int = 1, depths: Sequence[int] = (1, 2), resamples: int = 1000, replicas: int = 39, seed: int = 0,
        world: Sequence[str] = (), participants: Sequence[str] = (), fit: Sequence[str] = (),
        progress: bool = True, say: Callable[[str], None] = lambda s: None, sims: Sequence[str | Path] = (),
        fit_models: bool = True, logs: Sequence[str | Path] = (), command: str = "") -> dict:
    """Run ``study`` into ``out``; see the module docstring. ``sims``: finished simulations of the study's cohort
    (``python -m overhang_framework.participants`` run directories) to take as the participants instead of
    simulating them; ``logs``: behaviour logs of people (an export of the study: JSON Lines, CSV or a Psych-DS
    folder), analysed as the study's participants; ``fit_models`` false leaves out the fit (and the findings that
    need it); ``command``: the command line that ran it, which the graded design's preregistration names."""
    from omegaconf import OmegaConf

    checked = check_settings(study, out, scale, pool, n_tasks, jobs, depths, resamples, replicas, seed, world,
                             participants, fit, progress, sims, logs)
    cohort, model, planted, base, counts, sizes, simulated, sim_cfg, fit_words = (checked[k] for k in (
        "cohort", "model", "planted", "base", "counts", "sizes", "simulated", "sim_cfg", "fit_words"))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    steps = Steps(out)
    started = time.perf_counter()

    # 1. the participants
    from overhang_framework.behaviour.simulation import run as simulate

    t0 = time.perf_counter()
    data = "people" if logs else "sim"
    if logs:
        sizes = take_logs(logs, out / data, study, list(counts))
        simulated = dict(sizes)
        say(f"taking {sum(sizes.values())} people ({', '.join(f'{n} {k}' for k, n in sizes.items())}) from "
            f"{len(logs)} log{'s' * (len(logs) > 1)}")
    elif sims:
        screened: dict[str, int] = {}
        sizes = gather(sims, out / "sim", str(base.cohort.name), list(counts), str(sim_cfg.world.physics),
                       OmegaConf.to_container(sim_cfg, resolve=True), screened)
        simulated = dict(sizes)
        say(f"taking {sum(sizes.values())} participants ({', '.join(f'{n} {k}' for k, n in sizes.items())}) "
            f"from {len(sims)} simulation{'s' * (len(sims) > 1)}"
            + (f"; left out, screened out in the practice: {', '.join(f'{n} {k}' for k, n in screened.items())}"
               if screened else ""))
    else:
        say(f"simulating {sum(simulated.values())} participants "
            f"({', '.join(f'{n} {k}' for k, n in simulated.items())})")
        simulate(sim_cfg, out / "sim")
    log = out / data / "log.jsonl"
    if not steps.seconds("participants") or not steps.current("participants", _digest(log)):
        steps.finish("participants", _digest(log), time.perf_counter() - t0)

    # 2. the analyses a lab runs on people's logs
    from overhang_framework.behaviour.analysis import Settings, run as analyse

    digest = _digest(log, extra={"world": list(world), "seed": seed, "only": list(ANALYSES)})
    if not steps.current("analysis", digest):
        t0 = time.perf_counter()
        say("analysing the log (Table 1, Γ, the flows' lateral extent, Fig. 4)")
        analyse([log], out / "analysis", Settings(world_overrides=tuple(world), seed=seed,
                                                  only=ANALYSES, progress=progress))
        steps.finish("analysis", digest, time.perf_counter() - t0)
    if sims or logs:  # the tasks each did, as the report says it
        n_tasks = int(pd.read_csv(out / "analysis" / "table1_participants.csv")["trials"].max())

    # 3. the fit
    from overhang_framework.fit.__main__ import run as fit_run

    # how the fit runs (its processes, its progress bar) does not change what it finds
    digest = _digest(log, extra=[w for w in fit_words if not w.startswith(("jobs=", "progress="))])
    if not fit_models:  # an earlier fit in ``out`` is kept, and not read
        depths, replicas = (), 0
    elif not steps.current("fit", digest):
        t0 = time.perf_counter()
        say("fitting the models")
        cfg = _compose(fit_words, "fit", "--fit")
        OmegaConf.update(cfg, "logs", [str(log.resolve())])
        OmegaConf.update(cfg, "out", str((out / "fit").resolve()))
        OmegaConf.update(cfg, "truth", None)
        fit_run(cfg)
        steps.finish("fit", digest, time.perf_counter() - t0)

    if study in GRADED:
        return _graded(out, sim_cfg, sizes, steps, resamples, seed, started, fit_models, progress, data, jobs, say,
                       command or f"python -m overhang_framework.study {study} --out {out}")

    # 4. the findings, and their power by resampling participants
    t0 = time.perf_counter()
    pool_people, people = _participants(out, sizes, fit_models, data)
    found = evaluate(people, seed=seed)
    from overhang_framework.progress import progress_bar

    rows = []
    bar = progress_bar(total=resamples, desc="power", unit="study", disable=not progress or not resamples,
                       miniters=1, mininterval=0.5)
    rates = power(pool_people, sizes, resamples, seed, lambda: bar.update(1)) if resamples else {}
    bar.close()
    larger: dict[str, Optional[float]] = {}
    if planted and resamples:
        for f in FINDINGS:
            if f.name in ("stable",) or not rates.get(f.name, 1.0) < TARGET_POWER:
                continue
            larger[f.name] = None
        for multiple in MULTIPLES:
            todo = [n for n, m in larger.items() if m is None]
            if not todo:
                break
            bigger = {k: int(round(n * multiple)) for k, n in sizes.items()}
            r = power(pool_people, bigger, max(50, resamples // 2), seed + int(multiple * 100))
            for name in todo:
                if r[name] >= TARGET_POWER:
                    larger[name] = multiple
    for f in FINDINGS:
        got = found[f.name]
        rows.append({"finding": f.name, "text": f.text, "statistic": got["statistic"], "p": got["p"],
                     "holds": got["holds"], "tested": got.get("tested", True), "expected": expected(f.name, planted),
                     "rate": rates.get(f.name), "size_for_power": _size(larger.get(f.name, "n/a"), sizes),
                     "paper": f.paper})
    table = pd.DataFrame(rows)
    atomic_write_text(out / "findings.csv", table.to_csv(index=False))
    atomic_write_text(out / "power.csv", pd.DataFrame([{"finding": k, "rate": v, "resamples": resamples,
                                                         "sizes": json.dumps(sizes)} for k, v in rates.items()])
                      .to_csv(index=False))
    steps.finish("findings", "", time.perf_counter() - t0)
    why = diagnostics(pool_people)
    atomic_write_text(out / "study.md", report(study, table, steps, sizes, simulated, n_tasks, resamples, planted,
                                               depths, time.perf_counter() - started, replaced(pool_people, sizes),
                                               why=why, people=bool(logs), planned=counts if logs else None))

    # 5. the predictive check of the study's own participants (the findings do not wait for it)
    check_line = None
    if replicas:
        from overhang_framework.fit import check

        own = sorted(people["participant"].astype(str))
        digest = _digest(out / "fit" / "fits.csv", extra={"replicas": replicas, "seed": seed, "participants": own})
        made = out / "fit" / "check" / "check.json"
        if not steps.current("check", digest):
            import shutil

            if made.exists():  # a check of earlier fits, other participants or settings: started afresh
                previous = json.loads(made.read_text())
                now = {"fits": hashlib.sha256((out / "fit" / "fits.csv").read_bytes()).hexdigest(),
                       "participants": own, "replicas": replicas, "seed": seed, "model": None}
                if any(previous.get(k) != v for k, v in now.items()):
                    shutil.rmtree(out / "fit" / "check")
            t0 = time.perf_counter()
            say(f"checking the fits of the study's {len(own)} participants ({replicas} replicas each)")
            check.run(out / "fit", out / "fit" / "check", replicas, None, str(out / "scores.sqlite"), jobs, seed,
                      progress, own)
            steps.finish("check", digest, time.perf_counter() - t0)
        check_line = _check_line(out / "fit" / "check" / "check.md")
    text = report(study, table, steps, sizes, simulated, n_tasks, resamples, planted, depths,
                  time.perf_counter() - started, replaced(pool_people, sizes), check_line, why,
                  people=bool(logs), planned=counts if logs else None)
    atomic_write_text(out / "study.md", text)
    return {"out": str(out), "findings": table, "report": text}




def _participants(out: Path, sizes: dict[str, int], fitted: bool = True,
                  data: str = "sim") -> tuple[pd.DataFrame, pd.DataFrame]:
    """The participant table of the simulated pool (written to ``participants.csv``), and the study proper: the
    first participants of each condition, as many as ``sizes`` says (the rest of the pool only for redrawing)."""
    df = participant_table(out, fitted, data)
    atomic_write_text(out / "participants.csv", df.to_csv(index=False))
    pool_people = df[df["condition"].isin(sizes)]
    people = pd.concat([pool_people[pool_people["condition"] == c].sort_values("participant").head(n)
                        for c, n in sizes.items()], ignore_index=True)
    return pool_people, people


def _graded(out: Path, sim_cfg, sizes: dict[str, int], steps: "Steps", resamples: int, seed: int,
            started: float, fitted: bool = True, progress: bool = False, data: str = "sim", jobs: int = 1,
            say: Callable[[str], None] = lambda s: None, command: str = "") -> dict:
    """A graded study's step 4: each level's figures, the trends and the sample sizes (:mod:`overhang_framework.studies.graded`)."""
    from overhang_framework.studies import graded

    t0 = time.perf_counter()
    limits = {name: sim_cfg.conditions[name].get("time_limit") for name in sizes}
    levels = graded.levels_of(limits)
    pool_people, people = _participants(out, sizes, fitted, data)
    pred = graded.predictions(people, levels, seed=seed)
    found = graded.trends(people, levels, seed=seed)
    from overhang_framework.progress import progress_bar

    measured = [m for m in graded.MEASURES if m.column in pool_people.columns and pool_people[m.column].notna().any()]
    # people too few a level for the smallest study the design considers: a bootstrap of them is no power
    study = {lv: int((people["condition"] == lv).sum()) for lv in levels}
    few = data == "people" and graded.too_few(study, levels)
    bar = progress_bar(total=len(measured) * len(graded.SIZES) * resamples, desc="power", unit="study",
                       disable=not progress or not resamples or few, mininterval=1.0, dynamic_ncols=True)
    try:
        table = graded.power(pool_people, levels, resamples=resamples, seed=seed, on_study=lambda: bar.update(1)) \
            if resamples and not few else pd.DataFrame(columns=["measure", "per_level", "power", "resamples",
                                                                "mc_error"])
    finally:
        bar.close()
    for name, frame in (("predictions.csv", pred), ("trends.csv", found), ("power.csv", table)):
        atomic_write_text(out / name, frame.to_csv(index=False))
    written = ["predictions.csv", "trends.csv", "power.csv"]
    if data == "sim" and resamples:  # the design: its preregistration
        from omegaconf import OmegaConf

        from overhang_framework.behaviour.log import read_log
        from overhang_framework.studies import prereg
        from overhang_framework.version import commit, version

        planned, _ = prereg.planned_size(table)
        at = planned if planned is not None else int(max(graded.SIZES))
        effects = prereg.effect_power(pool_people, levels, at, max(50, resamples // 5), seed)
        atomic_write_text(out / "preregistration_effects.csv", effects.to_csv(index=False))
        minutes = prereg.durations(read_log(out / data / "log.jsonl"), levels)
        screen = _practice(out, sim_cfg, steps, jobs, progress, say)
        provenance = {"commit": commit(), "version": version(), "seed": seed, "resamples": resamples,
                      "settings_hash": prereg.settings_hash(OmegaConf.to_container(sim_cfg, resolve=True))}
        atomic_write_text(out / "preregistration.md", prereg.document(
            levels, limits, table, effects, minutes, {c: int((pool_people["condition"] == c).sum()) for c in levels},
            fitted, provenance, command, screen))
        written += ["preregistration.md", "preregistration_effects.csv"] + \
            (["practice.csv"] if isinstance(screen, pd.DataFrame) else [])
    steps.finish("findings", "", time.perf_counter() - t0)
    text = graded.report(pred, found, table, levels, limits, {c: int((pool_people["condition"] == c).sum())
                                                              for c in levels}, people=data == "people",
                         study=study)
    text += _unmapped_line(people) if fitted else ""
    if not fitted:
        text += ("\nNo fit (`--no-fit`): the fitted depth and risk aversion are neither predicted nor tested; "
                 "run the study again without `--no-fit` to add them.\n")
    text += ("\n## Steps\n\n" + "\n".join(f"- {k}: {v['seconds']:.0f} s" for k, v in steps.done.items())
             + f"\n\nTotal this run: {time.perf_counter() - started:.0f} s. Files: `{data}/`, `analysis/report.md`, "
             "`fit/comparison.md`, `participants.csv`, " + ", ".join(f"`{w}`" for w in written) + ".\n")
    atomic_write_text(out / "study.md", text)
    return {"out": str(out), "findings": found, "report": text}


def _practice(out: Path, sim_cfg, steps: Steps, jobs: int, progress: bool,
              say: Callable[[str], None]) -> "pd.DataFrame | str":
    """The design's participants doing the served study's practice (``practice.csv``, its step ``practice``), or why
    it could not be simulated (the server's practice has no stored towers for its physics, say)."""
    from omegaconf import OmegaConf

    from overhang_framework.progress import progress_bar
    from overhang_framework.studies import screenout

    config = OmegaConf.to_container(sim_cfg, resolve=True)
    try:
        _, practice, attempts, served = screenout.practice_of()
    except OverhangError as err:
        return " ".join(str(err).split())
    # what the practice depends on: the participants, the served world and practice, how many a level (not how the
    # run shows its progress or how many processes it takes)
    digest = _digest(extra={"config": {k: v for k, v in config.items() if k not in ("jobs", "progress")},
                            "served_world": served, "per_level": screenout.PER_LEVEL, "attempts": attempts,
                            "practice": [[p.task.id, list(p.task.sequence), p.pass_reward] for p in practice]})
    path = out / "practice.csv"
    if steps.current("practice", digest) and path.exists():
        return pd.read_csv(path)
    t0 = time.perf_counter()
    n = sum(min(int(v), screenout.PER_LEVEL) for v in config["cohort"]["participants"].values())
    say(f"the practice of {n} of the design's participants (up to {screenout.PER_LEVEL} a level), as the server "
        "scores it: the expected screen-out")
    bar = progress_bar(total=n, desc="practice", unit="participant", disable=not progress, miniters=1,
                       mininterval=0.5, dynamic_ncols=True)
    try:
        table = screenout.simulate_practice(config, jobs=jobs, on_participant=lambda: bar.update(1))
    finally:
        bar.close()
    atomic_write_text(path, table.to_csv(index=False))
    steps.finish("practice", digest, time.perf_counter() - t0)
    return table


def take_logs(logs: Sequence[str | Path], into: Path, study: str, conditions: Sequence[str]) -> dict[str, int]:
    """People's behaviour logs (``logs``: exports of the study) as the study's participants: their records written
    to ``into/log.jsonl`` and their conditions to ``into/people.csv``; the number a condition, in the order of
    ``conditions``. A condition the study does not have, or a log without records, is one :class:`ConfigError` line."""
    from overhang_framework.behaviour.log import LogError, read_log, require_records, write_log

    paths = [str(p) for p in logs]
    try:
        df = require_records(read_log(paths), paths)
    except LogError as err:
        raise ConfigError(f"--log: {err}") from None
    people = df.drop_duplicates("participant")[["participant", "condition"]]
    unknown = sorted(set(people["condition"].astype(str)) - set(conditions))
    if unknown:
        raise ConfigError(f"--log: participants in condition {unknown[0]!r}, which the study {study} does not have "
                          f"(its conditions: {', '.join(conditions)})")
    into.mkdir(parents=True, exist_ok=True)
    write_log(df, into / "log.jsonl")
    table = people.rename(columns={"participant": "id"}).sort_values("id", kind="stable")
    atomic_write_text(into / PEOPLE, table.to_csv(index=False))
    (into / "participants.csv").unlink(missing_ok=True)  # an earlier version's, which the fit would read as a truth
    return {c: int((people["condition"] == c).sum()) for c in conditions if (people["condition"] == c).any()}


def _unmapped_line(people: pd.DataFrame) -> str:
    """The report's line on the placements the fit's grid could not map (people place anywhere; the fit scores
    grid actions)."""
    share = people["unmapped_share"].dropna() if "unmapped_share" in people.columns else pd.Series(dtype=float)
    if not len(share):
        return ""
    worst = people.loc[share.idxmax()]
    return (f"\nPlacements the fit's grid could not map (left out of each participant's likelihood): "
            f"{share.mean():.1%} a participant on average, at most {share.max():.1%} "
            f"({worst['participant']}).\n")
