"""The Psych-DS export: the dataset a stored study gives, its check, reading it back, and the command's refusals.

The study is made as a participant's page makes it: through the HTTP API (five
participants in both conditions, towers that stand and fall, a timeout, one
participant screened out in the practice), stored in SQLite.
"""

from __future__ import annotations

import json
import shutil

import httpx
import pandas as pd
import pytest
from fastapi.testclient import TestClient

from overhang_framework.behaviour.log import COLUMNS, FIELDS, read_log
from overhang_framework.behaviour.psychds import DATA_FILE, PsychDSError, check_dataset, data_files
from overhang_framework.experiment.__main__ import main
from overhang_framework.experiment.api import create_app
from overhang_framework.experiment.export import EXPORT_VARIABLES, log_records, variables, write_psychds
from overhang_framework.experiment.settings import load_settings
from overhang_framework.experiment.store import Store

ADMIN = "admin-secret-token"
PEOPLE = ("P1", "P2", "sub_03", "P4", "P5")
SCREENED = "P6"


class Clock:
    def __init__(self):
        self.now = 1_000_000.0

    def __call__(self):
        return self.now


def _study(root):
    """Store a study in ``root``; the overrides that name it."""
    overrides = [f"run_dir={root}", f"admin_token={ADMIN}", "tasks.only=[paper00,paper03,paper07]",
                 "physics_processes=0"]
    settings = load_settings(overrides)
    store, clock = Store(settings.database), Clock()
    client = TestClient(create_app(settings, store=store, clock=clock))

    def post(path, session, **body):
        reply = client.post(path, json=body, headers={"Authorization": f"Bearer {session['token']}"})
        assert reply.status_code == 200, reply.text
        return reply.json()

    def place(session, phase, trial, step, x, layer, seconds, attempt=1, **extra):
        where = dict(phase=phase, trial=trial, attempt=attempt, step=step)
        post("/api/steps/start", session, **where)
        clock.now += seconds
        return post("/api/placements", session, **where, x=x, layer=layer, decision_time=seconds - 0.1, **extra)

    for k, pid in enumerate(PEOPLE):
        s = client.post("/api/sessions", json={"params": {"participant": pid}}).json()
        client.post("/api/consent", json={"version": s["consent"]["version"]},
                    headers={"Authorization": f"Bearer {s['token']}"})
        for pt in s["practice"]:
            for step, (_, x, layer) in enumerate(settings.practice[pt["trial"] - 1].shown_tower[1:], 1):
                place(s, "practice", pt["trial"], step, x, layer, 1.0)
        by_id = {t.id: t for t in settings.tasks}
        for trial, task_id in enumerate(store.participant(pid).order, 1):
            sequence, x = by_id[task_id].sequence, 0.0
            for step in range(1, len(sequence)):
                if s["condition"] == "time_limited" and trial == 2 and step == 2:
                    place(s, "main", trial, step, None, None, 5.2, timed_out=True)
                    break
                x += 0.15 * ((k + trial + step) % 3 - 1) * (1 + k % 2)  # on the block below; some towers fall
                if place(s, "main", trial, step, x, step, 0.6 + 0.4 * k + 0.1 * step)["trial_over"]:
                    break
    s = client.post("/api/sessions", json={"params": {"participant": SCREENED}}).json()
    client.post("/api/consent", json={"version": s["consent"]["version"]},
                headers={"Authorization": f"Bearer {s['token']}"})
    seq = settings.practice[0].task.sequence
    for attempt in range(1, settings.practice_max_attempts + 1):
        place(s, "practice", 1, 1, seq[0] / 2 + seq[1] / 2 - 0.05, 1, 1.5, attempt=attempt)
    return overrides, store, client


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("study")
    (root / "run").mkdir()
    overrides, store, client = _study(root / "run")
    yield root, overrides, store, client
    store.close()


@pytest.fixture(scope="module")
def exports(study):
    """The study exported both ways by the command: (the JSON Lines log, the Psych-DS folder)."""
    root, overrides, _, _ = study
    assert main(["export", "--out", str(root / "log.jsonl"), *overrides]) == 0
    assert main(["export", "--format", "psych-ds", "--out", str(root / "psychds"), *overrides]) == 0
    return root / "log.jsonl", root / "psychds"


def test_the_study_holds_what_the_export_must_carry(exports):
    log = read_log(exports[0])
    assert set(log.participant) == set(PEOPLE) and set(log.condition) == {"time_limited", "unconstrained"}
    assert log.timed_out.any() and (log.stable == False).any()  # noqa: E712: a timeout and a fall, as nulls and false


