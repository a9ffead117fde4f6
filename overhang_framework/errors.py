"""Errors a user can cause, each with a one-line message naming what is wrong and what is allowed."""

from __future__ import annotations

import difflib
from typing import Sequence


def closest(word: str, choices: Sequence[str]) -> list[str]:
    """The choice closest to ``word``, ignoring case (``k`` finds ``K``): one, or none when none is close."""
    by_lower: dict[str, str] = {}
    for choice in choices:
        by_lower.setdefault(choice.lower(), choice)
    return [by_lower[m] for m in difflib.get_close_matches(word.lower(), list(by_lower), n=1)]


def first_line(error: BaseException) -> str:
    """``Type: the first line of the message`` of ``error``, for a one-line report."""
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0]}" if text else type(error).__name__


class OverhangError(Exception):
    """Base class of errors caused by input; the CLI prints the message on one line and exits 2."""


class UnknownPluginError(OverhangError, LookupError):
    def __init__(self, kind: str, name: str, installed: Sequence[str]):
        self.kind, self.name, self.installed = kind, name, list(installed)
        listing = ", ".join(self.installed) if self.installed else "(none)"
        plural = kind if kind.endswith("s") else f"{kind}s"
        super().__init__(f"unknown {kind} {name!r}; installed {plural}: {listing}")


class UnknownPluginsError(OverhangError, LookupError):
    """Several unknown names at once, reported together: ``unknown predictor 'a' and planner 'b'; ...``."""

    def __init__(self, errors: Sequence[UnknownPluginError]):
        self.errors = list(errors)
        names = " and ".join(f"{e.kind} {e.name!r}" for e in self.errors)
        listings = []
        for e in self.errors:
            plural = e.kind if e.kind.endswith("s") else f"{e.kind}s"
            listing = f"installed {plural}: {', '.join(e.installed) if e.installed else '(none)'}"
            if listing not in listings:
                listings.append(listing)
        super().__init__(f"unknown {names}; {'; '.join(listings)}")


class ConfigError(OverhangError, ValueError):
    """A config value a model or the run refuses."""


class TaskError(OverhangError, ValueError):
    """A malformed task or task set."""


class IllegalActionError(OverhangError, ValueError):
    """An action that breaks the placement rules."""
