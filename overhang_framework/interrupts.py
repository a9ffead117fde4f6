"""Ctrl-C that a run still sees when Python drops the handler's exception."""

from __future__ import annotations

import signal
import threading

_CTRL_C: list = []
"""The SIGINTs this process received once :func:`remember_ctrl_c` ran."""


def remember_ctrl_c() -> None:
    """From now on, remember every Ctrl-C as well as raising :class:`KeyboardInterrupt` for it.

    A handler's exception raised while Python runs a finaliser (or while a C extension imports) is
    dropped, and the run would go on as if the key had not been pressed; the run checks the record
    before its first episode and between episodes. Main thread only; a handler other than Python's
    default is left alone."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return

    def interrupt(signum, frame):
        _CTRL_C.append(signum)
        raise KeyboardInterrupt()

    signal.signal(signal.SIGINT, interrupt)


def ctrl_c_seen() -> bool:
    """Whether a SIGINT came since :func:`remember_ctrl_c` (whether or not its exception was dropped)."""
    return bool(_CTRL_C)