def test_the_export_is_a_valid_dataset_that_reads_back_as_the_json_lines_export(exports):
    jsonl, folder = exports
    assert check_dataset(folder) == []
    files = data_files(folder)
    assert sorted(p.name for p in files) == sorted(f"study-overhang_subject-{s}_data.csv"
                                                    for s in ("P1", "P2", "sub03x6bb0fca7", "P4", "P5"))
    headers = set()
    for path in files:
        frame = pd.read_csv(path, keep_default_na=False, dtype=str)
        assert frame.participant.nunique() == 1  # one participant a file
        assert DATA_FILE.fullmatch(path.name) and "subject-" + frame.participant[0].replace("_", "") in path.name
        headers.add(tuple(frame.columns))
        for name in frame.columns:  # a column described as never missing has no empty cell
            assert variables()[name].optional or (frame[name] != "").all(), name
    assert len(headers) == 1  # one header: the files stack into one table
    meta = json.loads((folder / "dataset_description.json").read_text())
    assert meta["@context"] == "https://schema.org/" and meta["@type"] == "Dataset"
    assert [v["name"] for v in meta["variableMeasured"]] == list(next(iter(headers)))
    by_name = {v["name"]: v for v in meta["variableMeasured"]}
    assert by_name["decision_time"]["unitText"] == "seconds" and "JSON list" in by_name["trajectory"]["description"]
    assert meta["name"] == "Overhang Tower task: 5 participants" and "temporalCoverage" in meta
    pd.testing.assert_frame_equal(read_log(folder), read_log(jsonl))


def test_analyze_gives_the_same_results_from_the_dataset_as_from_the_json_lines(exports, tmp_path):
    from overhang_framework.analyze import main as analyze

    outs = {}
    for name, source in zip(("jsonl", "psychds"), exports):
        outs[name] = tmp_path / name
        assert analyze([str(source), "--out", str(outs[name]), "--only", "table1,gamma,flows", "--world",
                        "world.physics=static", "--n-resamples", "200", "--quiet"]) == 0
    written = sorted(p.name for p in outs["jsonl"].iterdir() if p.suffix in (".csv", ".md", ".json"))
    assert "table1.csv" in written and "report.md" in written
    assert written == sorted(p.name for p in outs["psychds"].iterdir() if p.suffix in (".csv", ".md", ".json"))
    for name in written:
        a, b = ((outs[k] / name).read_text() for k in outs)
        if name == "report.md":  # it names the input, and how long each section took
            assert "\n## Time\n" in a and "\n## Time\n" in b
            a, b = (t.replace(str(src), "LOG").split("\n## Time\n")[0] for t, src in zip((a, b), exports))
        if name == "summary.json":
            a, b = ({k: v for k, v in json.loads(t).items() if k != "seconds"} for t in (a, b))
        assert a == b, name


def test_screened_out_practice_is_exported_when_asked(study, tmp_path):
    _, overrides, _, _ = study
    out = tmp_path / "with"
    assert main(["export", "--format", "psych-ds", "--include-screened-out", "--out", str(out), *overrides]) == 0
    assert check_dataset(out) == []
    log = read_log(out)
    mine = log[log.participant == SCREENED]
    assert set(mine.phase) == {"practice"} and mine.attempt.min() == 1 and len(mine) > 1
    assert log[log.participant != SCREENED].phase.isna().all()


# every column described --------------------------------------------------------------------------------------
def test_every_field_the_export_writes_has_a_description(study):
    """A field added to the export's records fails here until it is described (EXPORT_VARIABLES)."""
    _, _, store, _ = study
    keys = {k for r in log_records(store, include_screened_out=True)[0] for k in r}
    described = variables()
    assert sorted(keys - set(described)) == []
    assert {f.name for f in FIELDS} <= set(described)
    assert set(EXPORT_VARIABLES) <= keys  # no description of a field the export no longer writes
    for name, v in described.items():
        assert v.description.strip() and v.kind in ("integer", "number", "boolean", "string", "list"), name


def test_a_record_with_an_undescribed_field_is_refused(study, tmp_path):
    _, _, store, _ = study
    records = [{**r, "framework_commit": "abc123"} for r in log_records(store)[0]]
    with pytest.raises(PsychDSError, match="'framework_commit'"):
        write_psychds(records, tmp_path / "out")
    assert not (tmp_path / "out").exists()


# the check on broken copies -------------------------------------------------------------------------------------
def _meta(folder, change):
    path = folder / "dataset_description.json"
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))


def _first_file(folder):
    return sorted((folder / "data").glob("*_data.csv"))[0]


def _edit_first(folder, edit):
    path = _first_file(folder)
    path.write_text(edit(path.read_text()))


