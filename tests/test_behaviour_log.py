"""The behaviour log: its round trips (JSON Lines, DataFrame, CSV), every kind of malformed log named by
file, line and field, model runs converted from a real run, the schema, and the examples of docs/behaviour.md."""

import contextlib
import copy
import io
import json
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from overhang_framework.behaviour import (COLUMNS, FIELDS, LogError, from_run, from_runs, read_log, to_csv, to_frame,
                                          write_log)
from overhang_framework.behaviour.convert import ConvertError
from overhang_framework.behaviour.log import DTYPES, REQUIRED, SOURCES, in_step_order, last_records
from overhang_framework.errors import OverhangError
from overhang_framework.geometry import MAX_LAYER, WIDTHS, Geometry, overhang
from overhang_framework.results import read_episodes

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = ROOT / "overhang_framework" / "behaviour" / "schema.json"
DOC = ROOT / "docs" / "behaviour.md"
SEQUENCES = "tasks.sequences=[[1.2,0.6,1.8],[0.6,1.2,1.2]]"


def placement(participant, condition, task_id, sequence, trial, step, x, layer, tower, stable, over, reward,
              decision_time, **more):
    return {"log_version": 1, "participant": participant, "condition": condition, "task_id": task_id,
            "sequence": sequence, "trial": trial, "step": step, "width": sequence[step], "x": x, "layer": layer,
            "tower_before": tower, "stable": stable, "overhang": over, "reward": reward,
            "decision_time": decision_time, "timed_out": False, **more}


def human_log() -> list[dict]:
    """Two people, four trials: one standing to the end, one timed out, one collapsed, one standing."""
    a, b = [1.2, 0.6, 1.8], [0.6, 1.2, 1.2]
    return [
        placement("p01", "time_limited", "paper00", a, 1, 1, 0.5, 1, [[1.2, 0, 0]], True, 0.8, None, 1.25,
                  trajectory=[[0, 0, 5], [0.5, 0.4, 2.0], [1.25, 0.5, 0.9]], dwell=[[0.5, 1, 0.6]],
                  source="human", browser="firefox"),
        placement("p01", "time_limited", "paper00", a, 1, 2, 0.6, 2, [[1.2, 0, 0], [0.6, 0.5, 1]], True, 1.5,
                  1.5, 2.0, source="human", note="1.5"),
        {**placement("p01", "time_limited", "paper01", b, 2, 1, None, None, [[0.6, 0, 0]], None, None, 0, 5.0),
         "timed_out": True},
        placement("p02", "unconstrained", "paper01", b, 1, 1, 0.9, 1, [[0.6, 0, 0]], False, 1.5, 0, 3.5,
                  screen={"w": 1920, "h": 1080}),
        placement("p02", "unconstrained", "paper00", a, 2, 1, -0.4, 1, [[1.2, 0, 0]], True, 0.7, None, 2.2),
        placement("p02", "unconstrained", "paper00", a, 2, 2, -0.9, 2, [[1.2, 0, 0], [0.6, -0.4, 1]], True, 1.8,
                  1.8, 4.0),
    ]


def write_lines(path: Path, records: list) -> Path:
    """``records`` one per line after a blank first line, so record i is on line i + 2; strings as they are."""
    path.write_text("\n" + "".join((r if isinstance(r, str) else json.dumps(r)) + "\n" for r in records))
    return path


# -- round trips -------------------------------------------------------------------------------------


