"""Task sets: paper20 is the seeded generator's output; user sequences are validated."""

import pytest

from overhang_framework.config import compose_config
from overhang_framework.errors import TaskError
from overhang_framework.tasks import generate_sequences, parse_tasks, tasks_from_config


def test_paper20_is_the_seeded_generator_output():
    cfg = compose_config(["tasks=paper20"]).tasks
    expected = generate_sequences(20, 6, seed=cfg.generator_seed)
    assert [list(t.sequence) for t in tasks_from_config(cfg)] == expected
    assert len({tuple(s) for s in expected}) == 20


def test_a_draw_is_another_seeded_set_of_the_same_kind():
    paper = tasks_from_config(compose_config(["tasks=paper20"]).tasks)
    same = tasks_from_config(compose_config(["tasks=draw", "tasks.generator_seed=2025"]).tasks)
    assert [t.sequence for t in same] == [t.sequence for t in paper]
    other = tasks_from_config(compose_config(["tasks=draw", "tasks.generator_seed=7", "tasks.count=30"]).tasks)
    assert len(other) == 30 and other[0].id == "draw00"
    assert [t.sequence for t in other[:20]] != [t.sequence for t in paper]
    assert all(len(t.sequence) == 6 for t in other)
    with pytest.raises(TaskError, match="tasks.count must be a whole number >= 1, got 0"):
        tasks_from_config(compose_config(["tasks=draw", "tasks.count=0"]).tasks)


def test_example_is_the_papers_figure_3_sequence():
    (task,) = tasks_from_config(compose_config(["tasks=example"]).tasks)
    assert task.sequence == (0.6, 1.8, 1.2, 1.8, 0.6, 1.8)


def test_custom_sequences_from_the_command_line():
    cfg = compose_config(["tasks=custom", "tasks.sequences=[[0.6,1.8],[1.2,1.2,0.6]]"]).tasks
    tasks = tasks_from_config(cfg)
    assert [t.sequence for t in tasks] == [(0.6, 1.8), (1.2, 1.2, 0.6)]
    assert [t.id for t in tasks] == ["custom00", "custom01"]


def test_only_selects_tasks_and_rejects_unknown_ids():
    cfg = compose_config(["tasks.only=[paper03,paper07]"]).tasks
    assert [t.id for t in tasks_from_config(cfg)] == ["paper03", "paper07"]
    with pytest.raises(TaskError, match="unknown task ids"):
        tasks_from_config(compose_config(["tasks.only=[nope]"]).tasks)


@pytest.mark.parametrize("sequences, match", [
    ([[0.6, 1.0]], "illegal block width 1.0; allowed widths are 0.6, 1.2, 1.8"),
    ([[0.6]], "needs the ground block and at least one more"),
    (["abc"], "must be a list of widths"),
    ([], "no task sequences"),
])
def test_bad_sequences_give_one_line_errors(sequences, match):
    with pytest.raises(TaskError, match=match) as err:
        parse_tasks(sequences)
    assert "\n" not in str(err.value)


def test_only_accepts_a_single_id_as_written_on_the_command_line():
    cfg = compose_config(["tasks.only=paper07"])
    assert [t.id for t in tasks_from_config(cfg.tasks)] == ["paper07"]
