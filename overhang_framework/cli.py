"""Command-line entry: the ``plugins`` listing, override checks, then the Hydra app."""

from __future__ import annotations

import json
import sys
from typing import Optional, Sequence

from overhang_framework.errors import OverhangError, UnknownPluginError

GROUPS = ("world", "predictor", "planner", "value", "condition", "tasks")


def list_plugins(as_json: bool = False) -> str:
    from overhang_framework.plugins import describe_plugins

    rows = describe_plugins()
    if as_json:
        return json.dumps(rows, indent=2)
    lines = []
    for row in rows:
        lines.append(f"{row['plugin']}  ({row['package']} {row['version']})".rstrip())
        for kind, names in row["registers"].items():
            lines.append(f"  {kind + 's':<12}{', '.join(names)}")
        for path in row["config_paths"]:
            lines.append(f"  {'configs':<12}{path}")
    return "\n".join(lines)


# Hydra's command-line flags that take the next word as their value.
_VALUE_FLAGS = {"--cfg", "-c", "--package", "-p", "--config-path", "-cp", "--config-name", "-cn",
                "--config-dir", "-cd", "--experimental-rerun", "--shell-completion", "-sc"}
_INFO_TOPICS = {"all", "config", "defaults", "defaults-tree", "plugins", "searchpath"}


def override_words(args: Sequence[str]) -> list[str]:
    """The config overrides among Hydra's command-line words (flags and their values removed)."""
    words, skip = [], False
    for i, arg in enumerate(args):
        if skip:
            skip = False
            continue
        if arg.startswith("-"):
            skip = arg in _VALUE_FLAGS or (
                arg in ("--info", "-i") and i + 1 < len(args) and args[i + 1] in _INFO_TOPICS)
            continue
        words.append(arg)
    return words


def check_overrides(args: Sequence[str]) -> None:
    """Raise :class:`UnknownPluginError` for a config-group choice that is not installed.

    Overrides this cannot read (a glob sweep, a malformed word) are left for
    Hydra to expand or report.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    known: dict[str, list[str]] = {}
    for word in override_words(args):
        try:
            (ov,) = parser.parse_overrides([word])
            if ov.key_or_group not in GROUPS or ov.is_delete() or ov.package:
                continue
            values = list(ov.sweep_string_iterator()) if ov.is_sweep_override() else [ov.value()]
        except Exception:
            continue
        for value in values:
            if not isinstance(value, str):
                continue
            group = ov.key_or_group
            if group not in known:
                from overhang_framework.config import group_options

                known[group] = group_options(group)
            if value not in known[group]:
                raise UnknownPluginError(group, value, known[group])


def main(argv: Optional[Sequence[str]] = None) -> None:
    args = list(sys.argv[1:] if argv is None else argv)
    if args and args[0] == "plugins":
        print(list_plugins(as_json="--json" in args[1:]))
        return
    try:
        check_overrides(args)
    except OverhangError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    from overhang_framework.app import main as app_main

    sys.argv = [sys.argv[0]] + args
    app_main()