def test_a_log_round_trips_through_json_lines_a_dataframe_and_csv(tmp_path):
    write_log(human_log(), tmp_path / "log.jsonl")
    df = read_log(tmp_path / "log.jsonl")
    assert list(df.columns) == [*COLUMNS, "browser", "note", "screen"]
    assert len(df) == 6 and df["step"].tolist() == [1, 2, 1, 1, 1, 2]
    assert {c: str(df[c].dtype) for c in ("trial", "x", "layer", "stable", "timed_out")} == {
        "trial": "int64", "x": "float64", "layer": "Int64", "stable": "boolean", "timed_out": "bool"}
    assert df["tower_before"][1] == [[1.2, 0.0, 0], [0.6, 0.5, 1]]
    assert df["trajectory"][0] == [[0.0, 0.0, 5.0], [0.5, 0.4, 2.0], [1.25, 0.5, 0.9]]
    assert df["trajectory"][1] is None and df["source"][2] is None
    timed_out = df.iloc[2]
    assert pd.isna(timed_out["x"]) and timed_out["layer"] is pd.NA and timed_out["stable"] is pd.NA
    assert timed_out["reward"] == 0
    assert df["reward"].isna().tolist() == [True, False, False, False, True, False]
    assert df["note"][1] == "1.5" and df["screen"][3] == {"w": 1920, "h": 1080} and df["browser"][0] == "firefox"

    to_csv(df, tmp_path / "log.csv")
    pd.testing.assert_frame_equal(read_log(tmp_path / "log.csv"), df)
    write_log(df, tmp_path / "again.jsonl")
    pd.testing.assert_frame_equal(read_log(tmp_path / "again.jsonl"), df)
    assert (tmp_path / "again.jsonl").read_text() == (tmp_path / "log.jsonl").read_text()
    pd.testing.assert_frame_equal(to_frame(human_log()), df)


def test_several_files_read_as_one_log_and_blank_lines_are_skipped(tmp_path):
    records = human_log()
    write_lines(tmp_path / "a.jsonl", records[:3])
    (tmp_path / "b.jsonl").write_text("\n".join(json.dumps(r) for r in records[3:]) + "\n\n\n")
    df = read_log([tmp_path / "a.jsonl", str(tmp_path / "b.jsonl")])
    assert df["participant"].tolist() == ["p01"] * 3 + ["p02"] * 3
    with pytest.raises(LogError, match=r"b\.jsonl line 2: field 'step': .* again \(first on .*a\.jsonl line 2\)"):
        read_log([tmp_path / "a.jsonl", write_lines(tmp_path / "b.jsonl", records[:1])])


def test_unknown_fields_are_kept_as_columns_in_order_of_appearance(tmp_path):
    records = human_log()
    records[4]["zeta"] = [1, {"deep": None}]
    records[0]["alpha"] = 7
    df = read_log(write_lines(tmp_path / "log.jsonl", records))
    assert list(df.columns[len(COLUMNS):]) == ["browser", "alpha", "note", "screen", "zeta"]
    assert df["zeta"][4] == [1, {"deep": None}] and df["alpha"][0] == 7
    to_csv(df, tmp_path / "log.csv")
    pd.testing.assert_frame_equal(read_log(tmp_path / "log.csv"), df)


def test_any_order_of_lines_and_files_reads_as_the_same_log_sorted_by_participant_trial_step(tmp_path):
    import random

    records = human_log()
    records[4]["zeta"] = 1                    # an extra field: its column's place must not depend on the order
    df = read_log(write_lines(tmp_path / "log.jsonl", records))
    assert list(zip(df.participant, df.trial, df.step)) == sorted(zip(df.participant, df.trial, df.step))
    shuffled = records[:]
    random.Random(0).shuffle(shuffled)
    backwards = sorted(records, key=lambda r: (r["participant"], r["trial"], -r["step"]))
    assert shuffled != records and backwards != records
    for i, other in enumerate([shuffled, backwards, records[::-1]]):
        pd.testing.assert_frame_equal(read_log(write_lines(tmp_path / f"other{i}.jsonl", other)), df)
        pd.testing.assert_frame_equal(to_frame(other), df)
    write_lines(tmp_path / "a.jsonl", shuffled[:3])
    write_lines(tmp_path / "b.jsonl", shuffled[3:])
    pd.testing.assert_frame_equal(read_log([tmp_path / "b.jsonl", tmp_path / "a.jsonl"]), df)


