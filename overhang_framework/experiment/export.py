"""The stored main trials as a behaviour log (``docs/behaviour.md``), the format every analysis reads.

Only whole trials are exported: a trial a participant left before its end
(a closed tab that never came back) would break the log's rule that every
trial ends with its final placement, a collapse or a timeout. How many were
left out is returned beside the text. Practice trials are not part of the log.
"""

from __future__ import annotations

from overhang_framework.behaviour.log import LOG_VERSION, log_text
from overhang_framework.experiment.store import Store


def log_records(store: Store) -> tuple[list[dict], int]:
    """The behaviour-log records of every whole main trial, and the number of unfinished trials left out."""
    conditions = {p.id: p for p in store.participants()}
    trials: dict[tuple, list] = {}
    for row in store.placements(phase="main"):
        trials.setdefault((row.participant_id, row.trial), []).append(row)
    records, unfinished = [], 0
    for (pid, _), rows in sorted(trials.items()):
        rows.sort(key=lambda r: r.step)
        if not rows[-1].trial_over:
            unfinished += 1
            continue
        p = conditions[pid]
        for r in rows:
            records.append({
                "log_version": LOG_VERSION, "participant": pid, "condition": p.condition, "task_id": r.task_id,
                "sequence": list(r.sequence), "trial": r.trial, "step": r.step, "width": r.width, "x": r.x,
                "layer": r.layer, "tower_before": r.tower_before, "stable": r.stable, "overhang": r.overhang,
                "reward": r.reward, "decision_time": r.decision_time, "timed_out": r.timed_out,
                "trajectory": r.trajectory, "dwell": r.dwell, "source": "human",
                "study_id": p.study_id, "session_id": p.session_id,
                "received_at": r.received_at.isoformat() if r.received_at else None,
            })
    return records, unfinished


def export_jsonl(store: Store) -> tuple[str, int]:
    """:func:`log_records` as checked JSON Lines text, and the number of unfinished trials left out."""
    records, unfinished = log_records(store)
    return log_text(records), unfinished
