"""Progress for long work: a live bar on a terminal, a plain line now and then anywhere else.

Every long job of the project reports progress through :func:`progress_bar`, which
takes tqdm's arguments. On a terminal it is tqdm's bar. When the stream is not
a terminal (a Slurm log, a pipe, a file), a bar's carriage-return redraws would
fill the log with hundreds of updates, so :class:`LogProgress` writes one
complete line at most every ``OVERHANG_PROGRESS_SECONDS`` seconds (default 60)
and one when the work ends, in tqdm's words::

    placements:  40%|####      | 40/100 [01:00<01:30,  0.67pl/s, episode 9/20 paper08]

``OVERHANG_PROGRESS_SECONDS=0`` writes no line at all off a terminal.
"""

from __future__ import annotations

import os
import sys
import time
from typing import Any, Iterable, Iterator, Optional, TextIO

from tqdm import tqdm

#: Seconds between two lines off a terminal, unless ``OVERHANG_PROGRESS_SECONDS`` says otherwise.
LINE_SECONDS = 60.0


def line_seconds() -> float:
    """Seconds between two lines off a terminal (``OVERHANG_PROGRESS_SECONDS``; 0: no lines)."""
    text = os.environ.get("OVERHANG_PROGRESS_SECONDS")
    if text is None:
        return LINE_SECONDS
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"OVERHANG_PROGRESS_SECONDS must be a number of seconds >= 0, got {text!r}") from None
    if value < 0 or value != value:
        raise ValueError(f"OVERHANG_PROGRESS_SECONDS must be a number of seconds >= 0, got {text!r}")
    return value


def is_terminal(stream: Optional[TextIO]) -> bool:
    try:
        return bool(stream is not None and stream.isatty())
    except (AttributeError, ValueError):
        return False


def progress_bar(iterable: Optional[Iterable] = None, **kwargs: Any):
    """tqdm's bar on a terminal, :class:`LogProgress` elsewhere; ``file`` defaults to stderr."""
    kwargs.setdefault("file", sys.stderr)
    if is_terminal(kwargs["file"]):
        return tqdm(iterable, **kwargs)
    return LogProgress(iterable, **kwargs)


class LogProgress:
    """The part of tqdm's interface the project uses, writing whole lines at a modest rate.

    Accepts tqdm's keyword arguments; those that only shape a terminal bar are
    ignored. A line is written when ``interval`` seconds have passed since the
    last one (checked on each update), and once at :meth:`close` if anything
    happened since the last line.
    """

    def __init__(self, iterable: Optional[Iterable] = None, *, total: Optional[float] = None,
                 desc: Optional[str] = None, unit: str = "it", initial: float = 0, disable: bool = False,
                 file: Optional[TextIO] = None, interval: Optional[float] = None, **_ignored: Any):
        self.iterable = iterable
        if total is None and iterable is not None:
            try:
                total = len(iterable)  # type: ignore[arg-type]
            except TypeError:
                total = None
        self.total, self.desc, self.unit = total, desc or "", unit
        self.n = initial
        self.initial = initial
        self.file = file if file is not None else sys.stderr
        self.interval = line_seconds() if interval is None else interval
        self.disable = disable or self.interval == 0
        self.postfix = ""
        self.start = time.monotonic()
        self.last_line = self.start
        self.lines = 0
        self._dirty = False
        self.closed = False

    def __iter__(self) -> Iterator:
        for item in self.iterable or ():
            yield item
            self.update(1)
        self.close()

    def __len__(self) -> int:
        return int(self.total or 0)

    def __enter__(self) -> "LogProgress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def update(self, n: float = 1) -> None:
        if n:
            self.n += n
            self._dirty = True
        self._maybe_write()

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        self.postfix = str(s)
        self._dirty = True
        self._maybe_write()

    def set_postfix(self, ordered_dict: Optional[dict] = None, refresh: bool = True, **kwargs: Any) -> None:
        items = {**(ordered_dict or {}), **kwargs}
        self.set_postfix_str(", ".join(f"{k}={v}" for k, v in items.items()), refresh)

    def set_description(self, desc: Optional[str] = None, refresh: bool = True) -> None:
        self.desc = desc or ""

    def refresh(self) -> None:
        self._maybe_write()

    def _maybe_write(self) -> None:
        if not self.disable and time.monotonic() - self.last_line >= self.interval:
            self.write_line()

    def write_line(self) -> None:
        """Write the current state as one line now."""
        if self.disable or self.closed:
            return
        now = time.monotonic()
        text = tqdm.format_meter(self.n, self.total, now - self.start, ncols=None, prefix=self.desc,
                                 unit=self.unit, postfix=self.postfix or None, initial=self.initial)
        try:
            self.file.write(text + "\n")
            self.file.flush()
        except (OSError, ValueError):
            self.disable = True  # the stream went away; progress is not worth failing over
            return
        self.last_line = now
        self.lines += 1
        self._dirty = False

    def close(self) -> None:
        if self.closed:
            return
        if self._dirty:
            self.write_line()
        self.closed = True
