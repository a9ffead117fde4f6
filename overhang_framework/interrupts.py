"""Ctrl-C that a run still sees when Python drops the handler's exception."""

from __future__ import annotations

import contextlib
import signal
import threading
from typing import Iterator

_CTRL_C: list = []
"""The SIGINTs that came while :func:`remember_ctrl_c` held and that no run has acted on yet."""


@contextlib.contextmanager
def raising(signum: int, exception: type, record: list, replace_own: bool = True) -> Iterator[list]:
    """For the duration, a signal ``signum`` raises ``exception`` and is appended to ``record``.

    A handler's exception raised while Python runs a finaliser (or while a C extension imports) is dropped,
    so a run also checks ``record`` between its steps. Main thread only; with ``replace_own`` false, a handler
    other than Python's default is left alone. On exit the previous handler is back. Yields ``record``."""
    default = signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL
    if threading.current_thread() is not threading.main_thread() or \
            (not replace_own and signal.getsignal(signum) is not default):
        yield record
        return

    def handler(number, frame):
        record.append(number)
        raise exception()

    previous = signal.signal(signum, handler)
    try:
        yield record
    finally:
        signal.signal(signum, previous)


@contextlib.contextmanager
def remember_ctrl_c() -> Iterator[None]:
    """For the duration, remember every Ctrl-C as well as raising :class:`KeyboardInterrupt` for it
    (:func:`raising`); the run checks the record (:func:`stop_if_ctrl_c`) before its first episode and
    between episodes. A handler of the program's own is left alone. On exit the record is empty."""
    try:
        with raising(signal.SIGINT, KeyboardInterrupt, _CTRL_C, replace_own=False):
            yield
    finally:
        _CTRL_C.clear()


def ctrl_c_seen() -> bool:
    """Whether a SIGINT came while :func:`remember_ctrl_c` held (whether or not its exception was dropped)."""
    return bool(_CTRL_C)


def stop_if_ctrl_c() -> None:
    """Raise the :class:`KeyboardInterrupt` of a Ctrl-C whose own exception was dropped (once)."""
    if _CTRL_C:
        _CTRL_C.clear()
        raise KeyboardInterrupt()
