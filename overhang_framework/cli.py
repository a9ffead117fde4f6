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


def check_overrides(args: Sequence[str]) -> None:
    """Raise :class:`UnknownPluginError` for a config-group choice that is not installed."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        overrides = OverridesParser.create().parse_overrides([a for a in args if not a.startswith("-")])
    except Exception:
        return  # malformed overrides are Hydra's to report
    for ov in overrides:
        group = ov.key_or_group
        if group not in GROUPS or ov.is_delete() or ov.package:
            continue
        if ov.is_sweep_override():
            values = list(ov.sweep_string_iterator())
        else:
            values = [ov.value()]
        known = None
        for value in values:
            if not isinstance(value, str):
                continue
            if known is None:
                from overhang_framework.config import group_options

                known = group_options(group)
            if value not in known:
                raise UnknownPluginError(group, value, known)


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