BREAKAGES = {
    "no description file": (lambda d: (d / "dataset_description.json").unlink(), "no dataset_description.json"),
    "description not JSON": (lambda d: (d / "dataset_description.json").write_text("{\"name\": "),
                             "not valid JSON"),
    "no context": (lambda d: _meta(d, lambda m: m.pop("@context")), "@context must be schema.org"),
    "wrong type": (lambda d: _meta(d, lambda m: m.update({"@type": "Thing"})), "@type must be Dataset"),
    "no name": (lambda d: _meta(d, lambda m: m.pop("name")), "name must be a non-empty string"),
    "empty description": (lambda d: _meta(d, lambda m: m.update(description=" ")), "description must be"),
    "no variables": (lambda d: _meta(d, lambda m: m.pop("variableMeasured")), "variableMeasured must be"),
    "a column not listed": (lambda d: _meta(d, lambda m: m["variableMeasured"].pop(3)),
                            "column 'task_id' is not in dataset_description.json's variableMeasured"),
    "a variable not used": (lambda d: _meta(d, lambda m: m["variableMeasured"].append("mood")),
                            "lists 'mood', a column of no data file"),
    "a variable listed twice": (lambda d: _meta(d, lambda m: m["variableMeasured"].append("trial")),
                                "lists 'trial' twice"),
    "a bad variable": (lambda d: _meta(d, lambda m: m["variableMeasured"].append({"@type": "Person", "name": "x"})),
                       "must have @type PropertyValue"),
    "no data folder": (lambda d: shutil.rmtree(d / "data"), "no data/ folder"),
    "no data file": (lambda d: [p.unlink() for p in (d / "data").iterdir()], "holds no data file"),
    "a badly named file": (lambda d: _first_file(d).rename(d / "data" / "P1.csv"),
                           "data/P1.csv: a data file's name must be keyword-value pairs"),
    "a value not alphanumeric": (lambda d: _first_file(d).rename(d / "data" / "study-overhang_subject-P_1_data.csv"),
                                 "keyword-value pairs ending _data.csv"),
    "a stray file": (lambda d: (d / "data" / "notes.txt").write_text("hello"), "data/notes.txt: not a data file"),
    "a sidecar": (lambda d: (d / "data" / "study-overhang_subject-P1_data.json").write_text("{}"),
                  "metadata for part of the data"),
    "an empty data file": (lambda d: _first_file(d).write_text(""), "no header row"),
    "a short row": (lambda d: _edit_first(d, lambda t: t + "1,2,3\n"), "3 cells, but the header names"),
    "a column twice": (lambda d: _edit_first(d, lambda t: t.replace("trial,", "step,", 1)),
                       "names column 'step' twice"),
    "not UTF-8": (lambda d: _first_file(d).write_bytes(b"participant\n\xff\xfe\n"), "not UTF-8"),
}


@pytest.mark.parametrize("breakage", BREAKAGES)
def test_each_rule_fails_a_broken_copy_with_a_clear_message(exports, tmp_path, breakage):
    folder = tmp_path / "copy"
    shutil.copytree(exports[1], folder)
    assert check_dataset(folder) == []
    brake, words = BREAKAGES[breakage]
    brake(folder)
    problems = check_dataset(folder)
    assert problems and any(words in p for p in problems), problems
    assert all("\n" not in p for p in problems)
    with pytest.raises(PsychDSError, match="not a valid Psych-DS dataset"):
        read_log(folder)


def test_ignored_and_hidden_files_do_not_break_the_dataset(exports, tmp_path):
    folder = tmp_path / "copy"
    shutil.copytree(exports[1], folder)
    (folder / "data" / "notes.txt").write_text("hello")
    (folder / "data" / ".DS_Store").write_bytes(b"\0")
    (folder / ".psychdsignore").write_text("notes.txt\n")
    (folder / "README.md").write_text("a dataset\n")  # beside data/: allowed
    assert check_dataset(folder) == []
    pd.testing.assert_frame_equal(read_log(folder), read_log(exports[0]))


def test_the_checker_command_says_what_is_wrong(exports, tmp_path, capsys):
    from overhang_framework.behaviour.psychds import main as check

    assert check([str(exports[1])]) == 0 and "a valid Psych-DS dataset (5 data files)" in capsys.readouterr().out
    folder = tmp_path / "copy"
    shutil.copytree(exports[1], folder)
    (folder / "data" / "notes.txt").write_text("hello")
    assert check([str(folder)]) == 2 and "data/notes.txt: not a data file" in capsys.readouterr().err


