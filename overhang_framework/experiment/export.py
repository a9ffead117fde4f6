"""The stored main trials as a behaviour log (``docs/behaviour.md``), the format every analysis reads.

Only whole trials are exported: a trial a participant left before its end
(a closed tab that never came back) would break the log's rule that every
trial ends with its final placement, a collapse or a timeout. How many were
left out is returned beside the text. Practice trials are not part of the log,
and participants screened out in the practice are left out unless asked for
(then their practice attempts are exported as trials with ``phase: practice``,
each attempt a task of its own: ``practice1-attempt2``).

``decision_time`` is the server's: from when the server handed the step out to
when the placement arrived, which a reload of the page cannot restart. In
``time_limited`` it is at most the participant's time limit: a timeout used the
whole window, and a placement that arrived within the grace after it took its
extra time on the network. The page's own measurement is kept beside it as
``page_decision_time``, and the server's elapsed time as ``server_time``.

Every record says where it comes from: the framework's version and commit that
stored it and the hashes of the study's settings and task set it was made under
(:mod:`~overhang_framework.experiment.provenance`), and the version of the
consent text the participant agreed to, with when. :func:`study_json` is the
sidecar ``study.json`` beside an export: the full settings, the versions, the
recorded changes, and the dates of the first and last participant.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Mapping, Optional

from overhang_framework.behaviour.log import LOG_VERSION, log_text
from overhang_framework.behaviour.psychds import Variable, log_variables, write_dataset
from overhang_framework.experiment.store import Store, utc_iso

#: The export's formats: a behaviour log file (JSON Lines), or a Psych-DS dataset folder.
FORMATS = ("jsonl", "psych-ds")

#: The fields the export adds to the log's own (:func:`log_records`), described for a Psych-DS
#: dataset's ``variableMeasured``. Every field a record can have must be here or among the log's own.
EXPORT_VARIABLES: dict[str, Variable] = {
    "page_decision_time": Variable(
        "Seconds from the start of the decision to the placement as the participant's page measured them "
        "(a reload of the page restarts this clock; decision_time is the server's).", "number", "seconds", 0,
        optional=False),
    "server_time": Variable(
        "Seconds from when the server first handed the step out to when the placement arrived, not capped at the "
        "time limit.", "number", "seconds", 0),
    "late_action": Variable(
        "The placement [x, layer] that arrived after the time limit and its grace, stored as a timeout; empty "
        "when none did.", "list", "task units and layers"),
    "study_id": Variable("The recruitment platform's study id (STUDY_ID); empty without one.", "string"),
    "session_id": Variable("The recruitment platform's session id (SESSION_ID); empty without one.", "string"),
    "received_at": Variable("When the server received the placement: ISO 8601 date and time, UTC.", "string"),
    "phase": Variable(
        "practice on the practice attempts of participants screened out in the practice (exported only when "
        "asked); empty on the main trials.", "string"),
    "practice_trial": Variable("The practice trial of the attempt (1 = first); empty on the main trials.",
                               "integer", None, 1),
    "attempt": Variable("The attempt at the practice trial (1 = first); empty on the main trials.",
                        "integer", None, 1),
    "consent_version": Variable(
        "The version of the consent text the participant agreed to: sha256: and the first 16 hex digits of the "
        "text's SHA-256, as the participant's condition shows it (the study's consent_file, with its duration).", "string"),
    "consented_at": Variable("When the server recorded the participant's consent: ISO 8601 date and time, UTC.",
                             "string"),
    "framework_version": Variable("The overhang-framework version of the server that stored the placement.",
                                  "string"),
    "commit": Variable("The git commit of the server's code that stored the placement (with -dirty when its files "
                       "differed from it); empty when it did not run from a git checkout.", "string"),
    "settings_hash": Variable(
        "SHA-256 of the settings the placement was played under: the study's in force, with the participant's own "
        "time limit (what participants see and how they are scored, the task set included; study.json has them in "
        "full: the current settings, a previous one of its history, or one of its played_settings).", "string"),
    "time_limit": Variable(
        "The participant's time limit per placement, in seconds, as it was when they started (kept through a later "
        "change of the study's settings); empty without one.", "number", "seconds", 0),
    "tasks_hash": Variable("SHA-256 of the study's main task set (ids and block widths) the placement was made "
                           "under.", "string"),
}


def decision_time(row, time_limit: Optional[float]) -> float:
    """The server's decision time of a stored placement, at most ``time_limit`` (when there is one)."""
    seconds = float(row.server_time)
    return min(seconds, time_limit) if time_limit is not None else seconds