def test_last_records_are_each_trials_last_step_whatever_the_rows_order():
    df = to_frame(human_log())
    for other in (df.iloc[::-1], df.sample(frac=1.0, random_state=1)):
        last = last_records(other)
        assert list(zip(last.participant, last.trial, last.step)) == [("p01", 1, 2), ("p01", 2, 1), ("p02", 1, 1),
                                                                      ("p02", 2, 2)]
        assert last["reward"].tolist() == [1.5, 0.0, 0.0, 1.8]
        pd.testing.assert_frame_equal(in_step_order(other), df)


def test_write_log_refuses_a_malformed_record_and_writes_nothing(tmp_path):
    records = human_log()
    records[1]["width"] = 0.9
    with pytest.raises(LogError, match=r"^record 2: field 'width': expected one of the widths 0.6, 1.2, 1.8"):
        write_log(records, tmp_path / "log.jsonl")
    assert not list(tmp_path.iterdir())


def test_a_dataframe_with_a_broken_row_is_not_written_as_csv(tmp_path):
    df = to_frame(human_log())
    df.loc[4, "decision_time"] = -2.0
    with pytest.raises(LogError, match=r"^row 5: field 'decision_time': expected a number of seconds >= 0"):
        to_csv(df, tmp_path / "log.csv")
    assert not (tmp_path / "log.csv").exists()


# -- malformed logs ----------------------------------------------------------------------------------


def _set(i, **fields):
    def mutate(records):
        records[i].update(fields)
    return mutate


def _replace(i, value):
    def mutate(records):
        records[i] = value
    return mutate


def _drop_field(i, name):
    def mutate(records):
        del records[i][name]
    return mutate


def _drop(i):
    def mutate(records):
        del records[i]
    return mutate


def _append(record):
    def mutate(records):
        records.append(record)
    return mutate


AFTER_COLLAPSE = placement("p02", "unconstrained", "paper01", [0.6, 1.2, 1.2], 1, 2, 0.0, 2,
                           [[0.6, 0, 0], [1.2, 0.9, 1]], True, 1.5, 1.5, 1.0)

