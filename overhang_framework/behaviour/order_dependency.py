"""Order dependency of a finished tower: the share of its construction orders that fall on the way.

A *valid order* of a tower places its ground block (its first block, on layer
0) first and then every other block once, each legal under the world's rules
when it is placed (``World.is_legal``: it rests on a block already placed one
layer below and overlaps no placed block of its layer). A *stable order* is a
valid order after every placement of which the partial tower stands under the
world's physics, the ground block alone and the finished tower included. The
paper's order dependency is

    Γ = 1 − |stable orders| / |valid orders|

0 when every way of building the tower stands, close to 1 when only a few
orders do (a counterweight that must come before its cantilever). It is
undefined (``None``) for a tower with no valid order, such as one with a
floating block.

The blocks' final positions are fixed, so a partial tower is determined by
which blocks it holds. Orders are counted by dynamic programming over subsets
of the blocks (bit masks, bit ``i`` for block ``i``, the ground block's bit
always set): the number of valid orders reaching ``S | {b}`` gains those
reaching ``S`` whenever ``b`` can be placed on ``S``, and the stable count does
the same through standing subsets only. Blocks are distinct even where their
widths are equal, so orders are permutations of distinct blocks. Only the
subsets on some valid order (reachable from the ground block and able to grow
into the whole tower) are checked for stability, each once, and
:func:`order_counts_many` asks for the subsets of all its towers together,
deduplicated by :attr:`~overhang_framework.geometry.Geometry.key`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping, Optional, Sequence

from overhang_framework.check import stable_batch
from overhang_framework.geometry import Action, Geometry
from overhang_framework.interfaces import State, World
from overhang_framework.progress import progress_bar


@dataclass(frozen=True)
class OrderCounts:
    """How many valid and stable construction orders a tower has, and its order dependency."""

    valid_orders: int
    stable_orders: int
    gamma: Optional[float]

    def as_dict(self) -> dict:
        """The JSON object of the command: ``valid_orders``, ``stable_orders``, ``gamma`` (null: no valid order)."""
        return {"valid_orders": self.valid_orders, "stable_orders": self.stable_orders, "gamma": self.gamma}


@dataclass(frozen=True)
class OrderGraph:
    """The valid orders of ``tower`` as a graph over subsets of its blocks.

    ``steps`` maps every subset on some valid order (a bit mask; bit ``i`` is
    ``tower.blocks[i]``) to the subsets one legal placement further on some
    valid order, subsets of fewer blocks first; it is empty when the tower has
    no valid order.
    """

    tower: Geometry
    steps: Mapping[int, tuple[int, ...]]

    @property
    def full(self) -> int:
        """The mask of the whole tower."""
        return (1 << len(self.tower.blocks)) - 1

    def partial(self, mask: int) -> Geometry:
        """The partial tower of the blocks in ``mask``, in the tower's block order."""
        return Geometry(tuple(b for i, b in enumerate(self.tower.blocks) if mask >> i & 1))

    def orders(self, standing: Callable[[int], bool] = lambda mask: True) -> int:
        """The number of valid orders all of whose partial towers are ``standing``."""
        if not self.steps:
            return 0
        ways = dict.fromkeys(self.steps, 0)
        ways[1] = int(standing(1))
        for mask, nexts in self.steps.items():
            if ways[mask]:
                for n in nexts:
                    if standing(n):
                        ways[n] += ways[mask]
        return ways[self.full]


def order_graph(tower: Geometry, world: World) -> OrderGraph:
    """The graph of the valid orders of ``tower`` under ``world``'s rules (no physics).

    Raises ``ValueError`` for a tower whose first block is not a ground block (layer 0).
    """
    blocks = tower.blocks
    if not blocks or blocks[0].layer != 0:
        raise ValueError("a tower starts with its ground block (layer 0)")
    graph = OrderGraph(tower, {})
    forward: dict[int, tuple[int, ...]] = {}
    level = [1]
    while level:
        following: dict[int, None] = {}
        for mask in level:
            placed = graph.partial(mask)
            forward[mask] = tuple(
                mask | 1 << i for i, b in enumerate(blocks)
                if not mask >> i & 1 and world.is_legal(State(placed, (b.width,)), Action(b.x, b.layer)))
            following.update(dict.fromkeys(forward[mask]))
        level = list(following)
    useful = {graph.full} if graph.full in forward else set()
    for mask in reversed(forward):
        if any(n in useful for n in forward[mask]):
            useful.add(mask)
    return OrderGraph(tower, {m: tuple(n for n in nexts if n in useful)
                              for m, nexts in forward.items() if m in useful})


def order_counts_many(towers: Sequence[Geometry], world: World, chunk: Optional[int] = None,
                      show_progress: bool = False) -> list[OrderCounts]:
    """:func:`order_counts` of every tower, with one physics check per distinct partial tower.

    The partial towers on the valid orders of all ``towers`` are deduplicated
    by their canonical key and checked with the world's batched verdicts in
    calls of ``chunk`` geometries (``None``: one call for all). With
    ``show_progress``, progress goes to standard error when there is more than
    one call.
    """
    graphs = [order_graph(t, world) for t in towers]
    partials: dict[tuple, Geometry] = {}
    for graph in graphs:
        for mask in graph.steps:
            g = graph.partial(mask)
            partials.setdefault(g.key, g)
    todo = list(partials.values())
    size = chunk or max(1, len(todo))
    verdict: dict[tuple, bool] = {}
    with progress_bar(total=len(todo), desc="partial towers", unit="tower",
                      disable=not show_progress or len(todo) <= size) as bar:
        for start in range(0, len(todo), size):
            part = todo[start:start + size]
            verdict.update((g.key, v) for g, v in zip(part, stable_batch(world, part)))
            bar.update(len(part))
    out = []
    for graph in graphs:
        valid = graph.orders()
        stable = graph.orders(lambda mask: verdict[graph.partial(mask).key])
        out.append(OrderCounts(valid, stable, 1 - stable / valid if valid else None))
    return out


def order_counts(tower: Geometry, world: World) -> OrderCounts:
    """The valid and stable construction orders of ``tower`` under ``world``, and Γ (``None``: no valid order)."""
    return order_counts_many([tower], world)[0]
