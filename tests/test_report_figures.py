"""What the report's figures show, checked on small synthetic results (no runs needed)."""

import math
from pathlib import Path

import matplotlib
import pytest

matplotlib.use("Agg")

from matplotlib import pyplot as plt  # noqa: E402

from overhang_framework.report.build import (  # noqa: E402
    Job,
    effort_plot,
    overhang_standing,
    share_standing,
    steps_plot,
    towers_plot,
    y_limits,
)


def step(x: float, layer: int, overhang: float, stable: bool = True, depth=1, seconds: float = 0.01) -> dict:
    return {"width": 1.2, "x": x, "layer": layer, "stable": stable, "overhang": overhang, "decision_time": seconds,
            "spend": {"depth_completed": depth}}


def episode(steps: list[dict], task_id: str = "t0", placements: int = 2) -> dict:
    stable = all(s["stable"] for s in steps)
    return {"task_id": task_id, "sequence": [1.2] * (placements + 1), "steps": steps, "stable_throughout": stable,
            "overhang": steps[-1]["overhang"], "reward": steps[-1]["overhang"] if stable else 0.0}


def job(name: str, episodes: list[dict], planner: str = "myopic") -> Job:
    config = {"predictor": {"name": "veridical"}, "planner": {"name": planner},
              "condition": {"name": "unconstrained"}}
    return Job(name, Path(name), "complete", "", config, episodes)


# Two placements each: one tower stands throughout, one falls at placement 2 far out, one falls at placement 1.
STOOD = episode([step(0.6, 1, 1.2), step(1.2, 2, 1.8)])
FELL_LATE = episode([step(0.6, 1, 1.0), step(3.4, 2, 4.0, stable=False)])
FELL_EARLY = episode([step(-1.0, 1, 1.6, stable=False)])


@pytest.fixture(autouse=True)
def close_figures():
    yield
    plt.close("all")


def series_lines(ax) -> list:
    """The data line of every errorbar series on ``ax``, in drawing order."""
    return [container.lines[0] for container in ax.containers]


def test_overhang_by_placement_leaves_out_the_towers_that_fell():
    points = overhang_standing([STOOD, FELL_LATE, FELL_EARLY])
    assert [(round(m, 9), n) for m, _, n in points] == [(1.1, 2), (1.8, 1)]


def test_share_standing_counts_an_earlier_collapse_as_fallen():
    points = share_standing([STOOD, FELL_LATE, FELL_EARLY])
    assert [(round(m, 9), n) for m, _, n in points] == [(round(2 / 3, 9), 3), (round(1 / 3, 9), 3)]


def test_the_steps_figure_plots_the_overhang_of_standing_towers_and_says_so():
    fig = steps_plot([job("0", [STOOD, FELL_LATE, FELL_EARLY])])
    overhang_ax, standing_ax = fig.axes
    assert list(series_lines(overhang_ax)[0].get_ydata()) == pytest.approx([1.1, 1.8])
    assert "standing" in overhang_ax.get_title() and "fell are left out" in overhang_ax.get_title()
    assert list(series_lines(standing_ax)[0].get_ydata()) == pytest.approx([2 / 3, 1 / 3])


def test_identical_conditions_stay_visible():
    jobs = [job("0", [STOOD]), job("1", [STOOD])]
    for fig in (steps_plot(jobs), effort_plot(jobs)):
        for ax in fig.axes:
            a, b = series_lines(ax)
            assert list(a.get_ydata()) == list(b.get_ydata())
            assert all(xa != xb for xa, xb in zip(a.get_xdata(), b.get_xdata()))
            assert a.get_marker() != b.get_marker() and a.get_linestyle() != b.get_linestyle()
            assert "0 = 1: identical values" in ax.get_title()


def test_each_figure_has_one_legend_for_all_panels_outside_the_axes():
    jobs = [job("0", [STOOD]), job("1", [FELL_LATE], planner="lookahead")]
    for fig in (steps_plot(jobs), effort_plot(jobs), towers_plot(jobs, "t0")[0]):
        assert len(fig.legends) == 1
        assert all(ax.get_legend() is None for ax in fig.axes)
        assert all(text.get_fontsize() >= 9 for text in fig.legends[0].get_texts())
    labels = [t.get_text() for t in steps_plot(jobs).legends[0].get_texts()]
    assert labels == ["0: veridical / myopic / unconstrained", "1: veridical / lookahead / unconstrained"]


def test_effort_axes_start_at_zero_and_a_constant_depth_is_not_squashed():
    fig = effort_plot([job("0", [STOOD, STOOD])])
    time_ax, depth_ax = fig.axes
    assert time_ax.get_ylim()[0] == 0 and time_ax.get_ylim()[1] > 0.01
    low, high = depth_ax.get_ylim()
    assert low == 0 and high >= 1.5
    ticks = [t for t in depth_ax.get_yticks() if low <= t <= high]
    assert 1 in ticks and all(float(t).is_integer() for t in ticks)


def test_y_limits_open_a_constant_series_and_cover_the_error_bars():
    assert y_limits([(1.0, math.nan, 1)] * 3, floor=0.0, integer=True) == (0.0, 1.5)
    low, high = y_limits([(2.0, math.nan, 1), (2.0, math.nan, 1)])
    assert low < 2.0 < high
    low, high = y_limits([(1.0, 0.5, 4), (3.0, 0.0, 4)], floor=0.0)
    assert low == 0.0 and high > 3.0


def test_the_towers_figure_has_axes_in_task_units_the_ground_and_the_overhang():
    fig, n = towers_plot([job("0", [STOOD]), job("1", [FELL_LATE])], "t0")
    assert n == 2
    stood, fell = fig.axes[:2]
    for ax in (stood, fell):
        assert ax.axison and ax.get_xlabel().startswith("x (task units")
        assert ax.get_xlim() == (-4.0, 4.0)
        assert any(list(line.get_ydata()) == [0, 0] for line in ax.lines)  # the ground
        verticals = {round(float(line.get_xdata()[0]), 9) for line in ax.lines
                     if list(line.get_xdata()) == [line.get_xdata()[0]] * 2}
        assert {-0.6, 0.0, 0.6} <= verticals  # the ground block's edges and x = 0
    assert 1.8 in {round(float(line.get_xdata()[0]), 9) for line in stood.lines}
    assert "stood: overhang 1.80" in stood.get_title()
    assert "fell at placement 2: overhang 4.00" in fell.get_title()


def test_no_tower_figure_for_a_task_nobody_played():
    assert towers_plot([job("0", [STOOD])], "other") == (None, 0)
