"""Order dependency Γ: hand-counted towers, agreement with brute force, physics asked once per subset, the command."""

import itertools
import json
import subprocess
import sys
from pathlib import Path

import pytest

from overhang_framework.behaviour.order_dependency import OrderCounts, order_counts, order_counts_many
from overhang_framework.physics.towers import episode_questions, family_towers, random_towers
from overhang_framework.check import build_world
from overhang_framework.geometry import Action, Geometry
from overhang_framework.rules import illegal_reason

ROOT = Path(__file__).resolve().parents[1]

# Each case: blocks [width, x, layer] (block 0 is the ground block, G), the static verdict of every
# partial tower (named by its blocks' indices; every one holds G), and the counts by hand.
CASES = {
    # A vertical stack G, 1, 2, 3, each centred on the one below: block k rests only on block k-1, so
    # the one valid order is G 1 2 3; all its partial towers stand. valid 1, stable 1, Γ = 0.
    "stack": ([[1.2, 0.0, 0], [1.2, 0.0, 1], [0.6, 0.0, 2], [0.6, 0.0, 3]],
              {"0": True, "01": True, "012": True, "0123": True},
              OrderCounts(1, 1, 0.0)),
    # A bridge: pillars 1 (x=-0.6) and 2 (x=+0.6) on G, deck 3 (1.8 wide, x=0) across both. The deck
    # needs one pillar below it, so the valid orders are the 3! = 6 permutations of 1, 2, 3 less the 2
    # that start with 3: G123, G213, G132, G231 (4). A deck on one pillar has its centre 0.3 beyond
    # that pillar's inner edge and falls (013, 023), so G132 and G231 fall. valid 4, stable 2, Γ = 1/2.
    "bridge": ([[1.8, 0.0, 0], [0.6, -0.6, 1], [0.6, 0.6, 1], [1.8, 0.0, 2]],
               {"0": True, "01": True, "012": True, "013": False, "023": False, "0123": True},
               OrderCounts(4, 2, 0.5)),
    # A counterweighted cantilever: arm 1 (1.8 wide, x=0.15) on a 0.6-wide G; on the arm a
    # counterweight 2 (x=-0.6) and a cantilever 3 (x=0.9). Both need the arm, so the valid orders
    # are G123 and G132 (2). With the cantilever alone the arm's load centre is at 0.45, 0.15 beyond
    # G's edge: 013 falls; with the counterweight first it is at 0.15 (012, 0123 stand). valid 2,
    # stable 1 (G123), Γ = 1/2.
    "counterweight": ([[0.6, 0.0, 0], [1.8, 0.15, 1], [1.2, -0.6, 2], [1.2, 0.9, 2]],
                      {"0": True, "01": True, "012": True, "013": False, "0123": True},
                      OrderCounts(2, 1, 0.5)),
    # A clamp: pillar 1 (x=-0.6) and a 1.8-wide block 2 (x=1.05) sticking out beyond G's edge at 0.9,
    # both on G; block 3 (1.8 wide, x=-0.6) on the pillar reaches over block 2's inner end and holds
    # it down. Block 3 needs the pillar or block 2 below it: valid orders G123, G213, G132, G231 (4).
    # Block 2 without the clamp falls (02, 012), block 2 under block 3 without the pillar falls (023);
    # the clamp on the pillar stands (013), and block 2 slid under it stands (0123). valid 4, stable 1
    # (G132), Γ = 3/4.
    "clamp": ([[1.8, 0.0, 0], [0.6, -0.6, 1], [1.8, 1.05, 1], [1.8, -0.6, 2]],
              {"0": True, "01": True, "02": False, "012": False, "013": True, "023": False, "0123": True},
              OrderCounts(4, 1, 0.75)),
    # A clamp no order can build: as above with block 2 at x=1.2 and block 3 a deck at x=0 that rests on
    # the pillar and block 2. Valid orders as above (4), but every order has a partial tower that falls:
    # block 2 alone (02, 012) and the deck on either support alone (013, 023). valid 4, stable 0, Γ = 1.
    "unbuildable clamp": ([[1.8, 0.0, 0], [0.6, -0.6, 1], [1.8, 1.2, 1], [1.8, 0.0, 2]],
                          {"01": True, "02": False, "012": False, "013": False, "023": False, "0123": True},
                          OrderCounts(4, 0, 1.0)),
    # A block floating on layer 2 with nothing on layer 1: no valid order. valid 0, stable 0, Γ undefined.
    "floating": ([[1.2, 0.0, 0], [0.6, 0.0, 2]], {}, OrderCounts(0, 0, None)),
    # The ground block alone: the one order is G, and G stands. valid 1, stable 1, Γ = 0.
    "ground only": ([[1.2, 0.0, 0]], {"0": True}, OrderCounts(1, 1, 0.0)),
}


