"""The run directory: which config its episodes belong to, resuming into it, starting it afresh.

A run writes ``run.json`` (the config that decides its results) before its first
episode. Running again into a directory that already holds episodes:

* of the same config, continues: finished episodes are kept as they are and
  only the missing ones run;
* of another config, is refused with one line naming the differences, unless
  ``overwrite=true``, which removes the earlier results first.

Settings that do not change results (``progress``, ``overwrite``, ``jobs``)
are not part of the config compared.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Optional

from overhang_framework.errors import OverhangError
from overhang_framework.results import atomic_write_json, readable

RUN_FILE = "run.json"
LOCK_FILE = ".run.lock"
EPISODES = "episodes.jsonl"
RESULT_FILES = (EPISODES, EPISODES + ".partial", "metrics.json", RUN_FILE)
#: Top-level settings that change how a run looks, not what it computes.
PRESENTATION_KEYS = ("progress", "overwrite", "jobs")


def _same_file(fh, path: Path) -> bool:
    """Whether the open file ``fh`` is still the file at ``path``."""
    try:
        return os.path.samestat(os.fstat(fh.fileno()), os.stat(path))
    except FileNotFoundError:
        return False


class RunDirError(OverhangError):
    """A run directory that holds results this run may not continue or replace."""


def run_config(directory: str | Path) -> dict:
    """The config a run directory's ``run.json`` holds; empty when the file is missing or is not a run's."""
    try:
        config = json.loads((Path(directory) / RUN_FILE).read_text()).get("config")
    except (OSError, ValueError, AttributeError):
        return {}
    return dict(config) if isinstance(config, dict) else {}


def result_config(cfg: Mapping[str, Any]) -> dict:
    """The part of a resolved run config that decides its results."""
    return {k: v for k, v in cfg.items() if k not in PRESENTATION_KEYS}


def flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    """A nested config as one level of dotted keys (``{"world": {"physics": "static"}}`` ->
    ``{"world.physics": "static"}``)."""
    if isinstance(data, Mapping):
        out: dict[str, Any] = {}
        for key, value in data.items():
            out.update(flatten(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: data}


#: Settings added to the configs after runs were made, by their last key, with the value that does what those
#: runs did: a run directory written without one is the same config as one with that value.
ADDED_LATER = {"lazy": False, "settle_batch": 16, "risk": 0.0, "risk_form": "power", "defer": True}


def config_differences(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """``key: old -> new`` for every leaf that differs (added and removed keys included), the
    most telling first: model names and top-level settings, then by depth. A setting of
    :data:`ADDED_LATER` that ``old`` lacks and ``new`` has at its former behaviour's value is no difference."""
    a, b = flatten(old), flatten(new)
    missing = object()
    diffs = []
    # the most telling first: model names and top-level settings, then shallow keys, then the rest
    order = sorted(set(a) | set(b), key=lambda k: (not k.endswith(".name") and "." in k, k.count("."), k))
    for key in order:
        va, vb = a.get(key, missing), b.get(key, missing)
        leaf = key.rsplit(".", 1)[-1]
        if va is missing and leaf in ADDED_LATER and vb == ADDED_LATER[leaf] and type(vb) is type(ADDED_LATER[leaf]):
            continue
        if va != vb:
            show = lambda v: "(unset)" if v is missing else json.dumps(v)  # noqa: E731
            diffs.append(f"{key}: {show(va)} -> {show(vb)}")
    return diffs


def _read_records(path: Path, notes: Optional[list[str]] = None) -> list[dict]:
    """Complete JSON lines of ``path``; an incomplete last line (a write cut short) is cut off the file,
    and a note saying so is added to ``notes``."""
    records, good_end = [], 0
    with open(path, "rb") as fh:
        data = fh.read()
    for raw in data.splitlines(keepends=True):
        try:
            if not raw.endswith(b"\n"):
                raise ValueError("unterminated line")
            if raw.strip():
                records.append(json.loads(raw))
        except ValueError:
            if good_end + len(raw) == len(data):
                with open(path, "r+b") as fh:
                    fh.truncate(good_end)
                if notes is not None:
                    notes.append(f"{path} line {len(records) + 1} was cut short (the run stopped while writing "
                                 f"it); dropped it, and its episode runs again")
                break
            raise RunDirError(f"{path} line {len(records) + 1} is not a JSON episode record; "
                              "move the file away or rerun with overwrite=true") from None
        good_end += len(raw)
    return records