# (mutation of human_log(), line, field or None, what the message says)
MALFORMED = {
    "not JSON": (_replace(1, "{oops"), 3, None, "not JSON (Expecting property name enclosed in double quotes"),
    "not an object": (_replace(1, "[1, 2]"), 3, None, "expected a JSON object (one record per line), got [1, 2]"),
    "missing field": (_drop_field(1, "stable"), 3, "stable", "missing (a required field)"),
    "wrong type": (_set(0, x="abc"), 2, "x", 'expected a number, got "abc"'),
    "wrong type of a list": (_set(0, sequence="1.2,0.6"), 2, "sequence", 'expected a list, got "1.2,0.6"'),
    "boolean for a number": (_set(0, trial=True), 2, "trial", "expected a whole number, got true"),
    "width not allowed": (_set(0, width=0.9), 2, "width", "expected one of the widths 0.6, 1.2, 1.8, got 0.9"),
    "sequence width not allowed": (_set(4, sequence=[1.2, 0.7, 1.8]), 6, "sequence",
                                   "item 2: expected one of the widths 0.6, 1.2, 1.8, got 0.7"),
    "width not sequence[step]": (_set(0, width=1.2), 2, "width", "expected 0.6, the width of sequence[1], got 1.2"),
    "step out of range": (_set(1, step=3), 3, "step", "expected a step from 1 to 2 (the sequence places 2 blocks"),
    "step zero": (_set(1, step=0), 3, "step", "expected a step from 1 to 2"),
    "trial zero": (_set(3, trial=0), 5, "trial", "expected a whole number >= 1, got 0"),
    "layer zero": (_set(0, layer=0), 2, "layer", "expected a layer from 1 to 12, got 0"),
    "layer not whole": (_set(0, layer=1.5), 2, "layer", "expected a whole number, got 1.5"),
    "negative decision time": (_set(0, decision_time=-0.5), 2, "decision_time",
                               "expected a number of seconds >= 0, got -0.5"),
    "tower block malformed": (_set(1, tower_before=[[1.2, 0, 0], [0.6]]), 3, "tower_before",
                              "block 2 must be [width, x, layer], got [0.6]"),
    "tower block width": (_set(1, tower_before=[[1.2, 0, 0], [0.7, 0.5, 1]]), 3, "tower_before",
                          "block 2: illegal block width 0.7"),
    "tower too short": (_set(1, tower_before=[[1.2, 0, 0]]), 3, "tower_before",
                        "expected 2 blocks (the ground block and the 1 placed before step 2), got 1"),
    "tower off the sequence": (_set(1, tower_before=[[1.2, 0, 0], [1.8, 0.5, 1]]), 3, "tower_before",
                               "block 2 has width 1.8, but sequence[1] is 0.6"),
    "ground block moved": (_set(0, tower_before=[[1.2, 0.5, 0]]), 2, "tower_before",
                           "the ground block stands at x=0, got x=0.5"),
    "ground block not on the ground": (_set(0, tower_before=[[1.2, 0, 1]]), 2, "tower_before",
                                       "the first block must be the ground block (layer 0), got layer 1"),
    "tower not continuing the last step": (_set(1, tower_before=[[1.2, 0, 0], [0.6, 0.4, 1]]), 3, "tower_before",
                                           "expected the tower of step 1"),
    "timed out with an x": (_set(2, x=0.3), 4, "x", "expected null on a timed-out record, got 0.3"),
    "timed out with a reward": (_set(2, reward=0.6), 4, "reward", "expected 0 on a timed-out record"),
    "placed without an x": (_set(0, x=None), 2, "x", "expected a number (null only on a timed-out record), got null"),
    "duplicate placement": (_replace(1, "COPY 0"), 3, "step", 'step 1 of trial 1 of participant "p01" again '
                                                             "(first on LOG line 2)"),
    "task in two trials": (_set(5, trial=3), 7, "trial", 'participant "p02" did task "paper00" as trial 2 '
                                                        "(LOG line 6); a task is one trial, got trial 3"),
    "trial of two tasks": (_set(5, task_id="paper09"), 7, "task_id", 'expected "paper00" as on LOG line 6'),
    "condition changes within a trial": (_set(1, condition="unconstrained"), 3, "condition",
                                         'expected "time_limited" as on LOG line 2'),
    "reward on a non-final record": (_set(0, reward=0.8), 2, "reward",
                                     "expected null: step 1 of 2 does not end the trial"),
    "reward missing on the final record": (_set(1, reward=None), 3, "reward",
                                           "expected a number on the trial's last record (the sequence's last "
                                           "block), got null"),
    "reward missing after a collapse": (_set(3, reward=None), 5, "reward",
                                        "expected a number on the trial's last record (the tower fell)"),
    "reward after a collapse": (_set(3, reward=1.5), 5, "reward", "expected 0 (the tower fell), got 1.5"),
    "reward not the overhang": (_set(1, reward=1.4), 3, "reward", "expected 1.5, the overhang"),
    "overhang not the tower's": (_set(0, overhang=0.9), 2, "overhang", "expected 0.8, the overhang of tower_before"),
    "unknown version": (_set(3, log_version=2), 5, "log_version", "unknown version 2; this reader reads version 1"),
    "gap in the steps": (_drop(4), 6, "step", 'trial 2 of participant "p02" has no step 1, got step 2'),
    "trial not ended": (_drop(1), 2, "step", 'trial 1 of participant "p01" stops at step 1 of 2'),
    "record after the end": (_append(AFTER_COLLAPSE), 8, "step",
                             'trial 1 of participant "p02" ended at step 1 (LOG line 5: the tower fell), got step 2'),
    "empty participant": (_set(0, participant=" "), 2, "participant", 'expected a non-empty string, got " "'),
    "unknown source": (_set(0, source="robot"), 2, "source", 'expected one of human, simulated, model, got "robot"'),
    "trajectory going back": (_set(0, trajectory=[[0, 0, 0], [1.0, 0, 0], [0.5, 0, 0]]), 2, "trajectory",
                              "item 3: expected a time >= 1 s"),
    "trajectory item malformed": (_set(0, trajectory=[[0, 0]]), 2, "trajectory",
                                  "item 1: expected [t, x, y], three numbers, got [0, 0]"),
    "dwell with a negative time": (_set(0, dwell=[[0.5, 1, -1]]), 2, "dwell", "item 1: expected seconds >= 0"),
}


