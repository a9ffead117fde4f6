"""A behaviour log as a Psych-DS dataset: writing one, checking a directory against the standard, reading it back.

Psych-DS (https://psych-ds.github.io) is a community standard for behavioural data sets:
a directory with a ``dataset_description.json`` (schema.org ``Dataset`` metadata in JSON-LD,
whose ``variableMeasured`` names every column of every data file) and a ``data/`` folder of
CSV files whose names are keyword-value pairs ending ``_data.csv``. A log is written as

    DIR/dataset_description.json
    DIR/data/study-overhang_subject-P1_data.csv      one file per participant, one row per record
    DIR/data/study-overhang_subject-P2_data.csv

Every file has the same header, the log's columns (:data:`~overhang_framework.behaviour.log.COLUMNS`
then any extra fields), so the files can be stacked into one table. Cells are as
:func:`~overhang_framework.behaviour.log.to_csv` writes them: text as it is, numbers and
``true``/``false`` as JSON, lists (``sequence``, ``tower_before``, ``trajectory``, ``dwell``) as
JSON text, and an empty cell for a missing value (null). :func:`read_log` of the directory gives
back the log that was written.

:func:`check_dataset` lists what breaks the standard's rules (or this package's stricter ones:
every listed variable is used, no stray file in ``data/``), one line each;
``python -m overhang_framework.behaviour.psychds DIR`` prints them.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import re
import shutil
import sys
import tempfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterable, Mapping, Optional, Sequence

from overhang_framework.behaviour.dataset_rules import (  # noqa: F401  (this module's names since it began)
    CHANGES, DATA, DATA_FILE, DESCRIPTION, IGNORE, IGNORE_NEW, README, SCHEMA_ORG, SCHEMA_VERSION, PsychDSError,
    _ignored, _is_ignored, check_dataset, data_files)
from overhang_framework.behaviour.log import FIELDS, count_noun, to_csv, to_frame
from overhang_framework.version import __version__

@dataclass(frozen=True)
class Variable:
    """One column: what it holds, in which unit, and the kind of its cells (as in ``schema.json``)."""

    description: str
    kind: str  # integer, number, boolean, string, list
    unit: Optional[str] = None
    minimum: Optional[float] = None
    optional: bool = True  # whether a cell may be empty (a missing value)

    def property_value(self, name: str) -> dict:
        """The schema.org ``PropertyValue`` describing column ``name``."""
        what = {"list": "a JSON list", "boolean": "true or false", "integer": "a whole number",
                "number": "a number", "string": "text"}[self.kind]
        entry: dict[str, Any] = {"@type": "PropertyValue", "name": name,
                                 "description": f"{self.description} Each cell: {what}"
                                                + ("; empty when missing." if self.optional else ".")}
        if self.unit:
            entry["unitText"] = self.unit
        if self.minimum is not None:
            entry["minValue"] = self.minimum
        return entry


#: The unit of each log field that has one (task units: a block is 0.6 high; the grid runs from -4 to 4).
_UNITS = {"width": "task units", "x": "task units", "overhang": "task units", "reward": "task units",
          "decision_time": "seconds", "sequence": "task units", "tower_before": "task units",
          "trajectory": "seconds and task units", "dwell": "task units and seconds",
          "layer": "layers of 0.6 task units"}
_KINDS = {"array": "list", "integer": "integer", "number": "number", "boolean": "boolean", "string": "string"}


@lru_cache(maxsize=None)
def log_variables() -> dict[str, Variable]:
    """The :class:`Variable` of every named field of the log, described as ``schema.json`` describes it."""

    schema = json.loads((Path(__file__).with_name("schema.json")).read_text(encoding="utf-8"))["properties"]
    out = {}
    for field in FIELDS:
        spec = schema[field.name]
        kind = _KINDS[next(t for t in field.types if t != "null")]
        out[field.name] = Variable(spec["description"], kind, _UNITS.get(field.name), spec.get("minimum"),
                                   optional=not field.required or "null" in field.types)
    return out


def subject_label(participant: str) -> str:
    """A participant's id as the value of a file name's ``subject-`` keyword: the id itself when it is letters
    and digits only; otherwise its letters and digits, ``x`` and the first 8 hex digits of the id's SHA-256
    (``lab_P1`` gives ``labP1x`` and 8 digits, never ``labP1``). It depends on the id alone, so a participant's
    file keeps its name whoever else is in the dataset, before and after a withdrawal."""
    import hashlib

    kept = re.sub(r"[^a-zA-Z0-9]", "", participant)
    if kept == participant and kept:
        return kept
    return f"{kept}x{hashlib.sha256(participant.encode()).hexdigest()[:8]}"


def _file_names(participants: Sequence[str], study: str) -> dict[str, str]:
    """Each participant's data file name (``subject-`` :func:`subject_label`); :class:`PsychDSError` in the
    unlikely case that two ids give one label."""
    names, used = {}, {}
    for p in participants:
        label = subject_label(p)
        if label in used:
            raise PsychDSError(f"participants {used[label]!r} and {p!r} would share the data file name subject-{label}")
        used[label] = p
        names[p] = f"study-{study}_subject-{label}_data.csv"
    return names


def description(columns: Sequence[str], variables: Mapping[str, Variable], name: str, text: str,
                **fields: Any) -> dict:
    """``dataset_description.json`` of data files with ``columns``; :class:`PsychDSError` when a column has
    no :class:`Variable` in ``variables`` (the description would not say what it holds)."""
    missing = [c for c in columns if c not in variables]
    if missing:
        raise PsychDSError(f"no description of the column(s) {', '.join(map(repr, missing))}: add them to the "
                           "variables the export describes")
    return {"@context": "https://schema.org/", "@type": "Dataset", "name": name, "description": text,
            **{k: v for k, v in fields.items() if v is not None},
            "variableMeasured": [variables[c].property_value(c) for c in columns]}


#: Files beside ``dataset_description.json`` that a dataset written here may hold (:func:`write_dataset`'s
#: ``sidecars``): replaced with it by a later export.
SIDECARS = ("study.json",)
#: Every file a dataset written here has at its root, besides ``data/``.
ROOT_FILES = (DESCRIPTION, README, CHANGES, IGNORE, IGNORE_NEW)


def write_dataset(records: Iterable[Mapping[str, Any]], out: str | os.PathLike, variables: Mapping[str, Variable],
                  name: str, text: str, study: str = "overhang", sidecars: Optional[Mapping[str, str]] = None,
                  **fields: Any) -> list[Path]:
    """Write the log ``records`` (checked first) as a Psych-DS dataset in ``out``; the data files written.

    ``variables`` describes every column (:func:`log_variables` and those of any extra field);
    ``name`` and ``text`` are the dataset's name and description, ``fields`` further schema.org
    ``Dataset`` properties (None left out), ``sidecars`` texts of files at the dataset's root, by name
    (from :data:`SIDECARS`). The dataset is built in a folder beside ``out`` and
    renamed into place: ``out`` may be new, an empty folder, or an earlier dataset written here
    (:func:`replaceable`), which it replaces; anything else is refused before a file is written.
    """
    from overhang_framework.results import readable

    out = Path(out)
    check_out(out)
    df = to_frame([readable(dict(r)) for r in records])
    if df.empty:
        raise PsychDSError("no records to write: a Psych-DS dataset needs at least one data file")
    columns = [str(c) for c in df.columns]
    meta = description(columns, variables, name, text, dateCreated=dt.date.today().isoformat(),
                       schemaVersion=SCHEMA_VERSION, **fields)
    participants = sorted(dict.fromkeys(df["participant"]))
    files = _file_names(participants, study)
    previous = out / CHANGES
    earlier = previous.read_text(encoding="utf-8") if previous.is_file() else ""
    out.absolute().parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=out.absolute().parent, prefix=f".{out.name}."))
    try:
        (staging / DATA).mkdir()
        for p in participants:
            to_csv(df[df["participant"] == p], staging / DATA / files[p])
        (staging / DESCRIPTION).write_text(json.dumps(meta, indent=2, ensure_ascii=False, allow_nan=False) + "\n",
                                           encoding="utf-8")
        for sidecar, content in (sidecars or {}).items():
            if sidecar not in SIDECARS:
                raise ValueError(f"sidecar {sidecar!r}: a dataset's root takes {', '.join(SIDECARS)}")
            (staging / sidecar).write_text(content, encoding="utf-8")
        ignored = sorted({*(sidecars or {}), IGNORE, IGNORE_NEW})  # what the standard does not cover, and these
        for ignore in (IGNORE, IGNORE_NEW):
            (staging / ignore).write_text("# files the Psych-DS validators need not check: sidecars of this export\n"
                                          + "".join(f"{f}\n" for f in ignored), encoding="utf-8")
        (staging / README).write_text(readme(meta, files, sidecars or {}), encoding="utf-8")
        (staging / CHANGES).write_text(changes(earlier, len(participants), len(df)), encoding="utf-8")
        problems = check_dataset(staging)
        if problems:  # what this module writes must pass its own check
            raise PsychDSError(f"the dataset written is not valid Psych-DS: {problems[0]}")
        os.chmod(staging, 0o777 & ~_umask())
        _put_in_place(staging, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return [out / DATA / files[p] for p in participants]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _put_in_place(staging: Path, out: Path) -> None:
    """Rename ``staging`` to ``out``; an earlier dataset there is moved aside first and removed after."""
    check_out(out)
    if out.exists() and any(out.iterdir()):
        old = Path(tempfile.mkdtemp(dir=out.absolute().parent, prefix=f".{out.name}.old."))
        os.replace(out, old / "dataset")
        try:
            os.replace(staging, out)
        except OSError:
            os.replace(old / "dataset", out)
            raise
        finally:
            shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(staging, out)  # over an empty folder too


def readme(meta: dict, files: Mapping[str, str], sidecars: Mapping[str, str]) -> str:
    """``README.md`` of a dataset: what it holds, how its files are named and read, where its columns are
    described."""

    lines = [f"# {meta['name']}", "", meta["description"], "",
             "## Files", "",
             f"- `{DESCRIPTION}`: the dataset's metadata (schema.org `Dataset`, {meta.get('schemaVersion')}); its "
             "`variableMeasured` describes every column: what it holds, its unit, its least value.",
             f"- `{DATA}/`: one CSV file per participant, `study-..._subject-..._data.csv`. The `subject-` value is "
             "the participant's id when that is letters and digits only; otherwise its letters and digits, `x` and "
             "8 hex digits of the id's SHA-256, so that a file's name depends on its participant alone. The "
             "`participant` column holds the id as it is. Every file has the same header, so the files stack "
             "into one table.",
             *(f"- `{name}`: the study's settings, their hashes and the versions that recorded and exported it."
               for name in sidecars if name == "study.json"),
             f"- `{CHANGES}`: each export of this dataset, with its date and counts.",
             f"- `{IGNORE}`, `{IGNORE_NEW}`: the files a Psych-DS validator need not check (the same list under the "
             "standard's two names for it).", "",
             "## Reading it", "",
             "In Python: `pandas.concat(map(pandas.read_csv, glob.glob('data/*_data.csv')))`; "
             "`python -m overhang_framework.analyze DIR` reads the folder as it is. An empty cell is a missing "
             "value; lists are JSON text; true and false are JSON.", "",
             f"Written by overhang-framework {__version__} ({len(files)} data files).", ""]
    return "\n".join(lines)


def changes(earlier: str, participants: int, records: int) -> str:
    """``CHANGES.md``: this export's entry (date, counts) above those of the export it replaces."""

    head = "# Changes\n\n"
    entry = (f"- {dt.date.today().isoformat()}: exported by overhang-framework {__version__}: {participants} "
             f"participant(s), {records} row(s).\n")
    kept = earlier[len(head):] if earlier.startswith(head) else ""
    return head + entry + kept