class RunDir:
    """The results of one run in ``path``: what is already finished and what config it belongs to.

    ``busy`` replaces the message that refuses a second holder of :meth:`lock`.
    """

    def __init__(self, path: Path | str, busy: Optional[str] = None):
        self.path, self.busy = Path(path), busy
        #: What :meth:`prepare` changed in the results it found, one sentence each.
        self.notes: list[str] = []

    @property
    def episodes(self) -> Path:
        return self.path / EPISODES

    @property
    def partial(self) -> Path:
        return self.path / (EPISODES + ".partial")

    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Hold the directory for this run; a second run into it at the same time is refused.

        The lock file exists only while a run holds it: it is removed, still
        locked, when the run ends. A run that opened the file just before it
        was removed finds its lock on a removed file and takes a new one.
        """
        self.path.mkdir(parents=True, exist_ok=True)
        lock_file = self.path / LOCK_FILE
        while True:
            fh = open(lock_file, "a")
            try:
                self._take(fh)
            except BaseException:
                fh.close()
                raise
            if _same_file(fh, lock_file):
                break
            fh.close()  # locked a file that its holder removed as it finished; lock the new one
        try:
            yield
        finally:
            with contextlib.suppress(FileNotFoundError):
                lock_file.unlink()
            fcntl.flock(fh, fcntl.LOCK_UN)
            fh.close()

    def _take(self, fh) -> None:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise RunDirError(self.busy or f"another run is writing to {self.path}; wait for it to end, "
                                           "or use another hydra.run.dir") from None

    def existing_file(self) -> Optional[Path]:
        """The episode file already there (``episodes.jsonl`` or its ``.partial``), if any."""
        present = [p for p in (self.episodes, self.partial) if p.exists()]
        if len(present) == 2:
            raise RunDirError(f"{self.path} holds both {EPISODES} and {EPISODES}.partial; "
                              "keep one of them, or rerun with overwrite=true")
        return present[0] if present else None

    def check_free(self) -> None:
        """Raise when another run holds the directory."""
        try:
            fh = open(self.path / LOCK_FILE)
        except FileNotFoundError:
            return
        with fh:
            self._take(fh)
            fcntl.flock(fh, fcntl.LOCK_UN)

    def check_config(self, config: Mapping[str, Any], overwrite: bool = False) -> None:
        """Raise :class:`RunDirError` when the directory holds results of another (or an unknown)
        config, unless ``overwrite``. Writes nothing."""
        if overwrite or not self.path.exists():
            return
        config = readable(config)  # as run.json holds it
        existing = self.existing_file()
        run_file = self.path / RUN_FILE
        if run_file.exists():
            try:
                previous = json.loads(run_file.read_text())["config"]
            except (ValueError, KeyError, TypeError):
                raise RunDirError(f"{run_file} is not a run description; move it away, "
                                  "or rerun with overwrite=true") from None
            diffs = config_differences(previous, config)
            if diffs:
                shown = "; ".join(diffs[:4]) + (f"; and {len(diffs) - 4} more" if len(diffs) > 4 else "")
                raise RunDirError(f"{self.path} holds results of a different config ({shown}); "
                                  "use another hydra.run.dir, or overwrite=true to replace them")
        elif existing is not None:
            raise RunDirError(f"{self.path} holds episodes of an unknown config (no {RUN_FILE}); "
                              "use another hydra.run.dir, or overwrite=true to replace them")

    def prepare(self, config: Mapping[str, Any], overwrite: bool = False) -> list[dict]:
        """Make the directory ready for ``config``; return the episodes already finished for it.

        Raises :class:`RunDirError` when the directory holds results of another
        config (or of an unknown one) and ``overwrite`` is false.
        """
        self.check_config(config, overwrite)
        config = readable(config)
        self.path.mkdir(parents=True, exist_ok=True)
        if overwrite:
            for name in RESULT_FILES:
                (self.path / name).unlink(missing_ok=True)
        existing = self.existing_file()
        run_file = self.path / RUN_FILE
        if not run_file.exists():
            (self.path / "metrics.json").unlink(missing_ok=True)
            atomic_write_json(run_file, {"config": dict(config)})
        return _read_records(existing, self.notes) if existing is not None else []

    def reopen(self) -> None:
        """Continue an earlier run's episode file: a finished ``episodes.jsonl`` becomes the
        ``.partial`` file again (renamed, not rewritten) until this run ends."""
        if self.episodes.exists() and not self.partial.exists():
            os.replace(self.episodes, self.partial)


def finished_jobs(records: Iterable[Mapping[str, Any]]) -> dict[tuple[int, int], dict]:
    """Finished episodes by ``(task_index, repeat)``."""
    return {(int(r["task_index"]), int(r["repeat"])): dict(r) for r in records}