# the command -----------------------------------------------------------------------------------------------------
def test_an_unknown_format_is_refused_in_one_line(study, tmp_path, capsys):
    _, overrides, _, _ = study
    assert main(["export", "--format", "csv", "--out", str(tmp_path / "o"), *overrides]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "error: --format csv: unknown format; formats: jsonl, psych-ds"
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("kind", ["a file", "a folder of other things"])
def test_an_out_that_is_not_an_earlier_export_is_refused_and_kept(study, tmp_path, capsys, kind):
    _, overrides, _, _ = study
    out = tmp_path / "out"
    if kind == "a file":
        out.write_text("keep me")
    else:
        out.mkdir()
        (out / "thesis.tex").write_text("keep me")
    assert main(["export", "--format", "psych-ds", "--out", str(out), *overrides]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("error: ") and ("new or empty folder" in err)
    assert (out.read_text() if kind == "a file" else (out / "thesis.tex").read_text()) == "keep me"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no staging folder left beside it


def test_an_earlier_export_is_replaced_whole(study, exports, tmp_path):
    _, overrides, _, _ = study
    out = tmp_path / "again"
    shutil.copytree(exports[1], out)
    old = out / "data" / "study-overhang_subject-gone_data.csv"
    shutil.copy(_first_file(out), old)  # a participant since deleted from the database
    (tmp_path / "empty").mkdir()
    assert main(["export", "--format", "psych-ds", "--out", str(out), *overrides]) == 0
    assert main(["export", "--format", "psych-ds", "--out", str(tmp_path / "empty"), *overrides]) == 0
    assert not old.exists() and check_dataset(out) == [] and check_dataset(tmp_path / "empty") == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again", "empty"]
    pd.testing.assert_frame_equal(read_log(out), read_log(exports[0]))


def test_a_running_servers_export_is_written_as_a_dataset(study, exports, tmp_path, monkeypatch):
    _, overrides, _, client = study

    def ask(method, url, headers, timeout):  # the running server is the test client
        return client.request(method, httpx.URL(url).path, headers=headers)

    monkeypatch.setattr(httpx, "request", ask)
    out = tmp_path / "served"
    assert main(["export", "--format", "psych-ds", "--out", str(out), "--url", "http://study.test",
                 f"admin_token={ADMIN}"]) == 0
    assert check_dataset(out) == []
    pd.testing.assert_frame_equal(read_log(out), read_log(exports[0]))
    assert list(read_log(out).columns[:len(COLUMNS)]) == list(COLUMNS)


def test_a_dataset_has_the_standards_root_files_and_its_sidecar_is_ignored(exports):
    from overhang_framework.behaviour.psychds import SCHEMA_VERSION

    folder = exports[1]
    assert sorted(p.name for p in folder.iterdir()) == [".psychds-ignore", ".psychdsignore", "CHANGES.md", "README.md",
                                                        "data", "dataset_description.json", "study.json"]
    for name in (".psychdsignore", ".psychds-ignore"):  # every root file the standard does not cover is listed
        listed = [line for line in (folder / name).read_text().splitlines() if line and not line.startswith("#")]
        assert listed == [".psychds-ignore", ".psychdsignore", "study.json"]
    meta = json.loads((folder / "dataset_description.json").read_text())
    assert meta["schemaVersion"] == SCHEMA_VERSION
    readme = (folder / "README.md").read_text()
    assert readme.startswith(f"# {meta['name']}\n") and "study.json" in readme and "subject-" in readme
    assert (folder / "CHANGES.md").read_text().count("\n- ") == 1


def test_file_names_depend_on_their_participant_alone_and_survive_a_withdrawal(exports, tmp_path):
    from overhang_framework.behaviour.psychds import subject_label
    from overhang_framework.experiment.export import write_psychds

    assert subject_label("labP1") == "labP1" and subject_label("lab_P1").startswith("labP1x")
    assert subject_label("lab_P1") != subject_label("lab.P1")
    # two ids with the same letters and digits, as a lab's ids can be
    names = {"P1": "labP1", "P2": "lab_P1"}
    rows = [{**r, "participant": names.get(r["participant"], r["participant"])}
            for r in (json.loads(line) for line in exports[0].read_text().splitlines())]
    out = tmp_path / "dataset"
    before = {p.name for p in write_psychds(rows, out)}
    after = {p.name for p in write_psychds([r for r in rows if r["participant"] != "labP1"], out)}
    assert after < before and before - after == {"study-overhang_subject-labP1_data.csv"}  # the others keep theirs
    assert check_dataset(out) == []
    assert (out / "CHANGES.md").read_text().count("\n- ") == 2  # the history of exports goes on
