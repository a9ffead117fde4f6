"""What a Psych-DS dataset must be: its file names, the rules a directory is checked against, and its data files.

:func:`check_dataset` lists what breaks the standard's rules (or this package's stricter ones), one line each;
:func:`data_files` gives a valid dataset's data files. Writing a dataset and reading it back as a behaviour log
are :mod:`~overhang_framework.behaviour.psychds`'s; the log reader takes the data files from here."""

from __future__ import annotations

import csv
import fnmatch
import json
import os
import re
from pathlib import Path
from typing import Optional, Sequence

from overhang_framework.errors import OverhangError

#: The metadata file at a dataset's root.
DESCRIPTION = "dataset_description.json"
#: The folder of the data files.
DATA = "data"
#: A data file's name: keyword-value pairs (keywords lowercase letters, values letters and digits),
#: joined by underscores, then ``_data.csv``.
DATA_FILE = re.compile(r"[a-z]+-[a-zA-Z0-9]+(?:_[a-z]+-[a-zA-Z0-9]+)*_data\.csv")
#: The JSON-LD context the required fields must be in.
SCHEMA_ORG = ("https://schema.org", "https://schema.org/", "http://schema.org", "http://schema.org/")
#: Files (glob patterns, one a line) that the standard's validators pass over (the name of the standard's earlier
#: versions, and :data:`IGNORE_NEW`, the name of 1.5; a dataset written here has both, the same).
IGNORE = ".psychdsignore"
IGNORE_NEW = ".psychds-ignore"
#: The version of the standard whose rules :func:`check_dataset` checks (the dataset's ``schemaVersion``).
SCHEMA_VERSION = "Psych-DS 1.5.1"
#: The README and CHANGES files the standard recommends at a dataset's root.
README, CHANGES = "README.md", "CHANGES.md"


class PsychDSError(OverhangError, ValueError):
    """A directory that is not a Psych-DS dataset this package can read, or an export that cannot be written."""



# checking --------------------------------------------------------------------------------------------------------
def _ignored(root: Path) -> list[str]:
    """The patterns of the dataset's ignore files (under either of the standard's names)."""
    out: list[str] = []
    for name in (IGNORE, IGNORE_NEW):
        path = root / name
        if path.is_file():
            lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
            out += [line.strip().rstrip("/") for line in lines if line.strip() and not line.startswith("#")]
    return out


def _is_ignored(relative: str, patterns: Sequence[str]) -> bool:
    parts = relative.split("/")
    return any(fnmatch.fnmatch(relative, p) or any(fnmatch.fnmatch(part, p) for part in parts) for p in patterns)


def _variable_names(meta: dict, problems: list[str]) -> Optional[list[str]]:
    listed = meta.get("variableMeasured")
    if not isinstance(listed, list) or not listed:
        problems.append(f"{DESCRIPTION}: variableMeasured must be a non-empty list of the data files' column names")
        return None
    names = []
    for k, item in enumerate(listed, 1):
        if isinstance(item, str) and item:
            names.append(item)
        elif isinstance(item, dict):
            kind = item.get("@type", item.get("type"))
            if kind not in ("PropertyValue", "https://schema.org/PropertyValue"):
                problems.append(f"{DESCRIPTION}: variableMeasured item {k}: an object must have @type "
                                f"PropertyValue, got {kind!r}")
            elif not isinstance(item.get("name"), str) or not item["name"]:
                problems.append(f"{DESCRIPTION}: variableMeasured item {k}: a PropertyValue needs a name (the column)")
            else:
                names.append(item["name"])
        else:
            problems.append(f"{DESCRIPTION}: variableMeasured item {k}: expected a column name or a PropertyValue "
                            f"object, got {json.dumps(item)}")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        problems.append(f"{DESCRIPTION}: variableMeasured lists {twice[0]!r} twice")
    return names


def _check_description(root: Path, problems: list[str]) -> Optional[list[str]]:
    """The column names ``dataset_description.json`` lists (None when it cannot say); problems appended."""
    path = root / DESCRIPTION
    if not path.is_file():
        problems.append(f"no {DESCRIPTION} at the dataset's root (the metadata every Psych-DS dataset has)")
        return None
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        problems.append(f"{DESCRIPTION}: not UTF-8 text")
        return None
    except json.JSONDecodeError as exc:
        problems.append(f"{DESCRIPTION}: not valid JSON ({exc.msg} at line {exc.lineno} column {exc.colno})")
        return None
    if not isinstance(meta, dict):
        problems.append(f"{DESCRIPTION}: expected a JSON object, got {type(meta).__name__}")
        return None
    context = meta.get("@context")
    if context not in SCHEMA_ORG:
        problems.append(f"{DESCRIPTION}: @context must be schema.org (\"https://schema.org/\"), got {context!r}")
    kind = meta.get("@type", meta.get("type"))
    if kind not in ("Dataset", "https://schema.org/Dataset"):
        problems.append(f"{DESCRIPTION}: @type must be Dataset, got {kind!r}")
    for key in ("name", "description"):
        if not isinstance(meta.get(key), str) or not meta[key].strip():
            problems.append(f"{DESCRIPTION}: {key} must be a non-empty string (a required field)")
    return _variable_names(meta, problems)


