"""Progress: tqdm's bar on a terminal, whole lines now and then elsewhere, and a long decision's calls."""

import io

import pytest

from overhang_framework.progress import LogProgress, line_seconds, progress_bar


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_off_a_terminal_lines_are_whole_and_rate_limited():
    out = io.StringIO()
    bar = LogProgress(total=100, desc="placements", unit="pl", file=out, interval=3600)
    for _ in range(100):
        bar.update(1)
    assert out.getvalue() == "", "no line before the interval has passed"
    bar.close()
    lines = out.getvalue().splitlines()
    assert len(lines) == 1 and lines[0].startswith("placements: 100%") and "100/100" in lines[0]
    assert "\r" not in out.getvalue()

    out = io.StringIO()
    with LogProgress(total=3, desc="towers", file=out, interval=1e-9) as bar:
        for _ in range(3):
            bar.update(1)
        bar.set_postfix_str("paper03")
    lines = out.getvalue().splitlines()
    assert [line.split("|")[2].split("[")[0].strip() for line in lines[:3]] == ["1/3", "2/3", "3/3"]
    assert lines[-1].endswith("paper03]")


def test_the_stream_decides_the_kind_of_progress(monkeypatch):
    from tqdm import tqdm

    on_terminal = progress_bar(total=2, file=Terminal())
    assert isinstance(on_terminal, tqdm)
    on_terminal.close()
    elsewhere = progress_bar(range(3), file=io.StringIO(), desc="items")
    assert isinstance(elsewhere, LogProgress) and list(elsewhere) == [0, 1, 2] and elsewhere.n == 3

    monkeypatch.setenv("OVERHANG_PROGRESS_SECONDS", "0")
    out = io.StringIO()
    with progress_bar(total=2, file=out) as quiet:
        quiet.update(2)
    assert out.getvalue() == ""
    monkeypatch.setenv("OVERHANG_PROGRESS_SECONDS", "soon")
    with pytest.raises(ValueError, match="OVERHANG_PROGRESS_SECONDS must be a number of seconds >= 0, got 'soon'"):
        line_seconds()


def test_a_long_decision_shows_its_predictor_calls_as_it_goes():
    """The budget's observer sees every charge; the run's watch puts the calls on the bar."""
    from overhang_framework.app import DecisionWatch
    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config
    from overhang_framework.episode import episode_rng, run_episode
    from overhang_framework.interfaces import Task

    models = build_models(compose_config(["planner=lookahead", "planner.depth=3", "world.physics=static"]))
    out = io.StringIO()
    bar = LogProgress(total=3, desc="placements", file=out, interval=1e-9)
    watch = DecisionWatch(bar, "episode 1/1 t", seconds=0)
    seen = []

    def charged(budget):
        seen.append(budget.calls_used)
        watch.charged(budget)

    record = run_episode(Task("t", (1.2, 0.6, 1.8, 0.6)), models["world"], models["predictor"], models["planner"],
                         models["value"], episode_rng(0, 0, 0), on_step=watch.placed, on_charge=charged)
    calls = sum(s["spend"]["predictor_calls"] for s in record["steps"])
    assert len(seen) == calls and calls > len(record["steps"])
    text = out.getvalue()
    assert "episode 1/1 t, placement 1: 1 predictor calls" in text
    assert f"placement 1: {record['steps'][0]['spend']['predictor_calls']:,} predictor calls" in text
    assert bar.n == len(record["steps"])