@pytest.fixture(scope="module")
def static_world():
    return build_world(["world.physics=static"])


def tower(rows) -> Geometry:
    return Geometry.from_tuples(rows)


class Counting:
    """A world that passes everything to ``world`` and records the geometries of each batched check."""

    def __init__(self, world):
        self.world, self.calls = world, []
        self.backend = self

    def is_legal(self, state, action):
        return self.world.is_legal(state, action)

    def stable_batch(self, geometries):
        self.calls.append(list(geometries))
        return self.world.backend.stable_batch(geometries)


@pytest.mark.parametrize("name", list(CASES))
def test_hand_counted_towers(static_world, name):
    rows, verdicts, expected = CASES[name]
    for subset, stands in verdicts.items():
        assert static_world.is_stable(tower([rows[int(i)] for i in subset])) is stands, subset
    assert order_counts(tower(rows), static_world) == expected


class Falling:
    """A world of ``world``'s rules in which nothing stands, without batched physics."""

    def __init__(self, world):
        self.world = world

    def is_legal(self, state, action):
        return self.world.is_legal(state, action)

    def is_stable(self, geometry):
        return False


def test_a_ground_block_that_falls_has_no_stable_order(static_world):
    assert order_counts(tower([[1.2, 0.0, 0]]), Falling(static_world)) == OrderCounts(1, 0, 1.0)
    assert order_counts(tower(CASES["bridge"][0]), Falling(static_world)) == OrderCounts(4, 0, 1.0)


def brute_force(geometry: Geometry, world) -> tuple[OrderCounts, set]:
    """Counts over every permutation of the non-ground blocks, and the block sets of their prefixes."""
    ground, rest = geometry.blocks[0], geometry.blocks[1:]
    valid = stable = 0
    prefixes = set()
    for order in itertools.permutations(rest):
        placed = Geometry((ground,))
        sets = [placed.key]
        stands = world.is_stable(placed)
        for b in order:
            if illegal_reason(placed, b.width, Action(b.x, b.layer)) is not None:
                break
            placed = placed.add(b)
            sets.append(placed.key)
            stands = stands and world.is_stable(placed)
        else:
            valid += 1
            stable += stands
            prefixes.update(sets)
    return OrderCounts(valid, stable, 1 - stable / valid if valid else None), prefixes


def brute_force_towers(world) -> list[Geometry]:
    """Random legal towers (most fall), towers grown by standing steps as in an episode, and bridges."""
    grown = episode_questions(world.backend.stable_batch, per_height=6, seed=3, min_blocks=3, max_blocks=6)
    towers = random_towers(12, seed=11, min_blocks=3, max_blocks=6) + [q.geometry for q in grown]
    return towers + family_towers("indeterminate", 6, seed=2)