def _check_csv(path: Path, where: str, problems: list[str]) -> Optional[list[str]]:
    """The header of the data file ``path`` (None when it has none); its problems appended."""
    try:
        with open(path, encoding="utf-8", newline="") as fh:
            reader = csv.reader(fh, strict=True)
            header = next(reader, None)
            if not header or not any(header):
                problems.append(f"{where}: no header row (the first row names the columns)")
                return None
            twice = sorted({n for n in header if header.count(n) > 1})
            if twice:
                problems.append(f"{where}: the header names column {twice[0]!r} twice")
            if "" in header:
                problems.append(f"{where}: the header has an empty column name")
            ids, row_id = set(), header.index("row_id") if "row_id" in header else None
            for row in reader:
                if len(row) != len(header):
                    problems.append(f"{where} line {reader.line_num}: {len(row)} cells, but the header names "
                                    f"{len(header)} columns")
                    break
                if row_id is not None:
                    if row[row_id] in ids:
                        problems.append(f"{where} line {reader.line_num}: row_id {row[row_id]!r} again (row_id "
                                        "must be unique)")
                        break
                    ids.add(row[row_id])
            return header
    except UnicodeDecodeError:
        problems.append(f"{where}: not UTF-8 text")
    except csv.Error as exc:
        problems.append(f"{where}: not valid CSV ({exc})")
    return None


def check_dataset(root: str | os.PathLike) -> list[str]:
    """What makes ``root`` no valid Psych-DS dataset, one line each (empty when it is valid).

    The standard's rules: ``dataset_description.json`` at the root, valid JSON with ``@context``
    schema.org, ``@type`` Dataset and non-empty ``name``, ``description`` and ``variableMeasured``
    (column names or ``PropertyValue`` objects with a name); a ``data/`` folder holding at least one
    data file; data file names keyword-value pairs ending ``_data.csv``; data files UTF-8 CSV with a
    header row, no column named twice, every row as many cells as the header, ``row_id`` unique; every
    column listed in ``variableMeasured``. And this package's: every listed variable is a column of
    some data file, and ``data/`` holds data files only (besides what ``.psychdsignore`` lists and
    hidden files): a sidecar or folder metadata file, which this reader would not apply, is refused.
    """
    root = Path(root)
    if not root.is_dir():
        return [f"{root} is not a folder (a Psych-DS dataset is a folder with {DESCRIPTION} and {DATA}/)"]
    problems: list[str] = []
    listed = _check_description(root, problems)
    data = root / DATA
    if not data.is_dir():
        problems.append(f"no {DATA}/ folder (the data files go in it)")
        return problems
    patterns = _ignored(root)
    columns: dict[str, str] = {}
    files = 0
    for path in sorted(data.rglob("*")):
        relative = path.relative_to(root).as_posix()
        if path.is_dir() or any(part.startswith(".") for part in path.relative_to(data).parts):
            continue
        if _is_ignored(relative, patterns):
            continue
        if path.name.endswith("_data.json") or path.name == "directory_metadata.json":
            problems.append(f"{relative}: metadata for part of the data, which this reader does not apply; move "
                            f"what it says into {DESCRIPTION}")
            continue
        if not path.name.endswith(".csv"):
            problems.append(f"{relative}: not a data file (data files are CSV, named ..._data.csv); remove it, "
                            f"or list it in {IGNORE}")
            continue
        if not DATA_FILE.fullmatch(path.name):
            problems.append(f"{relative}: a data file's name must be keyword-value pairs ending _data.csv, e.g. "
                            "study-overhang_subject-P1_data.csv (keywords a-z, values letters and digits)")
            continue
        files += 1
        for column in _check_csv(path, relative, problems) or []:
            columns.setdefault(column, relative)
    if not files:
        problems.append(f"{DATA}/ holds no data file (..._data.csv)")
    if listed is not None:
        unlisted = [c for c in columns if c not in listed]
        if unlisted:
            problems.append(f"{columns[unlisted[0]]}: column {unlisted[0]!r} is not in {DESCRIPTION}'s "
                            "variableMeasured (every column must be)")
        unused = [n for n in listed if n not in columns]
        if unused and files:
            problems.append(f"{DESCRIPTION}: variableMeasured lists {unused[0]!r}, a column of no data file")
    return problems


def data_files(root: str | os.PathLike) -> list[Path]:
    """The data files of the dataset ``root``, sorted; :class:`PsychDSError` naming the first problem
    (and how many more) when it is not a valid dataset."""
    root = Path(root)
    problems = check_dataset(root)
    if problems:
        more = f" (and {len(problems) - 1} more problem{'s' * (len(problems) > 2)})" if len(problems) > 1 else ""
        raise PsychDSError(f"{root}: not a valid Psych-DS dataset: {problems[0]}{more}; check it with "
                           f"python -m overhang_framework.behaviour.psychds {root}")
    patterns = _ignored(root)
    return sorted(p for p in (root / DATA).rglob("*_data.csv")
                  if DATA_FILE.fullmatch(p.name) and not _is_ignored(p.relative_to(root).as_posix(), patterns)
                  and not any(part.startswith(".") for part in p.relative_to(root / DATA).parts))