@pytest.mark.parametrize("kind", list(MALFORMED))
def test_a_malformed_log_fails_with_one_line_naming_file_line_and_field(tmp_path, kind):
    mutate, line, field, what = MALFORMED[kind]
    records = human_log()
    mutate(records)
    records = [copy.deepcopy(records[int(r.split()[1])]) if isinstance(r, str) and r.startswith("COPY") else r
               for r in records]
    path = write_lines(tmp_path / "log.jsonl", records)
    with pytest.raises(LogError) as caught:
        read_log(path)
    message = str(caught.value)
    where = f"{path} line {line}"
    assert message.startswith(f"{where}: " + (f"field '{field}': " if field else "")), message
    assert what.replace("LOG", str(path)) in message
    assert "\n" not in message
    assert (caught.value.where, caught.value.field) == (where, field)
    assert isinstance(caught.value, OverhangError)


def test_a_malformed_csv_names_the_csv_line_and_field(tmp_path):
    to_csv(to_frame(human_log()), tmp_path / "log.csv")
    lines = (tmp_path / "log.csv").read_text().splitlines()
    assert ",2,1.8,0.6,2," in lines[2]
    lines[2] = lines[2].replace(",2,1.8,0.6,2,", ",2,1.8,abc,2,")
    (tmp_path / "bad.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(LogError, match=re.escape(f"{tmp_path / 'bad.csv'} line 3: field 'x': expected a number, "
                                                 'got "abc"')):
        read_log(tmp_path / "bad.csv")
    (tmp_path / "short.csv").write_text(lines[0].replace(",stable,", ",") + "\n")
    with pytest.raises(LogError, match=r"short\.csv line 1: field 'stable': missing column"):
        read_log(tmp_path / "short.csv")


def test_a_missing_file_is_one_line_too(tmp_path):
    with pytest.raises(LogError, match=r"nowhere\.jsonl: cannot read it \(No such file or directory\)"):
        read_log(tmp_path / "nowhere.jsonl")


def test_the_log_command_prints_one_error_line_and_exits_2(tmp_path):
    records = human_log()
    records[0]["x"] = "abc"
    write_lines(tmp_path / "bad.jsonl", records)
    write_log(human_log(), tmp_path / "good.jsonl")
    command = [sys.executable, "-m", "overhang_framework.behaviour.log"]
    bad = subprocess.run([*command, "bad.jsonl"], cwd=tmp_path, capture_output=True, text=True)
    assert (bad.returncode, bad.stdout) == (2, "")
    assert bad.stderr == "error: bad.jsonl line 2: field 'x': expected a number, got \"abc\"\n"
    good = subprocess.run([*command, "good.jsonl", "--csv", "good.csv"], cwd=tmp_path, capture_output=True, text=True)
    assert good.returncode == 0, good.stderr
    assert good.stdout == ("6 records: 2 participants, 4 trials (conditions: time_limited, unconstrained); "
                           "written to good.csv\n")
    pd.testing.assert_frame_equal(read_log(tmp_path / "good.csv"), read_log(tmp_path / "good.jsonl"))


