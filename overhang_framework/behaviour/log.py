"""The behaviour log: one JSON Lines record per placement, written alike by people, simulated participants and models.

A record says who placed which block where, in which trial, what the tower
was before, what happened after, and how long the decision took (the fields:
:data:`FIELDS`; their meaning: ``docs/behaviour.md``; a JSON Schema of one
record: ``schema.json`` beside this module). This module reads and writes
logs and checks them:

* :func:`read_log` reads JSON Lines (``.jsonl``) or CSV (``.csv``) files (or Psych-DS folders) into
  a DataFrame, one row per record sorted by :data:`ORDER` (participant, trial,
  step) whatever the order of the lines, columns :data:`COLUMNS` then any extra
  fields in the order they first appear in those sorted records;
* :func:`in_step_order` and :func:`last_records` give any log DataFrame in that
  order and each trial's last step: what an analysis relies on never depends
  on the order in which records were merged;
* :func:`write_log` and :func:`to_csv` write them atomically, after checking;
* a malformed log raises :class:`LogError`, one line naming the file, the line
  and the field: ``log.jsonl line 3: field 'x': expected a number, got "abc"``.

Each record is checked on its own (types, allowed widths, ranges, the tower
before the placement, the overhang after it, which records carry a reward),
then the records together: no placement twice, each trial's steps 1, 2, ...
without gaps, ending with its final placement, a collapse or a timeout, each
tower the previous one with its block added, and each task one trial per
participant. Nothing is dropped or repaired.

    python -m overhang_framework.behaviour.log LOG [LOG...] [--csv OUT]
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Optional, Sequence, Union

import numpy as np
import pandas as pd

from overhang_framework.behaviour.dataset_rules import data_files
from overhang_framework.check import BadTower, parse_tower
from overhang_framework.errors import OverhangError
from overhang_framework.geometry import MAX_LAYER, WIDTHS, Block, Geometry, IllegalWidth, check_width, overhang
from overhang_framework.results import atomic_write_text, json_line, readable

#: The version of the format this module reads and writes.
LOG_VERSION = 1
#: Who made a log's placements (the optional ``source`` field).
SOURCES = ("human", "simulated", "model")
#: How far a logged overhang and reward may lie from the ones their tower gives, and a tower's x from
#: the previous record's.
TOLERANCE = 1e-6

PathLike = Union[str, "os.PathLike[str]"]


@dataclass(frozen=True)
class Field:
    """One field of a record: its name, the JSON Schema types its value may have, whether it must be present."""

    name: str
    types: tuple[str, ...]
    required: bool = True


#: Every named field of a record, in column order. ``schema.json`` lists the same fields (a test checks it).
FIELDS: tuple[Field, ...] = (
    Field("log_version", ("integer",)),
    Field("participant", ("string",)),
    Field("condition", ("string",)),
    Field("task_id", ("string",)),
    Field("sequence", ("array",)),
    Field("trial", ("integer",)),
    Field("step", ("integer",)),
    Field("width", ("number",)),
    Field("x", ("number", "null")),
    Field("layer", ("integer", "null")),
    Field("tower_before", ("array",)),
    Field("stable", ("boolean", "null")),
    Field("overhang", ("number", "null")),
    Field("reward", ("number", "null")),
    Field("decision_time", ("number",)),
    Field("timed_out", ("boolean",)),
    Field("trajectory", ("array", "null"), required=False),
    Field("dwell", ("array", "null"), required=False),
    Field("source", ("string", "null"), required=False),
)
COLUMNS: tuple[str, ...] = tuple(f.name for f in FIELDS)
REQUIRED: tuple[str, ...] = tuple(f.name for f in FIELDS if f.required)
#: The DataFrame dtype of each named column; extra columns get the dtype pandas infers.
DTYPES: dict[str, Any] = {
    "log_version": "int64", "participant": object, "condition": object, "task_id": object, "sequence": object,
    "trial": "int64", "step": "int64", "width": "float64", "x": "float64", "layer": "Int64",
    "tower_before": object, "stable": "boolean", "overhang": "float64", "reward": "float64",
    "decision_time": "float64", "timed_out": "bool", "trajectory": object, "dwell": object, "source": object,
}
TEXT_COLUMNS = ("participant", "condition", "task_id", "source")
#: The order of a log's records as :func:`read_log` and :func:`to_frame` give them: by participant, then
#: trial, then step. Records merged from several sources come in any order; this one is canonical.
ORDER = ("participant", "trial", "step")
_WORDS = {"integer": "a whole number", "number": "a number", "string": "a string", "boolean": "true or false",
          "array": "a list"}
_ALLOWED_WIDTHS = ", ".join(map(str, WIDTHS))


class LogError(OverhangError, ValueError):
    """A malformed behaviour log, in one line: ``FILE line N: field 'name': what is wrong``.

    ``where`` is ``FILE line N`` for a file (``FILE`` alone when it cannot be
    read), ``record N`` or ``row N`` for records and DataFrames in memory;
    ``field`` is None when the line is not a record at all.
    """

    def __init__(self, where: str, field: Optional[str], what: str):
        self.where, self.field, self.what = where, field, what
        super().__init__(f"{where}: field '{field}': {what}" if field else f"{where}: {what}")


class _Bad(Exception):
    """What is wrong with one field of a record (the reader adds where the record is)."""

    def __init__(self, field: Optional[str], what: str):
        super().__init__(what)
        self.field, self.what = field, what


def _show(value: Any) -> str:
    text = json.dumps(value, default=str)
    return text if len(text) <= 80 else text[:77] + "..."


def _is(value: Any, kind: str) -> bool:
    if kind == "number":
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if kind == "integer":
        return _is(value, "number") and float(value).is_integer()
    if kind == "string":
        return isinstance(value, str)
    if kind == "boolean":
        return isinstance(value, bool)
    if kind == "array":
        return isinstance(value, list)
    return value is None


def _width(value: Any, field: str, what: str = "") -> float:
    if not _is(value, "number"):
        raise _Bad(field, f"{what}expected a width ({_ALLOWED_WIDTHS}), got {_show(value)}")
    try:
        return check_width(value)
    except IllegalWidth:
        raise _Bad(field, f"{what}expected one of the widths {_ALLOWED_WIDTHS}, got {_show(value)}") from None


def _triples(value: list, field: str, names: str, whole_middle: bool = False) -> list[list]:
    """``value`` as a list of three-number items (the middle one whole when ``whole_middle``)."""
    out = []
    for k, item in enumerate(value, 1):
        if not isinstance(item, list) or len(item) != 3 or not all(_is(v, "number") for v in item):
            raise _Bad(field, f"item {k}: expected [{names}], three numbers, got {_show(item)}")
        if whole_middle and not (_is(item[1], "integer") and item[1] >= 0):
            raise _Bad(field, f"item {k}: expected a whole layer >= 0 as its second number, got {_show(item)}")
        out.append([float(item[0]), int(item[1]) if whole_middle else float(item[1]), float(item[2])])
    return out


def _tower(value: list, sequence: list[float], step: int) -> Geometry:
    """``tower_before`` checked against the sequence and step: the ground block at x=0, then one block per step."""
    if len(value) != step:
        raise _Bad("tower_before", f"expected {step} block{'s' * (step > 1)} (the ground block and the "
                                   f"{step - 1} placed before step {step}), got {len(value)}: {_show(value)}")
    try:
        geometry = parse_tower(json.dumps({"blocks": value}))
    except BadTower as exc:
        raise _Bad("tower_before", str(exc)) from None
    ground = geometry.blocks[0]
    if abs(ground.x) > TOLERANCE:
        raise _Bad("tower_before", f"the ground block stands at x=0, got x={ground.x:g}")
    for k, (block, width) in enumerate(zip(geometry.blocks, sequence), 1):
        if block.width != width:
            raise _Bad("tower_before", f"block {k} has width {block.width}, but sequence[{k - 1}] is {width}")
        if k > 1 and not 1 <= block.layer <= MAX_LAYER:
            raise _Bad("tower_before", f"block {k}: expected a layer from 1 to {MAX_LAYER}, got {block.layer}")
    return geometry


def ends_trial(record: Mapping[str, Any]) -> bool:
    """Whether a (checked) record is its trial's last: a timeout, a collapse, or the sequence's last block."""
    return bool(record["timed_out"]) or record["stable"] is False or record["step"] == len(record["sequence"]) - 1


def _ending(record: Mapping[str, Any]) -> str:
    if record["timed_out"]:
        return "the placement timed out"
    if record["stable"] is False:
        return "the tower fell"
    return "the sequence's last block"


def check_record(obj: Any) -> dict:
    """The record ``obj``, checked and normalised (widths as in :data:`WIDTHS`, whole numbers as ``int``,
    other numbers as ``float``, named fields first, extras kept as they are); raises ``_Bad``."""
    if not isinstance(obj, dict):
        raise _Bad(None, f"expected a JSON object (one record per line), got {_show(obj)}")
    version = obj.get("log_version")
    if "log_version" in obj and _is(version, "integer") and version != LOG_VERSION:
        raise _Bad("log_version", f"unknown version {_show(version)}; this reader reads version {LOG_VERSION}")
    for field in FIELDS:
        if field.name not in obj:
            if field.required:
                raise _Bad(field.name, "missing (a required field)")
            continue
        value = obj[field.name]
        if value is None and "null" in field.types:
            continue
        kinds = [t for t in field.types if t != "null"]
        if not any(_is(value, t) for t in kinds):
            raise _Bad(field.name, f"expected {' or '.join(_WORDS[t] for t in kinds)}, got {_show(value)}")
    r = {name: obj.get(name) for name in COLUMNS}
    for name in ("log_version", "trial", "step", "layer"):
        r[name] = None if r[name] is None else int(r[name])
    for name in ("x", "overhang", "reward", "decision_time"):
        r[name] = None if r[name] is None else float(r[name])
    for name in ("participant", "condition", "task_id"):
        if not r[name].strip():
            raise _Bad(name, f"expected a non-empty string, got {_show(r[name])}")
    sequence = r["sequence"] = [_width(w, "sequence", f"item {k}: ") for k, w in enumerate(r["sequence"], 1)]
    if len(sequence) < 2:
        raise _Bad("sequence", f"expected the ground block's width and at least one more, got {_show(sequence)}")
    if r["trial"] < 1:
        raise _Bad("trial", f"expected a whole number >= 1, got {r['trial']}")
    placements = len(sequence) - 1
    if not 1 <= r["step"] <= placements:
        raise _Bad("step", f"expected a step from 1 to {placements} (the sequence places {placements} "
                           f"block{'s' * (placements > 1)} after the ground block), got {r['step']}")
    r["width"] = _width(r["width"], "width")
    if r["width"] != sequence[r["step"]]:
        raise _Bad("width", f"expected {sequence[r['step']]}, the width of sequence[{r['step']}], got {r['width']}")
    before = _tower(r["tower_before"], sequence, r["step"])
    r["tower_before"] = [[b.width, b.x, b.layer] for b in before.blocks]
    if r["decision_time"] < 0:
        raise _Bad("decision_time", f"expected a number of seconds >= 0, got {r['decision_time']:g}")
    if r["timed_out"]:
        for name in ("x", "layer", "stable", "overhang"):
            if r[name] is not None:
                raise _Bad(name, f"expected null on a timed-out record, got {_show(r[name])}")
        if r["reward"] != 0:
            raise _Bad("reward", f"expected 0 on a timed-out record (a timeout ends the trial with reward 0), "
                                 f"got {_show(r['reward'])}")
    else:
        for name, kind in (("x", "number"), ("layer", "integer"), ("stable", "boolean"), ("overhang", "number")):
            if r[name] is None:
                raise _Bad(name, f"expected {_WORDS[kind]} (null only on a timed-out record), got null")
        if not 1 <= r["layer"] <= MAX_LAYER:
            raise _Bad("layer", f"expected a layer from 1 to {MAX_LAYER}, got {r['layer']}")
        expected = overhang(before.add(Block(r["width"], r["x"], r["layer"])))
        if abs(r["overhang"] - expected) > TOLERANCE:
            raise _Bad("overhang", f"expected {expected:.12g}, the overhang of tower_before with this block "
                                   f"(max |x| + width/2), got {r['overhang']:.12g}")
    if ends_trial(r):
        if r["reward"] is None:
            raise _Bad("reward", f"expected a number on the trial's last record ({_ending(r)}), got null")
        if r["stable"] is False and r["reward"] != 0:
            raise _Bad("reward", f"expected 0 (the tower fell), got {r['reward']:.12g}")
        if r["stable"] and abs(r["reward"] - r["overhang"]) > TOLERANCE:
            raise _Bad("reward", f"expected {r['overhang']:.12g}, the overhang (the tower stood after every "
                                 f"placement), got {r['reward']:.12g}")
    elif r["reward"] is not None:
        raise _Bad("reward", f"expected null: step {r['step']} of {placements} does not end the trial (the tower "
                             f"stands, no timeout), got {r['reward']:.12g}")
    if r["trajectory"] is not None:
        r["trajectory"] = _triples(r["trajectory"], "trajectory", "t, x, y")
        last = 0.0
        for k, (t, _, _) in enumerate(r["trajectory"], 1):
            if t < last:
                raise _Bad("trajectory", f"item {k}: expected a time >= {last:g} s (times start at 0 and never "
                                         f"go back), got t={t:g}")
            last = t
    if r["dwell"] is not None:
        r["dwell"] = _triples(r["dwell"], "dwell", "x, layer, seconds", whole_middle=True)
        for k, item in enumerate(r["dwell"], 1):
            if item[2] < 0:
                raise _Bad("dwell", f"item {k}: expected seconds >= 0, got {item[2]:g}")
    if r["source"] is not None and r["source"] not in SOURCES:
        raise _Bad("source", f"expected one of {', '.join(SOURCES)}, got {_show(r['source'])}")
    r.update((k, v) for k, v in obj.items() if k not in r)
    return r


def _checked(where: str, obj: Any) -> dict:
    if isinstance(obj, Mapping) and "steps" in obj and "task_index" in obj and "participant" not in obj:
        raise LogError(where, None, "an episode of a model run, not a behaviour log record; convert the run first: "
                                    "python -m overhang_framework.behaviour.convert RUN_DIR --out LOG")
    try:
        return check_record(obj)
    except _Bad as bad:
        raise LogError(where, bad.field, bad.what) from None


def _who(record: Mapping[str, Any]) -> str:
    return f"trial {record['trial']} of participant {_show(record['participant'])}"


def _same_tower(a: list[list], b: list[list]) -> bool:
    return len(a) == len(b) and all(p[0] == q[0] and p[2] == q[2] and abs(p[1] - q[1]) <= TOLERANCE
                                    for p, q in zip(a, b))


def check_log(entries: Sequence[tuple[str, dict]]) -> list[dict]:
    """The records of ``entries`` (``(where, checked record)`` pairs, in log order) checked together;
    raises :class:`LogError` naming the first record at fault."""
    seen: dict[tuple, str] = {}
    task_trial: dict[tuple, tuple[int, str]] = {}
    trials: dict[tuple, list[tuple[str, dict]]] = {}
    for where, r in entries:
        key = (r["participant"], r["trial"], r["step"])
        if key in seen:
            raise LogError(where, "step", f"step {r['step']} of {_who(r)} again (first on {seen[key]})")
        seen[key] = where
        trial, first = task_trial.setdefault((r["participant"], r["task_id"]), (r["trial"], where))
        if trial != r["trial"]:
            raise LogError(where, "trial", f"participant {_show(r['participant'])} did task {_show(r['task_id'])} "
                                           f"as trial {trial} ({first}); a task is one trial, got trial {r['trial']}")
        trials.setdefault((r["participant"], r["trial"]), []).append((where, r))
    for group in trials.values():
        group.sort(key=lambda entry: entry[1]["step"])
        first_where, first = group[0]
        previous: Optional[tuple[str, dict]] = None
        for step, (where, r) in enumerate(group, 1):
            for name in ("task_id", "condition", "sequence"):
                if r[name] != first[name]:
                    raise LogError(where, name, f"expected {_show(first[name])} as on {first_where} ({_who(r)}), "
                                                f"got {_show(r[name])}")
            if r["step"] != step:
                raise LogError(where, "step", f"{_who(r)} has no step {step}, got step {r['step']} next")
            if previous is not None:
                p_where, p = previous
                if ends_trial(p):
                    raise LogError(where, "step", f"{_who(r)} ended at step {p['step']} ({p_where}: {_ending(p)}), "
                                                  f"got step {r['step']}")
                expected = p["tower_before"] + [[p["width"], p["x"], p["layer"]]]
                if not _same_tower(r["tower_before"], expected):
                    raise LogError(where, "tower_before", f"expected the tower of step {p['step']} ({p_where}) "
                                                          f"with its block, {_show(expected)}, got "
                                                          f"{_show(r['tower_before'])}")
            previous = (where, r)
        last_where, last = group[-1]
        if not ends_trial(last):
            raise LogError(last_where, "step", f"{_who(last)} stops at step {last['step']} of "
                                               f"{len(last['sequence']) - 1} with the tower standing and no "
                                               "timeout: its later steps are missing")
    return [r for _, r in entries]


def to_frame(records: Iterable[Mapping[str, Any]]) -> pd.DataFrame:
    """The DataFrame of ``records`` (dicts as in a log, checked first): what :func:`read_log` gives for
    a file holding them. Raises :class:`LogError` (``record N: ...``) when one is malformed."""
    return _frame(_in_order(_checked_entries(records, "record")))


def _in_order(records: list[dict]) -> list[dict]:
    """``records`` sorted by :data:`ORDER` (stable)."""
    return sorted(records, key=lambda r: tuple(r[name] for name in ORDER))


def in_step_order(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` (a log DataFrame) with its rows sorted by :data:`ORDER` and numbered from 0: the order of
    :func:`read_log`, whatever order the rows came in."""
    return df.sort_values(list(ORDER), kind="mergesort").reset_index(drop=True)