def test_dynamic_programming_equals_brute_force_and_checks_each_subset_once(static_world):
    towers = brute_force_towers(static_world)
    expected = [brute_force(t, static_world) for t in towers]
    assert any(0 < c.stable_orders < c.valid_orders for c, _ in expected)  # some orders fall, some stand
    assert any(1 < c.stable_orders == c.valid_orders for c, _ in expected)
    for t, (counts, prefixes) in zip(towers, expected):
        world = Counting(static_world)
        assert order_counts(t, world) == counts
        checked = [g.key for call in world.calls for g in call]
        assert len(world.calls) == 1 and sorted(checked) == sorted(prefixes)
        assert len(checked) <= 2 ** (len(t) - 1)  # the subsets that hold the ground block
    world = Counting(static_world)
    assert order_counts_many(towers, world) == [c for c, _ in expected]
    checked = [g.key for call in world.calls for g in call]
    assert len(world.calls) == 1 and sorted(checked) == sorted(set().union(*(p for _, p in expected)))
    world = Counting(static_world)
    assert order_counts_many(towers, world, chunk=10) == [c for c, _ in expected]
    assert [len(call) for call in world.calls[:-1]] == [10] * (len(world.calls) - 1)


def test_a_tower_must_start_with_its_ground_block(static_world):
    with pytest.raises(ValueError, match="ground block"):
        order_counts(tower([[1.2, 0.0, 1], [1.2, 0.0, 0]]), static_world)


def run(args, stdin=None):
    return subprocess.run([sys.executable, "-m", "overhang_framework.order_dependency", *args], cwd=ROOT,
                          capture_output=True, text=True, input=stdin, timeout=300)


def test_command_writes_one_line_per_tower_in_input_order(tmp_path):
    names = ["clamp", "floating", "bridge", "stack"]
    path = tmp_path / "towers.jsonl"
    path.write_text("".join(json.dumps({"blocks": CASES[n][0]}) + "\n\n" for n in names))
    for args, stdin in (([str(path)], None), (["-"], path.read_text())):
        proc = run([*args, "world.physics=static"], stdin)
        assert proc.returncode == 0, proc.stderr
        assert proc.stderr == ""
        assert [json.loads(line) for line in proc.stdout.splitlines()] == [
            {"valid_orders": 4, "stable_orders": 1, "gamma": 0.75},
            {"valid_orders": 0, "stable_orders": 0, "gamma": None},
            {"valid_orders": 4, "stable_orders": 2, "gamma": 0.5},
            {"valid_orders": 1, "stable_orders": 1, "gamma": 0.0},
        ]


@pytest.mark.parametrize("args, text, expected", [
    (["world.physics=static"], '{"blocks": [[1.8, 0.0, 0], [1.3, 0.2, 1]]}',
     "error: {path} line 2: block 2: illegal block width 1.3"),
    (["world.physics=static"], '{"blocks": [[1.2, 0.2, 1]]}',
     "error: {path} line 2: the first block must be the ground block (layer 0)"),
    (["world.physics=nope"], '{"blocks": [[1.2, 0.0, 0]]}', "error: "),
    (["world.physics=static"], None, "error: {path}: cannot read it"),
], ids=["width", "ground", "override", "missing"])
def test_command_errors_are_one_line(tmp_path, args, text, expected):
    path = tmp_path / "towers.jsonl"
    if text is not None:
        path.write_text(json.dumps({"blocks": CASES["stack"][0]}) + "\n" + text + "\n")
    proc = run([str(path), *args])
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and proc.stdout == ""
    assert len(lines) == 1 and lines[0].startswith(expected.format(path=path))
    assert "nope" in lines[0] or "nope" not in args[0]


def test_progress_only_when_the_physics_takes_more_than_one_batch(static_world, capsys, monkeypatch):
    monkeypatch.setenv("OVERHANG_PROGRESS_SECONDS", "60")
    towers = random_towers(8, seed=5, min_blocks=4, max_blocks=5)
    expected = order_counts_many(towers, static_world, show_progress=True)
    assert capsys.readouterr().err == ""
    assert order_counts_many(towers, static_world, chunk=5, show_progress=True) == expected
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("partial towers: 100%")