# -- model runs --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A real run of the main job: two tasks, two repeats, static physics."""
    out = tmp_path_factory.mktemp("behaviour") / "run"
    done = subprocess.run([sys.executable, "-m", "overhang_framework", "tasks=custom", SEQUENCES,
                           "world.physics=static", "progress=false", "repeats=2", f"hydra.run.dir={out}"],
                          cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return out


def test_a_real_run_converts_into_records_that_agree_with_its_episodes(run_dir):
    records = from_run(run_dir)
    episodes = read_episodes(run_dir / "episodes.jsonl")
    assert len(episodes) == 4 and len(records) == sum(len(e["steps"]) for e in episodes)
    for episode in episodes:
        participant = f"veridical-myopic/{episode['repeat']}"
        mine = [r for r in records if r["participant"] == participant and r["task_id"] == episode["task_id"]]
        assert [r["step"] for r in mine] == list(range(1, len(episode["steps"]) + 1))
        assert {r["trial"] for r in mine} == {episode["task_index"] + 1}
        tower = [[episode["sequence"][0], 0.0, 0]]
        for record, step in zip(mine, episode["steps"]):
            assert record["tower_before"] == tower
            assert (record["width"], record["x"], record["layer"]) == (step["width"], step["x"], step["layer"])
            tower = tower + [[step["width"], step["x"], step["layer"]]]
            assert record["overhang"] == step["overhang"]
            assert overhang(Geometry.from_tuples(tower)) == pytest.approx(record["overhang"], abs=1e-9)
            assert record["stable"] == step["stable"]
            assert record["decision_time"] == step["decision_time"]
            assert (record["condition"], record["source"], record["timed_out"]) == ("unconstrained", "model", False)
            assert record["over_time_limit"] is False and record["seed"] == 0
        assert [r["reward"] for r in mine] == [None] * (len(mine) - 1) + [episode["reward"]]
    assert [(r["participant"], r["trial"], r["step"]) for r in records] == sorted(
        (r["participant"], r["trial"], r["step"]) for r in records)
    df = to_frame(records)
    assert sorted(df["participant"].unique()) == ["veridical-myopic/0", "veridical-myopic/1"]
    assert df.groupby(["participant", "trial"])["reward"].count().eq(1).all()


def test_a_runs_episodes_read_as_a_log_point_to_the_convert_command(run_dir, tmp_path):
    episodes = run_dir / "episodes.jsonl"
    with pytest.raises(LogError, match=r"episodes\.jsonl line 1: an episode of a model run.*behaviour\.convert RUN_DIR"):
        read_log(episodes)
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.fit", str(episodes), "--out",
                           str(tmp_path / "fit")], capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "python -m overhang_framework.behaviour.convert" in proc.stderr and not (tmp_path / "fit").exists()


