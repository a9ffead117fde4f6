"""Where the experiment's records come from, consent and withdrawal: the study's stored settings and versions,
the refusal of a restart with other settings, the consent record, ``withdraw`` and the stored public address."""

from __future__ import annotations

import json
import re
import os
import shutil
from pathlib import Path

import pytest

from overhang_framework.experiment.settings import load_settings

ADMIN = "long-enough-token"


def _serve_app(overrides, clock=None):
    """A test client of the app the settings ``overrides`` give (what one server process runs)."""
    from fastapi.testclient import TestClient

    from overhang_framework.experiment.api import create_app

    settings = load_settings([*overrides, f"admin_token={ADMIN}"])
    client = TestClient(create_app(settings, **({"clock": clock} if clock else {})))
    client.settings = settings
    return client


def _session(client, pid, consent=True, simulated=False):
    body = {"params": {"participant": pid}, **({"simulated": True} if simulated else {})}
    s = client.post("/api/sessions", json=body, headers={"X-Admin-Token": ADMIN} if simulated else {}).json()
    h = {"Authorization": f"Bearer {s['token']}"}
    if consent:
        reply = client.post("/api/consent", json={"version": s["consent"]["version"]}, headers=h)
        assert reply.status_code == 200, reply.text
    return s, h


def _play(client, pid, main_trials=1, simulated=False):
    """``pid`` consents, passes the practice with the shown towers and builds ``main_trials`` main towers."""
    s, h = _session(client, pid, simulated=simulated)

    def place(phase, trial, step, x, layer):
        body = {"phase": phase, "trial": trial, "step": step}
        assert client.post("/api/steps/start", json=body, headers=h).status_code == 200
        reply = client.post("/api/placements", json={**body, "x": x, "layer": layer, "decision_time": 1.0}, headers=h)
        assert reply.status_code == 200, reply.text
        return reply.json()

    for k, pt in enumerate(client.settings.practice, 1):
        for step, (_, x, layer) in enumerate(pt.shown_tower[1:], 1):
            place("practice", k, step, x, layer)
    order = client.app.state.store.participant(pid).order
    by_id = {t.id: t for t in client.settings.tasks}
    for trial in range(1, main_trials + 1):
        for step in range(1, len(by_id[order[trial - 1]].sequence)):
            if place("main", trial, step, 0.0, step)["trial_over"]:
                break
    return s, h


@pytest.fixture
def overrides(tmp_path):
    return [f"run_dir={tmp_path}", "tasks.only=[paper03,paper00]", "physics_processes=0"]


def test_every_placement_and_exported_record_carries_the_version_commit_and_settings_hashes(overrides):
    from overhang_framework.experiment.export import log_records
    from overhang_framework.experiment.provenance import digest, hashes, study_settings, task_set
    from overhang_framework.version import versions

    client = _serve_app(overrides)
    _play(client, "P1")
    store = client.app.state.store
    want = {**versions(), **hashes(client.settings)}
    assert want["settings_hash"] == digest(study_settings(client.settings))
    assert want["tasks_hash"] == digest(task_set(client.settings))
    rows = store.placements("P1")
    assert rows and all({k: getattr(r, k) for k in want} == want for r in rows)
    records, _ = log_records(store)
    assert records and all({k: r[k] for k in want} == want for r in records)
    assert {r["consent_version"] for r in records} == {client.settings.consent_version}
    assert all(r["consented_at"] for r in records)
    study = store.study()
    assert study.settings == json.loads(json.dumps(study_settings(client.settings)))
    assert (study.settings_hash, study.tasks_hash) == (want["settings_hash"], want["tasks_hash"])


