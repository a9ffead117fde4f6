"""Ctrl-C that a run still sees when Python drops the handler's exception."""

from __future__ import annotations

import contextlib
import signal
import threading
from typing import Iterator

_CTRL_C: list = []
"""The SIGINTs that came while :func:`remember_ctrl_c` held and that no run has acted on yet."""


@contextlib.contextmanager
def remember_ctrl_c() -> Iterator[None]:
    """For the duration, remember every Ctrl-C as well as raising :class:`KeyboardInterrupt` for it.

    A handler's exception raised while Python runs a finaliser (or while a C extension imports) is
    dropped, and the run would go on as if the key had not been pressed; the run checks the record
    (:func:`stop_if_ctrl_c`) before its first episode and between episodes. Main thread only; a handler
    other than Python's default is left alone. On exit the previous handler is back and the record empty."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return

    def interrupt(signum, frame):
        _CTRL_C.append(signum)
        raise KeyboardInterrupt()

    previous = signal.signal(signal.SIGINT, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _CTRL_C.clear()


def ctrl_c_seen() -> bool:
    """Whether a SIGINT came while :func:`remember_ctrl_c` held (whether or not its exception was dropped)."""
    return bool(_CTRL_C)


def stop_if_ctrl_c() -> None:
    """Raise the :class:`KeyboardInterrupt` of a Ctrl-C whose own exception was dropped (once)."""
    if _CTRL_C:
        _CTRL_C.clear()
        raise KeyboardInterrupt()