def log_records(store: Store, include_screened_out: bool = False,
                include_simulated: bool = False) -> tuple[list[dict], int]:
    """The behaviour-log records of every whole main trial, and the number of unfinished trials left out.

    ``include_screened_out`` adds the practice attempts of the participants screened out in the practice. A study
    of people leaves out its simulated participants (a pilot's) unless ``include_simulated``; each record's
    ``source`` is its participant's.
    """
    study = store.study()
    source = (study.settings.get("source") if study is not None else None) or "human"
    people = {p.id: p for p in store.participants()
              if include_simulated or source == "simulated" or (p.source or "human") != "simulated"}
    screened = {pid for pid, p in people.items() if p.screened_out_at is not None}
    trials: dict[tuple, list] = {}
    for row in store.placements(phase="main"):
        if row.participant_id in people and (row.participant_id not in screened or include_screened_out):
            trials.setdefault((row.participant_id, "main", row.trial, 1), []).append(row)
    if include_screened_out:
        for pid in sorted(screened):
            for row in store.placements(pid, phase="practice"):
                trials.setdefault((pid, "practice", row.trial, row.attempt), []).append(row)
    records, unfinished = [], 0
    numbers: dict[str, int] = {}
    for (pid, phase, trial, attempt), rows in sorted(trials.items(), key=lambda kv: (kv[0][0], kv[0][1] != "practice",
                                                                                       kv[0][2], kv[0][3])):
        rows.sort(key=lambda r: r.step)
        if not rows[-1].trial_over:
            unfinished += 1
            continue
        p = people[pid]
        if phase == "practice":
            numbers[pid] = numbers.get(pid, 0) + 1
            number, extra = numbers[pid], {"phase": "practice", "practice_trial": trial, "attempt": attempt}
            task_id = f"{rows[0].task_id}-attempt{attempt}"  # each attempt a trial of its own in the log
        else:
            number, extra, task_id = trial, {}, rows[0].task_id
        limit = p.time_limit
        for r in rows:
            records.append({
                "log_version": LOG_VERSION, "participant": pid, "condition": p.condition, "task_id": task_id,
                "sequence": list(r.sequence), "trial": number, "step": r.step, "width": r.width, "x": r.x,
                "layer": r.layer, "tower_before": r.tower_before, "stable": r.stable, "overhang": r.overhang,
                "reward": r.reward, "decision_time": decision_time(r, limit), "timed_out": r.timed_out,
                "trajectory": r.trajectory, "dwell": r.dwell,
                "source": "simulated" if source == "simulated" else (p.source or "human"), **extra,
                "time_limit": limit,
                "page_decision_time": r.decision_time, "server_time": r.server_time, "late_action": r.late_action,
                "study_id": p.study_id, "session_id": p.session_id,
                "received_at": utc_iso(r.received_at),
                "consent_version": p.consent_version,
                "consented_at": utc_iso(p.consented_at),
                "framework_version": r.framework_version, "commit": r.commit, "settings_hash": r.settings_hash,
                "tasks_hash": r.tasks_hash,
            })
    return records, unfinished


def export_jsonl(store: Store, include_screened_out: bool = False, include_simulated: bool = False) -> tuple[str, int]:
    """:func:`log_records` as checked JSON Lines text, and the number of unfinished trials left out."""
    records, unfinished = log_records(store, include_screened_out, include_simulated)
    return log_text(records), unfinished


def study_text(study: dict) -> str:
    """:func:`study_json`'s dict as the text of ``study.json``."""
    import json

    return json.dumps(study, indent=2, sort_keys=True) + "\n"


