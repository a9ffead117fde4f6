"""Order dependency of towers: ``python -m overhang_framework.order_dependency TOWERS [OVERRIDES...]``.

``TOWERS`` is read as by ``python -m overhang_framework.check``: a JSON Lines
file (``-`` for standard input), one tower per line as
``{"blocks": [[width, x, layer], ...]}`` with the ground block first. For
every tower, in input order, one JSON object is written to standard output:
``{"valid_orders": V, "stable_orders": S, "gamma": G}``, where ``G = 1 - S / V``
is null when the tower has no valid construction order. The world is that of
the composed run config with the usual overrides (e.g. ``world.physics=static``);
a malformed line or override stops the command with one ``error: ...`` line and
exit status 2. Progress goes to standard error when the physics takes more than
one batch. What is counted and how: :mod:`overhang_framework.behaviour.order_dependency`.
"""

from __future__ import annotations

from typing import Optional, Sequence

from overhang_framework.behaviour.order_dependency import order_counts_many
from overhang_framework.check import tower_command
from overhang_framework.geometry import Geometry
from overhang_framework.results import readable

#: Partial towers per batched physics call.
CHUNK = 512


def main(argv: Optional[Sequence[str]] = None) -> int:
    def answer(world, towers: list[Geometry], quiet: bool) -> list[dict]:
        counts = order_counts_many(towers, world, chunk=CHUNK, show_progress=not quiet)
        return [readable(c.as_dict()) for c in counts]

    return tower_command(argv, "python -m overhang_framework.order_dependency", __doc__.split("\n\n")[0], answer)


if __name__ == "__main__":
    raise SystemExit(main())
