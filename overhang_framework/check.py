"""Check towers with the world's physics: ``python -m overhang_framework.check TOWERS [OVERRIDES...]``.

``TOWERS`` is a JSON Lines file (``-`` for standard input), one tower per line
as ``{"blocks": [[width, x, layer], ...]}`` with the ground block first
(layer 0). Blank lines are skipped. For every tower, in input order, one JSON
object ``{"stable": true|false}`` is written to standard output.

The physics is the world of the composed run config, chosen with the usual
overrides, e.g. ``world.physics=pybullet world.pybullet.early_stop=false`` for
the full-window reference or ``world.physics=static``. The whole input is
read and checked before any physics runs; a malformed line stops the command
with ``error: FILE line N: <what is wrong>`` (``standard input line N`` for ``-``) and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any, Callable, Iterable, Optional, Sequence

from overhang_framework.geometry import Block, Geometry, IllegalWidth, check_width
from overhang_framework.results import json_line


class BadTower(ValueError):
    """A line of TOWERS that is not a tower."""


def parse_tower(text: str) -> Geometry:
    """The tower of one JSON Lines line; :class:`BadTower` says what is wrong."""
    try:
        obj = json_line(text)
    except ValueError as exc:
        raise BadTower(str(exc)) from None
    if not isinstance(obj, dict) or "blocks" not in obj:
        raise BadTower('expected an object {"blocks": [[width, x, layer], ...]}')
    rows = obj["blocks"]
    if not isinstance(rows, list) or not rows:
        raise BadTower('"blocks" must be a non-empty list of [width, x, layer]')
    blocks = []
    for k, row in enumerate(rows, 1):
        if not isinstance(row, list) or len(row) != 3:
            raise BadTower(f"block {k} must be [width, x, layer], got {json.dumps(row)}")
        width, x, layer = row
        if any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in row):
            raise BadTower(f"block {k} must hold three finite numbers, got {json.dumps(row)}")
        try:
            width = check_width(width)
        except IllegalWidth as exc:
            raise BadTower(f"block {k}: {exc}") from None
        if float(layer) != int(layer) or layer < 0:
            raise BadTower(f"block {k}: layer must be a whole number >= 0, got {layer!r}")
        blocks.append(Block(width, float(x), int(layer)))
    if blocks[0].layer != 0:
        raise BadTower(f"the first block must be the ground block (layer 0), got layer {blocks[0].layer}")
    return Geometry(tuple(blocks))


def read_towers(lines) -> list[Geometry]:
    """Every tower of the JSON Lines ``lines``; :class:`BadTower` names the first bad line."""
    towers = []
    for number, text in enumerate(lines, 1):
        if not text.strip():
            continue
        try:
            towers.append(parse_tower(text))
        except BadTower as exc:
            raise BadTower(f"line {number}: {exc}") from None
    return towers


def build_world(overrides: Sequence[str]):
    """The world of the run config composed with ``overrides``, built through the plugin registry."""
    from omegaconf import OmegaConf

    from overhang_framework.plugins import Registry
    from overhang_framework.preflight import compose_checked

    cfg = compose_checked(list(overrides))
    return Registry().create("world", OmegaConf.to_container(cfg.world, resolve=True))


def stable_batch(world, geometries: Sequence[Geometry]) -> list[bool]:
    """The world's verdict for every geometry: one ``stable_batch`` call when its backend has one."""
    backend = getattr(world, "backend", None)
    if backend is not None and hasattr(backend, "stable_batch"):
        return [bool(v) for v in backend.stable_batch(list(geometries))]
    return [bool(world.is_stable(g)) for g in geometries]


def verdicts(world, towers: Sequence[Geometry], chunk: int = 256, progress: bool = True) -> list[bool]:
    """The world's verdict for every tower, asked in batches of ``chunk``."""
    from tqdm import tqdm

    out: list[bool] = []
    with tqdm(total=len(towers), desc="towers", unit="tower", disable=not progress, file=sys.stderr) as bar:
        for start in range(0, len(towers), chunk):
            part = towers[start:start + chunk]
            out.extend(stable_batch(world, part))
            bar.update(len(part))
    return out


class UsageError(ValueError):
    """A mistake in a command's input or overrides; the message is the line printed after ``error: ``."""


def load(path: str, overrides: Sequence[str]) -> tuple[list[Geometry], Any]:
    """Every tower of the TOWERS file ``path`` (``-``: standard input), then the world of ``overrides``.

    The whole input is read before the world is built; any mistake raises
    :class:`UsageError` with its one-line message (``FILE line N: ...``,
    ``FILE: cannot read it ...``, or the config's own message).
    """
    name = "standard input" if path == "-" else path
    try:
        if path == "-":
            towers = read_towers(sys.stdin)
        else:
            with open(path, encoding="utf-8") as fh:
                towers = read_towers(fh)
    except BadTower as exc:
        raise UsageError(f"{name} {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"{name}: cannot read it ({getattr(exc, 'strerror', None) or exc})") from None
    try:
        world = build_world(overrides)
    except Exception as exc:  # a bad override or parameter: one line, as the main job reports it
        raise UsageError(" ".join(str(exc).split()) or type(exc).__name__) from None
    return towers, world


Answer = Callable[[Any, list[Geometry], bool], Iterable[dict]]
"""What a TOWERS command computes: ``(world, towers, quiet)`` to one JSON object per tower."""


def tower_command(argv: Optional[Sequence[str]], prog: str, description: str, answer: Answer) -> int:
    """Run a command of the form ``prog TOWERS [OVERRIDES...] [--quiet]``; the exit status.

    Reads the towers and builds the world (:func:`load`; a mistake prints
    ``error: ...`` and gives 2), writes one JSON line per object ``answer``
    returns, and closes the world's backend however the work ends.
    """
    ap = argparse.ArgumentParser(prog=prog, description=description)
    ap.add_argument("towers", metavar="TOWERS", help="JSON Lines file of towers, or - for standard input")
    ap.add_argument("overrides", nargs="*", metavar="OVERRIDE",
                    help="config overrides, as for the main job (e.g. world.physics=static)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    args = ap.parse_intermixed_args(argv)
    try:
        towers, world = load(args.towers, args.overrides)
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        results = list(answer(world, towers, args.quiet))
    finally:
        close = getattr(getattr(world, "backend", None), "close", None)
        if close is not None:
            close()
    sys.stdout.write("".join(json.dumps(r) + "\n" for r in results))
    sys.stdout.flush()
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    def answer(world, towers: list[Geometry], quiet: bool) -> list[dict]:
        return [{"stable": v} for v in verdicts(world, towers, progress=not quiet)]

    return tower_command(argv, "python -m overhang_framework.check", __doc__.split("\n\n")[0], answer)


if __name__ == "__main__":
    raise SystemExit(main())
