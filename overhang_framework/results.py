"""Results on disk: an episode log written as it grows, summaries written atomically."""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Optional

import numpy as np

TIMING_KEYS = ("decision_time", "seconds")
#: Significant digits of the floats written to results: enough for every value a run computes,
#: few enough that 1.1 + 0.6 is written 1.7, not 1.7000000000000002.
SIGNIFICANT_DIGITS = 12


def readable(data: Any) -> Any:
    """``data`` with every float rounded to :data:`SIGNIFICANT_DIGITS` significant digits, for writing.

    The values computed are unchanged; only their last-bit noise is dropped
    from the files (a relative change below 1e-12). A number that does not
    exist (NaN: the mean of no values, the SEM of one) is written as null,
    so the files are strict JSON.
    """
    if isinstance(data, float):
        return float(f"{data:.{SIGNIFICANT_DIGITS}g}") if math.isfinite(data) else None
    if isinstance(data, Mapping):
        return {k: readable(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [readable(v) for v in data]
    if isinstance(data, np.generic):
        return readable(data.item())
    return data


@contextlib.contextmanager
def atomic_output(path: Path | str) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; when the block succeeds, rename it onto ``path``.

    Whatever writes to the temporary path (text, a figure, a binary file) lands
    all at once or not at all. The file gets the usual permissions (0666 less the umask).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix or ".tmp")
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path | str, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same directory and a rename."""
    with atomic_output(path) as tmp:
        with open(tmp, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())


@contextlib.contextmanager
def staged_files(directory: Path | str) -> Iterator[Path]:
    """Yield a temporary directory beside ``directory``; when the block succeeds, move the files written
    into it to ``directory`` (made if need be), each by a rename.

    A command that writes several files leaves all of them or none: a failure
    half-way leaves ``directory`` as it was.
    """
    directory = Path(directory)
    directory.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=directory.parent, prefix=f".{directory.name}."))
    try:
        yield staging
        directory.mkdir(exist_ok=True)
        for path in sorted(staging.iterdir()):
            os.replace(path, directory / path.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def atomic_write_json(path: Path | str, data: Any) -> None:
    """Write ``data`` as indented JSON (floats :func:`readable`), atomically."""
    atomic_write_text(path, json.dumps(readable(data), indent=2, sort_keys=True, allow_nan=False) + "\n")


class EpisodeLog:
    """``episodes.jsonl``, one JSON object per episode.

    Lines go to ``episodes.jsonl.partial`` as episodes finish (flushed, so a
    crash loses nothing already computed); :meth:`close` renames it into place.
    With ``append`` the lines already in ``episodes.jsonl.partial`` are kept
    and new ones follow them.
    """

    def __init__(self, path: Path | str, append: bool = False):
        self.path = Path(path)
        self.partial = self.path.with_name(self.path.name + ".partial")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(self.partial, "a" if append else "w")

    def write(self, record: Mapping[str, Any]) -> None:
        self._fh.write(json.dumps(readable(record), sort_keys=True) + "\n")
        self._fh.flush()

    def close(self) -> None:
        """Rename the finished log into place, its lines in job order (``task_index``, ``repeat``):
        episodes played in parallel, or resumed, finish out of order."""
        self._fh.close()
        with open(self.partial) as fh:
            lines = [line for line in fh if line.strip()]
        ordered = sorted(lines, key=_job_order)
        if ordered != lines:
            with open(self.partial, "w") as fh:
                fh.writelines(ordered)
                fh.flush()
                os.fsync(fh.fileno())
        os.replace(self.partial, self.path)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self._fh.close()


def _job_order(line: str) -> tuple:
    record = json.loads(line)
    return int(record.get("task_index", 0)), int(record.get("repeat", 0))


def json_line(text: str) -> Any:
    """The value of one line of a JSON Lines file; ``ValueError`` with a message naming the column in the line
    (``not JSON (Expecting ',' delimiter at column 12)``), or saying the line is cut short when it ends
    before its value does (a write that stopped half-way)."""
    line = text.rstrip("\r\n")
    try:
        return json.loads(line)
    except json.JSONDecodeError as exc:
        if exc.pos >= len(line.rstrip()) and line.strip():
            raise ValueError(f"not JSON: the line ends at column {len(line)} before its value does "
                             "(cut short?)") from None
        raise ValueError(f"not JSON ({exc.msg} at column {exc.colno})") from None


def read_episodes(path: Path | str) -> list[dict]:
    with open(path) as fh:
        return [json.loads(line) for line in fh if line.strip()]


def mean_sem(values: Iterable[float]) -> tuple[float, float]:
    """Mean and standard error of the mean (NaN where it does not exist: both for no values,
    the SEM for one)."""
    arr = np.asarray(list(values), dtype=float)
    if arr.size == 0:
        return math.nan, math.nan
    sem = float(arr.std(ddof=1) / np.sqrt(arr.size)) if arr.size > 1 else math.nan
    return float(arr.mean()), sem


def median(values: Iterable[float]) -> float:
    """The median (NaN for no values)."""
    arr = np.asarray(list(values), dtype=float)
    return float(np.median(arr)) if arr.size else math.nan


def summarize(episodes: list[dict]) -> dict:
    """The summary of a run: reward, stability, overhang of successes and decision time (mean and SEM of
    each; the decision time's median and maximum too)."""
    rewards = [e["reward"] for e in episodes]
    placements = [s["stable"] for e in episodes for s in e["steps"]]
    succ_overhang = [e["overhang"] for e in episodes if e["stable_throughout"]]
    times = [s["decision_time"] for e in episodes for s in e["steps"]]
    out: dict[str, Any] = {"episodes": len(episodes), "placements": len(placements)}
    for key, values in (
        ("reward", rewards),
        ("stable_placement", [float(p) for p in placements]),
        ("success", [float(e["stable_throughout"]) for e in episodes]),
        ("overhang_successful", succ_overhang),
        ("decision_time", times),
    ):
        mean, sem = mean_sem(values)
        out[f"{key}_mean"], out[f"{key}_sem"] = mean, sem
    out["decision_time_median"] = median(times)
    out["decision_time_max"] = max(times) if times else math.nan
    out["over_time_limit"] = int(sum(s["over_time_limit"] for e in episodes for s in e["steps"]))
    return out


def without_timing(record: Any) -> Any:
    """``record`` with every timing field removed, for comparing runs."""
    if isinstance(record, dict):
        return {k: without_timing(v) for k, v in record.items()
                if k not in TIMING_KEYS and k != "over_time_limit"}
    if isinstance(record, list):
        return [without_timing(v) for v in record]
    return record


_FILE_DIGESTS: dict[tuple, str] = {}


def file_sha256(path: str | Path) -> Optional[str]:
    """The SHA-256 of the bytes of the file at ``path`` (hex), computed once per file and remembered while its
    size and change times stay the same; None when there is no such file."""
    try:
        path = Path(path).expanduser().resolve()
        st = path.stat()
    except OSError:
        return None
    mark = (str(path), st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino)
    known = _FILE_DIGESTS.get(mark)
    if known is None:
        made = hashlib.sha256()
        try:
            with open(path, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 20), b""):
                    made.update(chunk)
        except OSError:
            return None
        known = _FILE_DIGESTS[mark] = made.hexdigest()
    return known