def test_a_restart_with_settings_participants_see_is_refused_in_one_line_and_an_allowed_change_is_recorded(
        overrides, capsys):
    from overhang_framework.errors import ConfigError
    from overhang_framework.experiment.__main__ import main

    first = _serve_app(overrides)
    _play(first, "P1")
    old_hash = first.app.state.store.study().settings_hash
    first.app.state.store.close()
    # where the server listens and how many processes it runs change nothing a participant sees
    _serve_app([*overrides, "port=8123", "workers=1", "keep_alive=30", "world.cache=false",
                "world.workers=2"]).app.state.store.close()
    with pytest.raises(ConfigError, match=r"tasks\[0\]: \[\"paper00\", .*\] -> \[\"paper01\", .*\]; time_limit: 5\.0 -> 4\.0\); .*allow_settings_change=true"):
        _serve_app([*overrides[:1], "tasks.only=[paper03,paper01]", "physics_processes=0", "time_limit=4"])
    # the command line says it in one line, before it listens
    assert main([*overrides, "time_limit=4", f"admin_token={ADMIN}", "port=0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: the study in this database runs with other settings "
                                                   "(time_limit: 5.0 -> 4.0)")
    changed = _serve_app([*overrides, "time_limit=4", "allow_settings_change=true"])
    store = changed.app.state.store
    study = store.study()
    events = [e for e in study.history if e["what"] == "settings"]
    assert len(events) == 1 and events[0]["changes"] == ["time_limit: 5.0 -> 4.0"] and events[0]["at"]
    assert [e["changes"] for e in study.history if e["what"] == "address"] == [
        ["address: http://127.0.0.1:8000 -> http://127.0.0.1:8123"],
        ["address: http://127.0.0.1:8123 -> http://127.0.0.1:8000"]]
    assert study.settings_hash != old_hash and study.settings["time_limit"] == 4.0
    _play(changed, "P2")
    hashes = {(r.participant_id, r.settings_hash) for r in store.placements()}
    assert hashes == {("P1", old_hash), ("P2", study.settings_hash)}
    # the same changed settings again are no change
    again = _serve_app([*overrides, "time_limit=4"])
    assert len(again.app.state.store.study().history) == len(study.history)


def test_a_changed_consent_text_is_a_change_of_settings(overrides, tmp_path):
    from overhang_framework.errors import ConfigError

    _serve_app(overrides).app.state.store.close()
    text = tmp_path / "consent.html"
    text.write_text("<p>Other words.</p>")
    with pytest.raises(ConfigError, match=r"consent_version: sha256:[0-9a-f]{16} -> sha256:[0-9a-f]{16}"):
        _serve_app([*overrides, f"consent_file={text}"])
    with pytest.raises(ConfigError, match=r"consent_version: "):  # the shipped text names the contact
        _serve_app([*overrides, "contact=lab@example.org"])
    with pytest.raises(ConfigError, match=r"consent_file: cannot read .*nowhere\.html"):
        load_settings([*overrides, f"consent_file={tmp_path / 'nowhere.html'}", f"admin_token={ADMIN}"])


def test_consent_is_stored_with_its_time_and_version_and_nothing_is_placed_before_it(overrides):
    client = _serve_app(overrides)
    s, h = _session(client, "P1", consent=False)
    assert s["consent"]["html"] == client.settings.consent_html and "I agree" in s["consent"]["html"]
    assert f"by contacting {client.settings.contact}: your" in s["consent"]["html"]  # @contact@ filled in
    assert s["consent"]["given"] is False
    body = {"phase": "practice", "trial": 1, "step": 1}
    refused = client.post("/api/steps/start", json=body, headers=h)
    assert refused.status_code == 403 and refused.json()["reason"] == "no_consent"
    refused = client.post("/api/placements", json={**body, "x": 0.0, "layer": 1, "decision_time": 1.0}, headers=h)
    assert refused.status_code == 403 and "POST /api/consent first" in refused.json()["error"]
    stale = client.post("/api/consent", json={"version": "sha256:0000000000000000"}, headers=h)
    assert stale.status_code == 409 and "reload the page" in stale.json()["error"]
    agreed = client.post("/api/consent", json={"version": s["consent"]["version"]}, headers=h).json()
    assert agreed["consent_version"] == client.settings.consent_version
    p = client.app.state.store.participant("P1")
    assert p.consent_version == client.settings.consent_version and p.consented_at is not None
    again = client.post("/api/consent", json={"version": s["consent"]["version"]}, headers=h).json()
    assert again == agreed  # the first record stays
    assert client.get("/api/session", headers=h).json()["consent"]["given"] is True
    assert client.post("/api/steps/start", json=body, headers=h).status_code == 200


def test_withdraw_deletes_a_participant_from_the_database_and_every_later_export_and_keeps_a_count(
        overrides, tmp_path, capsys):
    from overhang_framework.behaviour.log import read_log
    from overhang_framework.experiment.__main__ import main

    client = _serve_app(overrides)
    for pid in ("P1", "P2", "P3"):
        _play(client, pid)
    store = client.app.state.store
    out = tmp_path / "before" / "log.jsonl"
    out.parent.mkdir()
    assert main(["export", "--out", str(out), *overrides]) == 0
    assert set(read_log(out).participant) == {"P1", "P2", "P3"}
    capsys.readouterr()
    assert main(["withdraw", "P2", *overrides]) == 2
    assert "add --yes" in capsys.readouterr().err and store.participant("P2") is not None
    n = len(store.placements("P2"))
    assert main(["withdraw", "P2", "--yes", *overrides]) == 0
    err = capsys.readouterr().err
    assert err.startswith(f"withdrew participant P2: deleted them with {n} placement(s)") and "1 withdrawn" in err
    assert store.participant("P2") is None and store.placements("P2") == []
    assert store.clock("P2", "practice", 1, 1, 1) is None
    after = tmp_path / "after" / "log.jsonl"
    after.parent.mkdir()
    assert main(["export", "--out", str(after), *overrides]) == 0
    assert set(read_log(after).participant) == {"P1", "P3"}
    study = json.loads((after.parent / "log.study.json").read_text())
    assert study["participants"]["withdrawn"] == 1 and study["participants"]["total"] == 2
    assert "P2" not in (after.parent / "log.study.json").read_text()
    # P2 cannot come back, with the old link or as a newcomer
    back = client.post("/api/sessions", json={"params": {"participant": "P2"}})
    assert back.status_code == 403 and back.json()["reason"] == "session_elsewhere"
    # and the answer to the id alone is the one of a participant half way or finished: it does not say they withdrew
    busy = client.post("/api/sessions", json={"params": {"participant": "P1"}})
    assert busy.status_code == back.status_code and busy.json() == {**back.json(), "error": busy.json()["error"]}
    assert back.json()["error"].replace("P2", "P1") == busy.json()["error"]
    assert "withdr" not in back.text
    assert store.participant("P2") is None
    capsys.readouterr()
    assert main(["withdraw", "P2", "--yes", *overrides]) == 2
    assert capsys.readouterr().err == "error: no participant 'P2'; the study has 2: P1, P3\n"
    # through a running server, with the admin token
    reply = client.post("/api/admin/participants/P3/withdraw", headers={"X-Admin-Token": ADMIN})
    assert reply.status_code == 200 and reply.json()["withdrawn"] == 2
    assert client.get("/api/admin/study", headers={"X-Admin-Token": ADMIN}).json()["participants"]["withdrawn"] == 2
    assert client.post("/api/admin/participants/P3/withdraw").status_code in (401, 403)


def test_the_export_sidecar_holds_the_settings_versions_and_the_first_and_last_participant(overrides, tmp_path):
    from overhang_framework.experiment.__main__ import main
    from overhang_framework.experiment.provenance import study_settings
    from overhang_framework.experiment.store import utc_iso
    from overhang_framework.version import versions

    client = _serve_app(overrides)
    for pid in ("P1", "P2"):
        _play(client, pid)
    people = client.app.state.store.participants()
    out = tmp_path / "export" / "log.jsonl"
    out.parent.mkdir()
    assert main(["export", "--out", str(out), *overrides]) == 0
    study = json.loads((out.parent / "log.study.json").read_text())
    assert study["study"]["settings"] == json.loads(json.dumps(study_settings(client.settings)))
    assert {k: study["study"][k] for k in ("framework_version", "commit")} == versions()
    assert study["exported_with"] == versions()
    created = sorted(utc_iso(p.created_at) for p in people)
    assert (study["first_participant"], study["last_participant"]) == (created[0], created[-1])
    assert study["participants"]["by_condition"] == {c: sum(p.condition == c for p in people)
                                                     for c in {p.condition for p in people}}
    assert study == client.get("/api/admin/study", headers={"X-Admin-Token": ADMIN}).json()


def test_reissue_takes_the_public_address_stored_with_the_study(overrides, capsys):
    from overhang_framework.experiment.__main__ import main

    client = _serve_app([*overrides, "public_url=https://study.example.org/tower"])
    _session(client, "P1")
    client.app.state.store.close()
    assert main(["reissue", "P1", *overrides]) == 0  # no public_url given: the stored one
    out = capsys.readouterr()
    assert out.out.startswith("https://study.example.org/tower/?participant=P1&token=") and "note:" not in out.err
    assert main(["reissue", "P1", *overrides, "public_url=https://elsewhere.example.org"]) == 0
    assert capsys.readouterr().out.startswith("https://elsewhere.example.org/?participant=P1&token=")


def test_reissue_without_a_public_url_takes_the_address_the_server_listened_on(overrides, capsys):
    from overhang_framework.experiment.__main__ import main

    client = _serve_app([*overrides, "port=8123"])
    _session(client, "P1")
    client.app.state.store.close()
    assert main(["reissue", "P1", *overrides]) == 0  # the command line's port is 8000: the stored one counts
    out = capsys.readouterr()
    assert out.out.startswith("http://127.0.0.1:8123/?participant=P1&token=")
    assert "note: the link starts with http://127.0.0.1:8123" in out.err


def test_the_commands_refuse_targets_they_would_clobber_and_arguments_in_the_wrong_place(overrides, tmp_path, capsys):
    from overhang_framework.experiment.__main__ import main

    client = _serve_app(overrides)
    _play(client, "P1")
    client.app.state.store.close()
    other = tmp_path / "notes.csv"
    other.write_text("a,b\n1,2\n")
    folder = tmp_path / "folder"
    folder.mkdir()
    cases = [
        (["export", "--out", str(other)], "exists and is not a behaviour log"),
        (["export", "--out", str(tmp_path / "x.study.json")], "study.json sidecar"),
        (["export", "--out", str(folder)], "is a folder"),
        (["backup", "--out", str(folder)], "is a folder"),
        (["withdraw", "--yes"], "withdraw needs a participant's id first"),
        (["reissue"], "reissue needs a participant's id first"),
        (["withdraw", "nobody"], "no participant 'nobody'; the study has 1: P1"),
    ]
    for words, message in cases:
        assert main([*words, *overrides]) == 2, words
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and message in err, (words, err)
    assert other.read_text() == "a,b\n1,2\n" and list(folder.iterdir()) == []
    assert main(["withdraw", "P1", *overrides]) == 2
    err = capsys.readouterr().err
    assert "deletes them with their" in err and "nothing was deleted" in err
    # exports into one folder keep their own sidecars
    assert main(["export", "--out", str(tmp_path / "a.jsonl"), *overrides]) == 0
    assert main(["export", "--out", str(tmp_path / "b.jsonl"), *overrides]) == 0
    assert (tmp_path / "a.study.json").is_file() and (tmp_path / "b.study.json").is_file()
    assert main(["export", "--out", str(tmp_path / "a.jsonl"), *overrides]) == 0  # an earlier log is replaced



def test_the_commands_help_lists_every_command_and_says_what_each_does(capsys):
    from overhang_framework.experiment.__main__ import DESCRIPTIONS, SUMMARIES, main

    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert set(SUMMARIES) == set(DESCRIPTIONS)
    for command, summary in SUMMARIES.items():
        assert f"  {command:<13} {summary}" in text
    with pytest.raises(SystemExit):
        main(["withdraw", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert DESCRIPTIONS["withdraw"] in text and "without it nothing is deleted" in text


def test_a_participant_who_does_not_agree_leaves_nothing_but_a_count(overrides):
    client = _serve_app(overrides)
    s, h = _session(client, "P1", consent=False)
    store = client.app.state.store
    assert store.participant("P1") is not None  # the session exists before the consent page
    reply = client.post("/api/decline", headers=h)
    assert reply.status_code == 200 and reply.json() == {"decline_url": "/declined"}
    assert store.participant("P1") is None and store.participants() == []
    assert client.get("/api/admin/study", headers={"X-Admin-Token": ADMIN}).json()["participants"]["declined"] == 1
    assert client.post("/api/consent", json={"version": s["consent"]["version"]}, headers=h).status_code == 403
    assert "Nothing about you is kept" in client.get("/declined").text
    # who agreed cannot decline: only withdrawal deletes them
    s2, h2 = _session(client, "P2")
    refused = client.post("/api/decline", headers=h2)
    assert refused.status_code == 409 and "withdraw" in refused.json()["error"]
    assert store.participant("P2") is not None


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0 or shutil.which("git") is None
                    or not Path("/usr/bin/python3").exists(),
                    reason="needs root (to run as another user), git and the system's Python")
def test_the_commit_is_read_by_a_service_user_from_a_checkout_root_owns_and_not_from_another_users(
        tmp_path, service_user):
    """The deployment's case: the service's user reads a checkout that root owns, which plain git refuses as
    "dubious ownership". A checkout of another unprivileged user is not trusted (its configuration could run
    code as the reader): root gets no commit from it."""
    import pwd
    import subprocess
    import tempfile

    from test_experiment_deploy import service_python

    from overhang_framework.version import commit_of

    home = Path(tempfile.mkdtemp(prefix="overhang-checkout-", dir="/tmp"))
    try:
        os.chmod(home, 0o755)
        package = home / "checkout" / "overhang_framework"
        package.mkdir(parents=True)
        (package / "__init__.py").write_text("")

        def git(*args):
            return subprocess.run(["git", "-c", "user.email=lab@example.org", "-c", "user.name=lab", *args],
                                  cwd=package.parent, check=True, capture_output=True, text=True).stdout.strip()

        git("init", "-q")
        git("add", ".")
        git("commit", "-qm", "the lab's checkout")
        head = git("rev-parse", "HEAD")
        subprocess.run(["chmod", "-R", "a+rX", str(home)], check=True)
        user = pwd.getpwnam(service_user)
        python = service_python(home)
        ask = f"from pathlib import Path; from overhang_framework.version import commit_of; print(commit_of(Path({str(package)!r})))"

        def as_service(*words):
            return subprocess.run([*words], capture_output=True, text=True, user=user.pw_uid, group=user.pw_gid,
                                  extra_groups=[], env={"PATH": "/usr/bin:/bin", "HOME": str(home)})

        refused = as_service("git", "-C", str(package), "rev-parse", "HEAD")
        assert refused.returncode != 0 and "dubious ownership" in refused.stderr  # what plain git says
        assert as_service(python, "-c", ask).stdout.strip() == head
        (package / "__init__.py").write_text("changed = True\n")
        assert as_service(python, "-c", ask).stdout.strip() == head + "-dirty"
        assert commit_of(package) == head + "-dirty"  # root reads its own checkout
        subprocess.run(["chown", "-R", "nobody", str(package.parent)], check=True)
        assert commit_of(package) == ""  # another unprivileged user's checkout: not trusted
    finally:
        shutil.rmtree(home, ignore_errors=True)


def test_a_participant_who_started_before_an_allowed_change_exports_with_the_hash_and_limit_they_played_under(
        overrides):
    from overhang_framework.experiment.export import log_records, study_json
    from overhang_framework.experiment.provenance import digest

    limited = [*overrides, "conditions=[time_limited]"]
    first = _serve_app(limited)
    s1, h1 = _session(first, "P1")  # starts under 5 s, places nothing yet
    old_hash = first.app.state.store.study().settings_hash
    first.app.state.store.close()
    # the limit and the bonus change; P1 keeps their limit, and gets the new bonus
    changed = _serve_app([*limited, "time_limit=4", "bonus_per_unit=0.3", "allow_settings_change=true"])
    store = changed.app.state.store
    new = store.study()
    new_hash = new.settings_hash
    played = {**new.settings, "time_limit": 5.0}
    played_hash = digest(played)
    assert len({old_hash, new_hash, played_hash}) == 3
    for k, pt in enumerate(changed.settings.practice, 1):
        for step, (_, x, layer) in enumerate(pt.shown_tower[1:], 1):
            body = {"phase": "practice", "trial": k, "step": step}
            assert changed.post("/api/steps/start", json=body, headers=h1).status_code == 200
            reply = changed.post("/api/placements", json={**body, "x": x, "layer": layer, "decision_time": 1.0},
                                 headers=h1)
            assert reply.status_code == 200, reply.text
    order = store.participant("P1").order
    by_id = {t.id: t for t in changed.settings.tasks}
    for step in range(1, len(by_id[order[0]].sequence)):
        body = {"phase": "main", "trial": 1, "step": step}
        assert changed.post("/api/steps/start", json=body, headers=h1).status_code == 200
        reply = changed.post("/api/placements", json={**body, "x": 0.0, "layer": step, "decision_time": 1.0},
                             headers=h1)
        if reply.json()["trial_over"]:
            break
    _play(changed, "P2")
    assert {(r.participant_id, r.settings_hash) for r in store.placements()} == {("P1", played_hash),
                                                                                ("P2", new_hash)}
    records, _ = log_records(store)
    assert {(r["participant"], r["settings_hash"], r["time_limit"]) for r in records} == {
        ("P1", played_hash, 5.0), ("P2", new_hash, 4.0)}
    # every hash a record carries resolves in the sidecar, to the settings in force for that participant
    study = study_json(store)["study"]
    assert study["settings_hash"] == new_hash
    assert study["played_settings"] == {played_hash: played}
    assert played["time_limit"] == 5.0 and played["bonus_per_unit"] == 0.3
    earlier = {e["previous"]["settings_hash"]: e["previous"]["settings"] for e in study["history"]
               if e["what"] == "settings"}
    assert earlier[old_hash]["time_limit"] == 5.0


def test_a_pilots_participants_are_stored_as_simulated_and_left_out_of_a_default_export(overrides, tmp_path):
    from overhang_framework.experiment.export import log_records, study_json, write_psychds

    client = _serve_app(overrides)
    # a page cannot mark itself simulated: only a pilot with the study's admin token can
    refused = client.post("/api/sessions", json={"params": {"participant": "sly"}, "simulated": True})
    assert refused.status_code == 403 and "admin token" in refused.json()["error"]
    assert client.app.state.store.participant("sly") is None
    _play(client, "person")
    _play(client, "pilot-001", simulated=True)
    _play(client, "pilot-002")  # a session the page starts is a person's, whatever its id
    store = client.app.state.store
    assert store.participant("pilot-001").source == "simulated" and store.participant("person").source == "human"
    records, _ = log_records(store)
    assert {r["participant"] for r in records} == {"person", "pilot-002"}
    assert {r["source"] for r in records} == {"human"}
    assert study_json(store)["participants"]["simulated"] == 1
    admin = {"X-Admin-Token": ADMIN}
    assert "pilot-001" not in client.get("/api/admin/export", headers=admin).text
    asked = client.get("/api/admin/export?include_simulated=true", headers=admin).text
    assert {json.loads(line)["source"] for line in asked.splitlines() if "pilot-001" in line} == {"simulated"}
    records, _ = log_records(store, include_simulated=True)
    write_psychds(records, tmp_path / "dataset")
    description = json.loads((tmp_path / "dataset" / "dataset_description.json").read_text())["description"]
    assert description.startswith("People (2) and simulated participants of a pilot (1, source: simulated)")


def test_stored_rewards_and_the_practice_pass_mark_carry_no_float_noise(overrides):
    from types import SimpleNamespace

    from overhang_framework.experiment.api import total_reward

    rewards = [2.1, 2.1, 2.1]
    assert repr(sum(rewards)) == "6.300000000000001"  # what a plain sum stores
    trials = [SimpleNamespace(reward=r, trial_over=True) for r in rewards]
    assert repr(total_reward([*trials, SimpleNamespace(reward=None, trial_over=False)])) == "6.3"
    settings = load_settings([*overrides, f"admin_token={ADMIN}"])
    for practice in settings.practice:
        assert len(repr(practice.pass_reward)) <= 5 and len(repr(practice.shown_reward)) <= 5, practice


def test_a_new_contact_is_refused_as_the_consent_text_change_it_is_and_says_so(overrides):
    from overhang_framework.errors import ConfigError

    _serve_app([*overrides, "contact=lab@example.org"]).app.state.store.close()
    with pytest.raises(ConfigError, match=r"consent_version: .* -> .*\) \(the consent text changed: it includes the "
                                          r"contact= and the session's duration=, so a new contact, duration, "
                                          r"durations or consent_file changes it\); serve"):
        _serve_app([*overrides, "contact=other-lab@example.org"])


def test_a_pilots_sessions_do_not_unbalance_the_peoples_conditions(overrides):
    client = _serve_app([*overrides, "conditions=[time_limited,unconstrained]"])
    for k in range(3):  # a pilot against the live study, first
        _session(client, f"pilot-{k}", consent=False, simulated=True)
    store = client.app.state.store
    people = [client.post("/api/sessions", json={"params": {"participant": f"P{k}"}}).json()["condition"]
              for k in range(4)]
    assert sorted(people) == ["time_limited"] * 2 + ["unconstrained"] * 2  # balanced among people alone
    pilots = [store.participant(f"pilot-{k}").condition for k in range(3)]
    assert sorted(set(pilots)) == ["time_limited", "unconstrained"]  # and the pilot's among themselves


def test_each_level_s_consent_page_states_its_own_expected_duration(overrides):
    """``durations`` gives each condition its expected minutes, which its consent page states (``duration`` the
    rest): a participant sees and agrees to their condition's text, whose version is stored with their consent; a
    page of another condition's version is refused; bad durations are one line."""
    from overhang_framework.errors import ConfigError

    words = [*overrides, "conditions=[time_limited,unconstrained]", "+durations.unconstrained=25", "duration=15"]
    client = _serve_app(words)
    assert client.settings.durations == {"time_limited": 15.0, "unconstrained": 25.0}
    seen = {}
    for pid in ("P1", "P2", "P3", "P4"):
        s, h = _session(client, pid, consent=False)
        seen.setdefault(s["condition"], []).append((s, h))
    assert set(seen) == {"time_limited", "unconstrained"}  # balanced: two each
    (tl, tl_h), (un, un_h) = seen["time_limited"][0], seen["unconstrained"][0]
    assert "It takes about 15 minutes." in tl["consent"]["html"] and "about 25 minutes" in un["consent"]["html"]
    assert "@duration@" not in tl["consent"]["html"] and tl["consent"]["version"] != un["consent"]["version"]
    assert seen["time_limited"][1][0]["consent"] == tl["consent"]  # one text a condition
    refused = client.post("/api/consent", json={"version": un["consent"]["version"]}, headers=tl_h)
    assert refused.status_code == 409 and "reload the page" in refused.json()["error"]
    for s, h in ((tl, tl_h), (un, un_h)):
        assert client.post("/api/consent", json={"version": s["consent"]["version"]}, headers=h).status_code == 200
        assert client.app.state.store.participant(s["participant"]).consent_version == s["consent"]["version"]
    # the study's consent version is of every condition's text: changing one level's duration changes it
    assert client.settings.consent_version not in (tl["consent"]["version"], un["consent"]["version"])
    client.app.state.store.close()
    with pytest.raises(ConfigError, match=r"consent_version: sha256:[0-9a-f]{16} -> sha256:[0-9a-f]{16}\).*"
                                          r"so a new contact, duration, durations or consent_file changes it"):
        _serve_app([*overrides, "conditions=[time_limited,unconstrained]", "+durations.unconstrained=30",
                    "duration=15"])
    for bad, words in (("+durations.unconstrained=-5", "durations.unconstrained must be a number of minutes > 0, "
                                                         "got -5"),
                       ("duration=soon", "duration must be a number of minutes > 0, got 'soon'"),
                       ("durations=[1,2]", "bad value for 'durations'"),
                       ("+durations.unconstrainted=25", "durations: 'unconstrainted' is not a condition of the study "
                                                        "(its conditions and time_limits: time_limited, unconstrained); "
                                                        "remove it with '~durations.unconstrainted'")):
        with pytest.raises(ConfigError, match=re.escape(words)):
            load_settings([*overrides, bad, f"admin_token={ADMIN}"])


def test_a_refused_restart_shows_where_two_long_settings_differ():
    """Two task lists that share a long start: the refusal names the changed task, or, when one is removed, each
    side shows the place where they part."""
    from overhang_framework.experiment.provenance import SHOWN, differences

    old = {"tasks": [{"id": f"paper{i:02d}", "sequence": [1.2, 0.6, 1.8]} for i in range(20)]}
    new = {"tasks": [*old["tasks"][:12], {"id": "paper12", "sequence": [1.2, 0.6, 0.6]}, *old["tasks"][13:]]}
    assert differences(old, new) == ["tasks[paper12].sequence: [1.2, 0.6, 1.8] -> [1.2, 0.6, 0.6]"]
    longer = {"tasks": [*old["tasks"][:12], *old["tasks"][13:]]}  # a task removed: the texts where they part
    (line,) = differences(old, longer)
    before, after = line.removeprefix("tasks: ").split(" -> ")
    assert before.startswith("...") and after.startswith("...") and '"paper12"' in before and '"paper13"' in after
    assert len(before) <= SHOWN and len(after) <= SHOWN
    assert differences({"time_limit": 5.0}, {"time_limit": 4}) == ["time_limit: 5.0 -> 4"]  # short values whole


def test_a_study_served_before_durations_were_settable_restarts_with_the_same_consent_text(overrides):
    """The shipped text said "about 30 minutes" before its duration was a setting: the default keeps that text, so a
    study already running restarts unchanged."""
    import hashlib

    from overhang_framework.experiment.settings import CONSENT_FILE

    settings = load_settings([*overrides, f"admin_token={ADMIN}"])
    before = CONSENT_FILE.read_text().replace("@duration@", "30").replace("@contact@", settings.contact)
    assert settings.consent_html == before and "about 30 minutes" in before
    assert settings.consent_version == "sha256:" + hashlib.sha256(before.encode()).hexdigest()[:16]


def test_a_participant_of_a_dropped_level_who_has_not_agreed_sees_their_own_level_s_duration(overrides):
    """A level dropped from the conditions (kept in time_limits and durations) while someone is in it: their consent
    page is their level's own text, its version the hash of what they see."""
    import hashlib

    settings = load_settings([*overrides, f"admin_token={ADMIN}", "conditions=[unconstrained]",
                              "+time_limits.limit_3s=3.0", "+durations.limit_3s=12", "+durations.unconstrained=25"])
    html, version = settings.consent_of("limit_3s")
    assert "about 12 minutes" in html and version == "sha256:" + hashlib.sha256(html.encode()).hexdigest()[:16]
    assert "about 25 minutes" in settings.consent_of("unconstrained")[0]
    assert "about 30 minutes" in settings.consent_of("time_limited")[0]  # none of its own: duration