def replaceable(out: Path) -> bool:
    """Whether ``out`` holds only what :func:`write_dataset` writes: ``dataset_description.json`` and
    ``data/`` with data files in it, the README, CHANGES and ignore files, and the :data:`SIDECARS`; nothing
    else."""
    if not (out / DESCRIPTION).is_file() or not (out / DATA).is_dir():
        return False
    if not {p.name for p in out.iterdir()} <= {*ROOT_FILES, DATA, *SIDECARS}:
        return False
    return all(p.is_file() and DATA_FILE.fullmatch(p.name) for p in (out / DATA).iterdir())


def check_out(out: Path) -> None:
    """Raise :class:`PsychDSError` unless ``out`` may take a dataset: it is new, an empty folder, or an
    earlier dataset (:func:`replaceable`)."""
    if not out.exists():
        return
    if not out.is_dir():
        raise PsychDSError(f"{out} is a file; a Psych-DS dataset is a folder: give a new or empty folder")
    if any(out.iterdir()) and not replaceable(out):
        raise PsychDSError(f"{out} is not empty and not an earlier Psych-DS export (only "
                           f"{', '.join((*ROOT_FILES, *SIDECARS))} and {DATA}/*_data.csv); give a new or empty folder")



def main(argv: Optional[Sequence[str]] = None) -> int:

    ap = argparse.ArgumentParser(prog="python -m overhang_framework.behaviour.psychds",
                                 description="Check that folders are valid Psych-DS datasets; print what is wrong.")
    ap.add_argument("datasets", nargs="+", metavar="DIR", help="a dataset's folder (with dataset_description.json)")
    args = ap.parse_args(argv)
    bad = 0
    for root in args.datasets:
        problems = check_dataset(root)
        for line in problems:
            print(f"{root}: {line}", file=sys.stderr)
        if not problems:
            print(f"{root}: a valid Psych-DS dataset ({count_noun(len(data_files(root)), 'data file')})")
        bad += bool(problems)
    return 2 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