def last_records(df: pd.DataFrame) -> pd.DataFrame:
    """The last record of each trial of ``df`` (the one with the highest step, not the last row), one row
    per (participant, trial), in :data:`ORDER`."""
    return in_step_order(df).groupby(["participant", "trial"], sort=False).tail(1).reset_index(drop=True)


def _frame(records: list[dict]) -> pd.DataFrame:
    extras = list(dict.fromkeys(k for r in records for k in r if k not in DTYPES))
    data = {}
    for name in (*COLUMNS, *extras):
        values = [r.get(name) for r in records]
        data[name] = pd.Series(values, dtype=DTYPES[name]) if name in DTYPES else pd.Series(values)
    return pd.DataFrame(data, columns=[*COLUMNS, *extras])


def _data(value: Any) -> Any:
    """``value`` as plain JSON data: tuples and arrays as lists, numpy scalars as Python ones, NA as None."""
    if isinstance(value, Mapping):
        return {k: _data(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_data(v) for v in value]
    if value is pd.NA:
        return None
    return value.item() if isinstance(value, np.generic) else value


def _cell_value(value: Any) -> Any:
    """A DataFrame cell as JSON data; a missing value (None, NaN, NA) as None."""
    if isinstance(value, (float, np.floating)) and math.isnan(value):
        return None
    return _data(value)


def records_of(df: pd.DataFrame) -> list[dict]:
    """The records of a DataFrame as :func:`read_log` makes it (absent and null optional fields alike left out)."""
    records = []
    for row in df.itertuples(index=False, name=None):
        record = {}
        for name, value in zip(df.columns, row):
            value = _cell_value(value)
            if value is not None or name in REQUIRED:
                record[str(name)] = value
        records.append(record)
    return records


def _checked_entries(records: Iterable[Mapping[str, Any]], label: str) -> list[dict]:
    """``records`` checked alone and together, each named ``{label} N`` in errors."""
    return check_log([(f"{label} {i}", _checked(f"{label} {i}", _data(r))) for i, r in enumerate(records, 1)])


def log_text(records: Union[Iterable[Mapping[str, Any]], pd.DataFrame]) -> str:
    """``records`` (dicts, or a DataFrame from :func:`read_log`) checked and as JSON Lines text; numbers
    with 12 significant digits. Raises :class:`LogError` (``record N: ...``, ``row N: ...`` for a
    DataFrame) when one is malformed."""
    if isinstance(records, pd.DataFrame):
        checked = _checked_entries([readable(r) for r in records_of(records)], "row")
    else:
        checked = _checked_entries([readable(_data(r)) for r in records], "record")
    lines = [json.dumps({k: v for k, v in r.items() if v is not None or k in REQUIRED}, allow_nan=False)
             for r in checked]
    return "".join(line + "\n" for line in lines)


def write_log(records: Union[Iterable[Mapping[str, Any]], pd.DataFrame], path: PathLike) -> None:
    """Check ``records`` (as :func:`log_text`) and write them to ``path`` as JSON Lines, atomically;
    nothing is written when one is malformed."""
    atomic_write_text(path, log_text(records))


def _cell(name: str, value: Any) -> str:
    """A CSV cell: text fields as they are, other values as JSON (null as an empty cell), and text in other
    columns as it is unless it would read back as JSON or as empty."""
    if value is None:
        return ""
    if isinstance(value, str):
        if name in TEXT_COLUMNS:
            return value
        try:
            json.loads(value)
        except ValueError:
            return value if value else '""'
    return json.dumps(value, allow_nan=False)


def _uncell(name: str, text: Optional[str]) -> Any:
    if not text:
        return None
    if name in TEXT_COLUMNS:
        return text
    try:
        return json.loads(text)
    except ValueError:
        return text


def to_csv(df: pd.DataFrame, path: PathLike) -> None:
    """Write the log ``df`` (a DataFrame from :func:`read_log`) to ``path`` as CSV, atomically, checking it first.

    The columns are ``df``'s. Lists (``sequence``, ``tower_before``, ...) are JSON in their cells; an
    empty cell is null. :func:`read_log` reads the file back into the same DataFrame.
    """
    records = _checked_entries(records_of(df), "row")
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(df.columns)
    for r in records:
        writer.writerow([_cell(name, r.get(name)) for name in df.columns])
    atomic_write_text(path, out.getvalue())


def _read_jsonl(path: Path) -> list[tuple[str, dict]]:
    entries = []
    with open(path, encoding="utf-8") as fh:
        for number, text in enumerate(fh, 1):
            if not text.strip():
                continue
            where = f"{path} line {number}"
            try:
                obj = json_line(text)
            except ValueError as exc:
                raise LogError(where, None, str(exc)) from None
            entries.append((where, _checked(where, obj)))
    return entries


def _read_csv(path: Path) -> list[tuple[str, dict]]:
    entries = []
    with open(path, encoding="utf-8", newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None:
            return entries
        twice = sorted({name for name in header if header.count(name) > 1})
        if twice:
            raise LogError(f"{path} line 1", twice[0], "a column named twice in the header")
        missing = [name for name in REQUIRED if name not in header]
        if missing:
            raise LogError(f"{path} line 1", missing[0], "missing column (a required field)")
        start = reader.line_num + 1
        for row in reader:
            where, start = f"{path} line {start}", reader.line_num + 1
            if not any(row):
                continue
            if len(row) > len(header):
                raise LogError(where, None, f"{len(row)} cells, but the header names {len(header)} columns")
            obj = {name: _uncell(name, text) for name, text in zip(header, row)}
            entries.append((where, _checked(where, {k: v for k, v in obj.items()
                                                    if v is not None or k in REQUIRED})))
    return entries


def read_log(paths: Union[PathLike, Sequence[PathLike]]) -> pd.DataFrame:
    """The behaviour log in ``paths`` (one file or several; ``.csv`` files as CSV, folders as Psych-DS
    datasets (:mod:`~overhang_framework.behaviour.psychds`), others as JSON Lines) as a DataFrame: one
    row per record, sorted by participant, trial and step (:data:`ORDER`) whatever the order of the lines
    and files, columns :data:`COLUMNS` (dtypes :data:`DTYPES`) then extra fields.
    Blank lines are skipped; anything else that is not a valid record raises :class:`LogError` naming
    the file, the line and the field."""
    files = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if any(Path(name).is_dir() for name in files):
        files = [f for name in files for f in (data_files(name) if Path(name).is_dir() else [name])]
    entries: list[tuple[str, dict]] = []
    for name in files:
        path = Path(name)
        try:
            entries.extend(_read_csv(path) if path.suffix.lower() == ".csv" else _read_jsonl(path))
        except (OSError, UnicodeDecodeError) as exc:
            raise LogError(str(path), None, f"cannot read it ({getattr(exc, 'strerror', None) or exc})") from None
    return _frame(_in_order(check_log(entries)))


def require_records(df: pd.DataFrame, paths: Union[PathLike, Sequence[PathLike]]) -> pd.DataFrame:
    """``df``, the log read from ``paths``; :class:`LogError` when it holds no record."""
    if df.empty:
        files = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
        raise LogError(", ".join(str(p) for p in files), None,
                       "no records; give a behaviour log with at least one placement")
    return df


def count_noun(n: int, noun: str) -> str:
    """``1 trial``, ``2 trials``."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def describe(df: pd.DataFrame) -> str:
    """One line about a log: records, participants, trials and conditions."""
    trials = len(df.drop_duplicates(["participant", "trial"]))
    conditions = ", ".join(sorted(df["condition"].unique()))
    return (f"{count_noun(len(df), 'record')}: {count_noun(df['participant'].nunique(), 'participant')}, "
            f"{count_noun(trials, 'trial')}" + (f" (conditions: {conditions})" if conditions else ""))


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.behaviour.log",
                                 description="Check behaviour logs (JSON Lines or CSV) and say what they hold.")
    ap.add_argument("logs", nargs="+", metavar="LOG", help="a log file (.jsonl or .csv); several are read as one")
    ap.add_argument("--csv", metavar="OUT", help="also write the log as CSV to OUT")
    args = ap.parse_args(argv)
    try:
        df = read_log(args.logs)
        if args.csv:
            to_csv(df, args.csv)
    except OverhangError as exc:
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"error: cannot write {args.csv}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(describe(df) + (f"; written to {args.csv}" if args.csv else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