def study_json(store: Store) -> dict:
    """The sidecar of an export: the study's settings and their hashes, the framework's version and commit
    that started it and the changes recorded since, the address participants open, the counts of
    participants (withdrawn ones as a count only) and the dates of the first and last participant."""
    from overhang_framework.version import versions

    study = store.study()
    people = store.participants()
    started = [p.created_at for p in people if p.created_at is not None]
    out = {
        "exported_with": versions(),
        "participants": {"total": len(people), "completed": sum(p.completed_at is not None for p in people),
                         "simulated": sum((p.source or "human") == "simulated" for p in people),
                         "screened_out": sum(p.screened_out_at is not None for p in people),
                         "by_condition": {c: sum(p.condition == c for p in people)
                                          for c in sorted({p.condition for p in people})},
                         "withdrawn": study.withdrawn if study is not None else 0,
                         "declined": study.declined if study is not None else 0},
        "first_participant": utc_iso(min(started)) if started else None,
        "last_participant": utc_iso(max(started)) if started else None,
    }
    if study is None:
        return {"study": None, **out}
    return {"study": {"started_at": utc_iso(study.started_at), "framework_version": study.framework_version,
                      "commit": study.commit, "settings_hash": study.settings_hash, "tasks_hash": study.tasks_hash,
                      "public_url": study.public_url, "address": study.address, "history": study.history,
                      "settings": study.settings, "played_settings": store.played_settings()}, **out}


def variables() -> dict[str, Variable]:
    """The description of every column the export can write: the log's fields and :data:`EXPORT_VARIABLES`."""
    return {**log_variables(), **EXPORT_VARIABLES}


def write_psychds(records: Iterable[Mapping], out: str | Path, study: Optional[dict] = None) -> list[Path]:
    """Write the exported ``records`` as a Psych-DS dataset in the folder ``out`` (one data file per
    participant, :mod:`~overhang_framework.behaviour.psychds`), with ``study`` (:func:`study_json`) as its
    ``study.json``; the data files written."""
    records = list(records)
    people = sorted({r["participant"] for r in records})
    conditions = sorted({r["condition"] for r in records})
    days = sorted(str(r["received_at"])[:10] for r in records if r.get("received_at"))
    practice = any(r.get("phase") == "practice" for r in records)
    simulated = {r["participant"] for r in records if r.get("source") == "simulated"}
    if simulated and len(simulated) == len(people):
        who = "Simulated participants (a pilot through the server)"
    elif simulated:
        who = (f"People ({len(people) - len(simulated)}) and simulated participants of a pilot ({len(simulated)}, "
               "source: simulated)")
    else:
        who = "People"
    text = (f"{who} building towers in the Overhang Tower task, recorded by the overhang-framework web experiment: "
            f"{len(people)} participant{'s' * (len(people) != 1)} in the condition(s) {', '.join(conditions)}. "
            "One data file per participant, one row per placement (a block placed, or a decision that ran out of "
            "time); the whole main trials"
            + (", and the practice attempts of participants screened out in the practice (phase: practice)"
               if practice else "")
            + ". The columns are the overhang-framework behaviour log (docs/behaviour.md, log_version 1): lists "
              "are JSON text in their cells, true and false are JSON, an empty cell is a missing value. "
              "python -m overhang_framework.analyze reads this folder as it is.")
    return write_dataset(records, out, variables(), name=f"Overhang Tower task: {len(people)} participants",
                         text=text, keywords=["Overhang Tower", "physical reasoning", "planning", "block stacking"],
                         temporalCoverage=f"{days[0]}/{days[-1]}" if days else None,
                         sidecars=None if study is None else {"study.json": study_text(study)})


def export_psychds(store: Store, out: str | Path, include_screened_out: bool = False,
                   include_simulated: bool = False) -> tuple[list[dict], int]:
    """:func:`log_records` written by :func:`write_psychds` to ``out``; the records and the number of unfinished
    trials left out."""
    records, unfinished = log_records(store, include_screened_out, include_simulated)
    write_psychds(records, out, study_json(store))
    return records, unfinished