def test_the_convert_command_writes_a_log_and_its_csv(run_dir, tmp_path):
    command = [sys.executable, "-m", "overhang_framework.behaviour.convert", str(run_dir)]
    for out in ("log.jsonl", "log.csv"):
        done = subprocess.run([*command, "--out", out], cwd=tmp_path, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        assert done.stdout == f"8 records: 2 participants, 4 trials (conditions: unconstrained); written to {out}\n"
        assert done.stderr == ""
    pd.testing.assert_frame_equal(read_log(tmp_path / "log.csv"), read_log(tmp_path / "log.jsonl"))
    pd.testing.assert_frame_equal(read_log(tmp_path / "log.jsonl"), to_frame(from_run(run_dir)))
    missing = subprocess.run([*command[:-1], str(tmp_path / "nothing"), "--out", "x.jsonl"], cwd=tmp_path,
                             capture_output=True, text=True)
    assert missing.returncode == 2
    assert missing.stderr == f"error: {tmp_path / 'nothing'} holds no run (no run.json or .hydra/overrides.yaml " \
                             "in it or below it)\n"


def test_a_sweep_converts_every_job_with_participants_told_apart(run_dir, tmp_path):
    sweep = tmp_path / "sweep"
    for job, condition, limit in (("0", "unconstrained", None), ("1", "time_limited", 5.0)):
        shutil.copytree(run_dir, sweep / job)
        config = json.loads((sweep / job / "run.json").read_text())
        config["config"]["condition"].update(name=condition, time_limit=limit)
        (sweep / job / "run.json").write_text(json.dumps(config))
    (sweep / "multirun.yaml").write_text("{}\n")
    records = from_run(sweep)
    df = to_frame(records)
    assert sorted(df["participant"].unique()) == [
        "veridical-myopic[condition=time_limited]/0", "veridical-myopic[condition=time_limited]/1",
        "veridical-myopic[condition=unconstrained]/0", "veridical-myopic[condition=unconstrained]/1"]
    assert (df["participant"].str.contains("time_limited") == (df["condition"] == "time_limited")).all()
    (sweep / "2").mkdir()
    shutil.copytree(sweep / "1", sweep / "2" / "short")
    config = json.loads((sweep / "2" / "short" / "run.json").read_text())
    config["config"]["condition"]["time_limit"] = 2.0
    (sweep / "2" / "short" / "run.json").write_text(json.dumps(config))
    assert sorted({r["participant"].rsplit("/", 1)[0] for r in from_run(sweep)}) == [
        "veridical-myopic[condition=time_limited,condition.time_limit=2.0]",
        "veridical-myopic[condition=time_limited,condition.time_limit=5.0]",
        "veridical-myopic[condition=unconstrained,condition.time_limit=null]"]
    twins = from_runs([sweep / "0", run_dir])
    assert {r["participant"].rsplit("/", 1)[0] for r in twins} == {
        f"veridical-myopic[{sweep / '0'}]", f"veridical-myopic[{run_dir}]"}
    to_frame(twins)


def test_an_unfinished_run_is_refused(run_dir, tmp_path):
    shutil.copytree(run_dir, tmp_path / "run")
    (tmp_path / "run" / "episodes.jsonl").rename(tmp_path / "run" / "episodes.jsonl.partial")
    with pytest.raises(ConvertError, match=r"has no episodes.jsonl \(the run did not finish: rerun its command"):
        from_run(tmp_path / "run")


# -- schema and docs ---------------------------------------------------------------------------------


def test_the_schema_lists_the_fields_and_types_the_reader_checks():
    schema = json.loads(SCHEMA.read_text())
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert schema["required"] == list(REQUIRED)
    assert list(schema["properties"]) == list(COLUMNS) == list(DTYPES)
    for field in FIELDS:
        declared = schema["properties"][field.name]["type"]
        assert set([declared] if isinstance(declared, str) else declared) == set(field.types), field.name
    assert schema["properties"]["log_version"]["const"] == 1
    assert schema["properties"]["width"]["enum"] == list(WIDTHS) == schema["$defs"]["width"]["enum"]
    assert schema["properties"]["layer"]["maximum"] == MAX_LAYER
    assert schema["properties"]["source"]["enum"] == [*SOURCES, None]
    assert set(schema["then"]["properties"]) | set(schema["else"]["properties"]) == {
        "x", "layer", "stable", "overhang", "reward"}
    assert schema["additionalProperties"] is True


def _blocks(text: str) -> list[tuple[str, str]]:
    return [(m.group(1), m.group(2)) for m in re.finditer(r"^```(\w*)\n(.*?)^```$", text, re.M | re.S)]


def test_the_docs_examples_run_and_print_what_the_docs_show(tmp_path, monkeypatch):
    text = DOC.read_text()
    for field in COLUMNS:
        assert f"| `{field}` |" in text, f"docs/behaviour.md does not describe {field}"
    monkeypatch.chdir(tmp_path)
    blocks = _blocks(text)
    namespace: dict = {}
    outputs = []
    for kind, code in blocks:
        output = ""
        if kind == "python":
            buffer = io.StringIO()
            with contextlib.redirect_stdout(buffer):
                exec(compile(code, str(DOC), "exec"), namespace)
            output = buffer.getvalue()
        elif kind == "bash":
            for command in code.splitlines():
                words = shlex.split(command)
                assert words[0] == "python", command
                done = subprocess.run([sys.executable, *words[1:]], capture_output=True, text=True)
                output += done.stdout + done.stderr
        outputs.append(output)
    for (kind, code), before in zip(blocks[1:], outputs):
        if kind == "text":
            shown = [line.rstrip() for line in code.splitlines() if line.strip()]
            printed = [line.rstrip() for line in before.splitlines()]
            assert all(line in printed for line in shown), (shown, before)
    example = next(code for kind, code in blocks if kind == "json")
    assert example == (tmp_path / "log.jsonl").read_text().splitlines()[0] + "\n"
    assert sum(kind == "text" for kind, _ in blocks) == 8
