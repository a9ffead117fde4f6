"""The experiment's HTTP API: sessions, placements, refusals, resuming, the end and the export.

Every storage test runs on SQLite and on PostgreSQL. PostgreSQL is the server
that ``OVERHANG_TEST_POSTGRES_URL`` names (``.ci/run`` installs and starts one);
without it those tests are skipped, except under CI, where they fail.
"""

from __future__ import annotations

import os
import threading

import pytest
from fastapi.testclient import TestClient

from overhang_framework import rules
from overhang_framework.behaviour.log import read_log
from overhang_framework.experiment.api import create_app
from overhang_framework.experiment.settings import load_settings
from overhang_framework.experiment.store import Base, Store
from overhang_framework.geometry import Action, Geometry
from overhang_framework.plugins import Registry

ADMIN = "admin-secret-token"
PG_ENV = "OVERHANG_TEST_POSTGRES_URL"


@pytest.fixture(scope="module")
def base_settings(tmp_path_factory):
    run = tmp_path_factory.mktemp("experiment")
    return load_settings([f"run_dir={run}", f"admin_token={ADMIN}", "tasks.only=[paper00,paper03]", "physics_processes=0"])


@pytest.fixture(params=["sqlite", "postgresql"])
def database(request, tmp_path):
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'experiment.sqlite'}"
        return
    url = os.environ.get(PG_ENV)
    if not url:
        if os.environ.get("CI"):
            pytest.fail(f"{PG_ENV} is not set: .ci/run starts a PostgreSQL server and sets it")
        pytest.skip(f"no PostgreSQL server ({PG_ENV} not set)")
    from sqlalchemy import create_engine

    engine = create_engine(url)  # not a Store: tables of an earlier schema are dropped, not refused
    Base.metadata.drop_all(engine)
    engine.dispose()
    yield url


@pytest.fixture
def make_client(base_settings, database):
    clients = []

    def make(clock=None, **changes):
        settings = base_settings.__class__(**{**base_settings.__dict__, "database": database, **changes})
        store = Store(database)
        client = TestClient(create_app(settings, store=store, **({"clock": clock} if clock else {})))
        client.store = store
        clients.append(client)
        return client

    yield make
    for c in clients:
        c.store.close()


@pytest.fixture
def client(make_client):
    return make_client()


def start(client, pid="P1", token=None, consent=True):
    """Start (or resume) a session; ``consent`` then agrees to the consent text the session shows, as the page
    does when "I agree" is clicked."""
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    reply = client.post("/api/sessions", json={"params": {"participant": pid}}, headers=headers)
    if consent and reply.status_code in (200, 201):
        s = reply.json()
        agreed = client.post("/api/consent", json={"version": s["consent"]["version"]}, headers=auth(s))
        assert agreed.status_code == 200, agreed.text
    return reply


def auth(session):
    return {"Authorization": f"Bearer {session['token']}"}


def begin(client, session, phase, trial, step, attempt=1):
    """Start a step as the page does before a decision (the server's clock)."""
    body = {"phase": phase, "trial": trial, "attempt": attempt, "step": step}
    return client.post("/api/steps/start", json=body, headers=auth(session))


def place(client, session, phase, trial, step, x, layer, attempt=1, start=True, **extra):
    """A placement; ``start`` first starts the step, as the page does (a step already started is not restarted)."""
    if start:
        begin(client, session, phase, trial, step, attempt)
    body = {"phase": phase, "trial": trial, "attempt": attempt, "step": step, "x": x, "layer": layer,
            "decision_time": 1.0, **extra}
    return client.post("/api/placements", json=body, headers=auth(session))


def trials_of(client, session, pid=None):
    """The participant's main trials as the server holds them (the session sends a trial's blocks only when
    it starts): ``[{"trial", "task_id", "sequence"}, ...]``."""
    settings = client.app.state.settings
    by_id = {t.id: t for t in settings.tasks}
    order = client.store.participant(pid or session["participant"]).order
    return [{"trial": k, "task_id": i, "sequence": list(by_id[i].sequence)} for k, i in enumerate(order, 1)]


def practice_tower(client, k):
    """Practice trial ``k``'s shown tower: a tower that passes."""
    return client.app.state.settings.practice[k - 1].shown_tower


def pass_practice(client, session):
    reply = None
    for pt in session["practice"]:
        for step, (_, x, layer) in enumerate(practice_tower(client, pt["trial"])[1:], 1):
            reply = place(client, session, "practice", pt["trial"], step, x, layer)
            assert reply.status_code == 200, reply.json()
    return reply.json()


def stack(client, session, trial, sequence):
    """Each block centred on the one below: a tower that stands; the last reply."""
    for step in range(1, len(sequence)):
        reply = place(client, session, "main", trial, step, 0.0, step)
        assert reply.status_code == 200, reply.json()
    return reply.json()


def without_clock(reply: dict) -> dict:
    return {k: v for k, v in reply.items() if k != "clock"}


def rows(client):
    return client.store.count()["placements"]


def error(reply, status):
    assert reply.status_code == status, (reply.status_code, reply.text)
    message = reply.json()["error"]
    assert isinstance(message, str) and "\n" not in message and message
    return message


# sessions -----------------------------------------------------------------------------------------------------
def test_session_is_issued_then_resumed_only_with_its_token(client):
    first = start(client)
    assert first.status_code == 201
    s = first.json()
    assert s["position"] == {"phase": "practice", "trial": 1, "attempt": 1, "step": 1,
                             "tower": [[s["practice"][0]["sequence"][0], 0.0, 0]], "total_reward": 0}
    assert sorted(t["task_id"] for t in trials_of(client, s)) == ["paper00", "paper03"]
    assert s["trials"] == [{"trial": 1}, {"trial": 2}]  # the blocks come when a trial starts
    assert s["time_limit"] == (5.0 if s["condition"] == "time_limited" else None)
    again = start(client, token=s["token"])
    assert again.status_code == 200
    assert {k: again.json()[k] for k in ("condition", "trials")} == {k: s[k] for k in ("condition", "trials")}
    assert "already has a session" in error(start(client), 403)
    other = start(client, "P2").json()
    error(start(client, token=other["token"]), 403)  # another participant's token
    error(start(client, token="forged"), 403)


def test_prolific_parameters_identify_the_participant(client):
    s = client.post("/api/sessions", json={"params": {"PROLIFIC_PID": "5f1a", "STUDY_ID": "st", "SESSION_ID": "se"}})
    assert s.status_code == 201 and s.json()["participant"] == "5f1a"
    rows_ = client.get("/api/admin/participants", headers={"X-Admin-Token": ADMIN}).json()
    assert rows_[0]["study_id"] == "st" and rows_[0]["session_id"] == "se"


@pytest.mark.parametrize("body, words", [
    ({"params": {}}, "PROLIFIC_PID"),
    ({"params": {"participant": "a b"}}, "participant id"),
    ({"params": {"participant": "P1"}, "extra": 1}, "extra"),
    ({"params": {"participant": 3}}, "params.participant"),
])
def test_bad_session_requests_are_refused(client, body, words):
    assert words in error(client.post("/api/sessions", json=body), 422)
    assert client.store.count()["participants"] == 0


def test_malformed_json_is_refused_in_one_line(client):
    reply = client.post("/api/sessions", content=b"{not json", headers={"Content-Type": "application/json"})
    assert "JSON" in error(reply, 422)


def test_conditions_are_balanced(client):
    conditions = [start(client, f"P{i}").json()["condition"] for i in range(10)]
    assert conditions.count("time_limited") == conditions.count("unconstrained") == 5
    orders = {tuple(t["task_id"] for t in trials_of(client, start(client, f"Q{i}").json())) for i in range(8)}
    assert len(orders) == 2  # both orders of the two tasks occur


# placements ---------------------------------------------------------------------------------------------------
def test_a_placement_is_checked_run_and_stored(client, base_settings):
    s = start(client).json()
    pt = s["practice"][0]
    _, x, layer = practice_tower(client, 1)[1]
    reply = place(client, s, "practice", 1, 1, x, layer, trajectory=[[0, 0.0, 2.0], [0.5, x, 0.9]],
                  dwell=[[x, layer, 0.4]])
    assert reply.status_code == 200
    out = reply.json()
    assert out["stable"] is True and out["trial_over"] is False and out["reward"] is None
    assert out["overhang"] == pytest.approx(abs(x) + pt["sequence"][1] / 2)
    assert out["position"]["step"] == 2
    assert out["position"]["tower"] == [[pt["sequence"][0], 0.0, 0], [pt["sequence"][1], x, layer]]
    stored = client.store.placements("P1")
    assert len(stored) == 1 and stored[0].trajectory == [[0, 0.0, 2.0], [0.5, x, 0.9]]


def test_a_falling_tower_is_the_worlds_verdict_and_is_animated(client, base_settings):
    s = start(client).json()
    pt = s["practice"][0]
    width = pt["sequence"][1]
    x = pt["sequence"][0] / 2 + width / 2 - 0.05  # resting on 5 cm of the ground block's edge
    world = Registry().create("world", base_settings.world)
    tower = Geometry.from_tuples([[pt["sequence"][0], 0.0, 0]])
    assert not world.is_stable(rules.place(tower, width, Action(x, 1)))
    out = place(client, s, "practice", 1, 1, x, 1).json()
    assert out["stable"] is False and out["trial_over"] is True and out["reward"] == 0
    settings = client.app.state.settings
    assert out["passed"] is False and out["optimum"] == settings.practice[0].optimum
    assert out["shown_tower"] == practice_tower(client, 1) and out["pass_reward"] == settings.practice[0].pass_reward
    poses = out["frames"]["poses"]
    assert len(poses) > 10 and len(poses[0]) == 2
    assert poses[0][1][:2] == pytest.approx([x, 0.9], abs=1e-3)
    assert abs(poses[-1][1][0] - x) + abs(poses[-1][1][1] - 0.9) > 0.05  # the block has left its place
    assert out["position"] == {**out["position"], "phase": "practice", "trial": 1, "attempt": 2, "step": 1}


@pytest.mark.parametrize("x, layer, words", [
    (0.0, 1, None),        # legal: the control
    (0.0, 2, "supports"),  # nothing in layer 1
    (3.9, 1, "outside the grid"),
    (2.5, 1, "supports"),
    (0.0, 0, "ground"),
])
def test_illegal_actions_are_refused_and_nothing_is_written(client, x, layer, words):
    s = start(client).json()
    reply = place(client, s, "practice", 1, 1, x, layer)
    if words is None:
        assert reply.status_code == 200 and rows(client) == 1
    else:
        assert words in error(reply, 422) and rows(client) == 0


def test_overlap_in_a_layer_is_refused(client):
    s = start(client).json()
    _, x, layer = practice_tower(client, 1)[1]
    place(client, s, "practice", 1, 1, x, layer)
    assert "overlaps" in error(place(client, s, "practice", 1, 2, x, layer), 422)
    assert rows(client) == 1


def test_steps_must_come_in_order(client):
    s = start(client).json()
    assert "out of order" in error(place(client, s, "practice", 1, 2, 0.0, 1), 409)
    assert "out of order" in error(place(client, s, "main", 1, 1, 0.0, 1), 409)  # practice first
    assert "out of order" in error(place(client, s, "practice", 2, 1, 0.0, 1), 409)
    assert "out of order" in error(place(client, s, "practice", 1, 1, 0.0, 1, attempt=2), 409)
    assert rows(client) == 0


def test_a_retry_returns_the_stored_reply_and_stores_nothing_twice(client):
    s = start(client).json()
    _, x, layer = practice_tower(client, 1)[1]
    first = place(client, s, "practice", 1, 1, x, layer)
    again = place(client, s, "practice", 1, 1, x, layer)
    assert without_clock(first.json()) == without_clock(again.json()) and rows(client) == 1
    # the retry's clock is the next step's as it is now: started by the first reply, not restarted
    assert again.json()["clock"]["step"] == 2 and again.json()["clock"]["elapsed"] >= first.json()["clock"]["elapsed"]
    assert "different placement" in error(place(client, s, "practice", 1, 1, x + 0.1, layer), 409)
    assert rows(client) == 1


def test_simultaneous_retries_store_one_placement(client):
    s = start(client).json()
    _, x, layer = practice_tower(client, 1)[1]
    replies = []
    threads = [threading.Thread(target=lambda: replies.append(place(client, s, "practice", 1, 1, x, layer)))
               for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(r.status_code == 200 for r in replies), [r.text for r in replies]
    assert len({str(without_clock(r.json())) for r in replies}) == 1 and rows(client) == 1


@pytest.mark.parametrize("headers, status", [({}, 401), ({"Authorization": "Bearer nope"}, 403),
                                             ({"Authorization": "Basic abc"}, 401)])
def test_placements_need_the_participants_token(client, headers, status):
    start(client)
    body = {"phase": "practice", "trial": 1, "step": 1, "x": 0.0, "layer": 1, "decision_time": 1.0}
    error(client.post("/api/placements", json=body, headers=headers), status)
    assert rows(client) == 0


def test_one_participant_cannot_change_anothers_data(client):
    a, b = start(client, "A").json(), start(client, "B").json()
    _, x, layer = practice_tower(client, 1)[1]
    place(client, a, "practice", 1, 1, x, layer)
    # B's token addresses B's own position only: A's step 2 is not B's next step
    assert "out of order" in error(place(client, b, "practice", 1, 2, 0.0, 2), 409)
    assert client.get("/api/session", headers=auth(b)).json()["position"]["step"] == 1
    assert len(client.store.placements("A")) == 1 and client.store.placements("B") == []


@pytest.mark.parametrize("change, words", [
    ({"x": None}, "needs x and layer"),
    ({"decision_time": -1}, "decision_time"),
    ({"trajectory": [[0.5, 0, 0], [0.2, 0, 0]]}, "never go back"),
    ({"trajectory": [[0.5, 0]]}, "trajectory"),
    ({"phase": "warmup"}, "phase"),
    ({"step": 0}, "step"),
    ({"layer": "one"}, "layer"),
    ({"colour": "red"}, "colour"),
    ({"timed_out": True}, "no time limit"),
])
def test_malformed_placements_are_refused(make_client, change, words):
    client = make_client(conditions=["unconstrained"])
    s = start(client).json()
    body = {"phase": "practice", "trial": 1, "attempt": 1, "step": 1, "x": 0.0, "layer": 1, "decision_time": 1.0,
            **change}
    assert words in error(client.post("/api/placements", json=body, headers=auth(s)), 422)
    assert rows(client) == 0


# practice, main trials, timeouts, the end ----------------------------------------------------------------------
def test_practice_is_retried_until_passed_then_the_main_trials_follow(client):
    s = start(client).json()
    pt = s["practice"][0]
    # attempt 1: the block one step off the ground block's edge collapses
    out = place(client, s, "practice", 1, 1, pt["sequence"][0] / 2 + pt["sequence"][1] / 2 - 0.05, 1).json()
    assert out["passed"] is False and out["position"]["attempt"] == 2
    # attempt 2: a low tower, stacked centred, stands but reaches no further than its ground block: not passed
    for step in range(1, len(pt["sequence"])):
        out = place(client, s, "practice", 1, step, 0.0, step, attempt=2).json()
    assert out["stable"] is True and out["reward"] == pytest.approx(pt["sequence"][0] / 2)
    assert out["passed"] is False and out["position"]["attempt"] == 3
    for step, (_, x, layer) in enumerate(practice_tower(client, 1)[1:], 1):
        out = place(client, s, "practice", 1, step, x, layer, attempt=3).json()
    assert out["passed"] is True and out["position"]["trial"] == 2
    for k in (2, 3):
        for step, (_, x, layer) in enumerate(practice_tower(client, k)[1:], 1):
            out = place(client, s, "practice", k, step, x, layer).json()
    assert out["position"]["phase"] == "main" and out["position"]["trial"] == 1


def test_a_timeout_ends_the_trial_with_reward_zero(make_client):
    clock = FakeClock()
    client = make_client(clock=clock, conditions=["time_limited"])
    s = start(client).json()
    assert s["time_limit"] == 5.0
    pass_practice(client, s)
    begin(client, s, "main", 1, 1)
    clock.now += 5.0
    assert "x and layer null" in error(place(client, s, "main", 1, 1, 0.0, 1, timed_out=True, decision_time=5.0), 422)
    out = place(client, s, "main", 1, 1, None, None, timed_out=True, decision_time=5.0).json()
    assert out["trial_over"] is True and out["reward"] == 0 and out["stable"] is None
    assert out["position"]["trial"] == 2 and out["position"]["step"] == 1


def test_a_reopened_session_resumes_at_the_same_step(client):
    s = start(client).json()
    pass_practice(client, s)
    place(client, s, "main", 1, 1, 0.0, 1)
    place(client, s, "main", 1, 2, 0.0, 2)
    again = start(client, token=s["token"]).json()
    assert again["position"]["phase"] == "main" and again["position"]["trial"] == 1
    assert again["position"]["step"] == 3 and len(again["position"]["tower"]) == 3
    assert client.get("/api/session", headers=auth(s)).json()["position"] == again["position"]


def test_finish_only_after_the_last_trial_and_then_export(client):
    s = start(client).json()
    pass_practice(client, s)
    assert "not finished" in error(client.post("/api/finish", headers=auth(s)), 409)
    total = 0.0
    for t in trials_of(client, s):
        total += stack(client, s, t["trial"], t["sequence"])["reward"]
    assert "every trial is over" in error(place(client, s, "main", 3, 1, 0.0, 1), 409)
    done = client.post("/api/finish", headers=auth(s)).json()
    assert done["total_reward"] == pytest.approx(total) and done["bonus"] == round(total * 0.25, 2)
    assert client.post("/api/finish", headers=auth(s)).json() == done
    assert start(client, token=s["token"]).json()["completed"] is True

    error(client.get("/api/admin/export"), 401)
    error(client.get("/api/admin/export", headers={"X-Admin-Token": "wrong-token"}), 403)
    reply = client.get("/api/admin/export", headers={"X-Admin-Token": ADMIN})
    assert reply.status_code == 200
    path = client.store.url  # the log goes beside the database
    log = read_log_text(reply.text, tmp=os.path.dirname(path.split(":///")[-1]) if "sqlite" in path else None)
    assert len(log) == sum(len(t["sequence"]) - 1 for t in trials_of(client, s))
    assert set(log.participant) == {"P1"} and set(log.source) == {"human"}
    assert log.groupby("trial").reward.last().sum() == pytest.approx(total)


def read_log_text(text, tmp=None):
    import tempfile

    with tempfile.NamedTemporaryFile("w", suffix=".jsonl", dir=tmp, delete=False) as f:
        f.write(text)
    try:
        return read_log(f.name)
    finally:
        os.unlink(f.name)


def test_an_unfinished_trial_is_left_out_of_the_export(client):
    from overhang_framework.experiment.export import export_jsonl

    s = start(client).json()
    pass_practice(client, s)
    stack(client, s, 1, trials_of(client, s)[0]["sequence"])
    place(client, s, "main", 2, 1, 0.0, 1)
    text, unfinished = export_jsonl(client.store)
    assert unfinished == 1 and text.count("\n") == len(trials_of(client, s)[0]["sequence"]) - 1


# the server's clock ------------------------------------------------------------------------------------------
class FakeClock:
    """The server's clock, moved by the test."""

    def __init__(self, now=1_000_000.0):
        self.now = now

    def __call__(self):
        return self.now


def fall_x(client, k=1):
    seq = client.app.state.settings.practice[k - 1].task.sequence
    return seq[0] / 2 + seq[1] / 2 - 0.05  # resting on 5 cm of the ground block's edge: it falls


def test_a_reload_continues_the_servers_clock_and_a_late_placement_is_a_timeout(make_client):
    clock = FakeClock()
    client = make_client(clock=clock, conditions=["time_limited"])
    s = start(client).json()
    pass_practice(client, s)
    # the trial-ending reply does not start the next trial: its first step starts when the page starts it
    assert client.get("/api/session", headers=auth(s)).json()["clock"] is None
    clock.now += 30  # the participant reads the main part's instructions
    reply = begin(client, s, "main", 1, 1).json()
    assert reply["task"]["sequence"] == trials_of(client, s)[0]["sequence"]  # the trial's blocks, with its clock
    started = reply["clock"]
    assert started["elapsed"] == 0 and started["time_left"] == 5.0
    clock.now += 1.0
    out = place(client, s, "main", 1, 1, 0.0, 1, start=False).json()
    assert out["timed_out"] is False and out["server_time"] == 1.0
    assert out["clock"] == {"phase": "main", "trial": 1, "attempt": 1, "step": 2, "elapsed": 0.0, "time_left": 5.0}
    clock.now += 3.0  # three seconds into step 2, the page is reloaded
    again = start(client, token=s["token"]).json()
    assert again["position"]["step"] == 2 and again["clock"]["elapsed"] == 3.0 and again["clock"]["time_left"] == 2.0
    clock.now += 0.5  # the page starts the step again: the clock goes on
    assert begin(client, s, "main", 1, 2).json()["clock"]["time_left"] == 1.5
    clock.now += 2.0 + 0.6  # past the limit and the grace
    late = place(client, s, "main", 1, 2, 0.0, 2, start=False, decision_time=2.0)
    assert late.status_code == 200, late.text  # stored, not refused
    out = late.json()
    assert out["timed_out"] is True and out["late"] is True and out["reward"] == 0 and out["trial_over"] is True
    assert out["position"]["trial"] == 2 and out["position"]["step"] == 1
    row = [r for r in client.store.placements("P1") if r.phase == "main" and r.step == 2][0]
    assert row.timed_out and row.x is None and row.late_action == [0.0, 2]
    assert row.server_time == pytest.approx(6.1) and row.decision_time == 2.0


def test_a_placement_within_the_grace_counts(make_client):
    clock = FakeClock()
    client = make_client(clock=clock, conditions=["time_limited"])
    s = start(client).json()
    begin(client, s, "practice", 1, 1)
    clock.now += 5.0 + client.app.state.settings.time_grace - 0.01
    out = place(client, s, "practice", 1, 1, 0.0, 1, start=False).json()
    assert out["timed_out"] is False and out["stable"] is True


def test_a_step_must_be_started_before_it_is_placed(client):
    s = start(client).json()
    assert "not been started" in error(place(client, s, "practice", 1, 1, 0.0, 1, start=False), 409)
    assert "out of order" in error(begin(client, s, "practice", 1, 2), 409)
    assert rows(client) == 0


@pytest.mark.parametrize("condition", ["time_limited", "unconstrained"])
def test_the_export_gives_the_servers_decision_time_beside_the_pages(make_client, condition):
    from overhang_framework.experiment.export import export_jsonl

    clock = FakeClock()
    client = make_client(clock=clock, conditions=[condition])
    s = start(client).json()
    pass_practice(client, s)
    for t in trials_of(client, s):
        for step in range(1, len(t["sequence"])):
            if step == 1:
                begin(client, s, "main", t["trial"], 1)
            clock.now += 2.5
            if condition == "time_limited" and t["trial"] == 2 and step == 2:
                clock.now += 2.6  # the page's timer ran out: 5.1 s by the server's clock
                place(client, s, "main", t["trial"], step, None, None, start=False, timed_out=True, decision_time=5.0)
                break
            place(client, s, "main", t["trial"], step, 0.0, step, start=False, decision_time=0.7)
    text, _ = export_jsonl(client.store)
    log = read_log_text(text)
    placed = log[~log.timed_out]
    assert set(placed.decision_time) == {2.5} and set(placed.page_decision_time) == {0.7}
    if condition == "time_limited":
        out = log[log.timed_out].iloc[0]
        assert out.decision_time == 5.0 and out.server_time == pytest.approx(5.1)  # capped at the limit


# practice: screening out ---------------------------------------------------------------------------------------
def test_practice_attempts_used_up_screen_the_participant_out(make_client):
    from overhang_framework.experiment.export import export_jsonl

    client = make_client(practice_max_attempts=2, conditions=["unconstrained"])
    s = start(client).json()
    assert s["practice_max_attempts"] == 2
    first = place(client, s, "practice", 1, 1, fall_x(client), 1).json()
    assert first["position"]["phase"] == "practice" and first["position"]["attempt"] == 2
    second = place(client, s, "practice", 1, 1, fall_x(client), 1, attempt=2).json()
    assert second["position"]["phase"] == "screened_out" and second["screen_out_url"] == "/screened-out"
    again = start(client, token=s["token"]).json()
    assert again["position"]["phase"] == "screened_out" and again["screen_out_url"] == "/screened-out"
    assert "used up" in error(place(client, s, "practice", 1, 1, 0.0, 1, attempt=3), 409)
    assert "screened out" in error(client.post("/api/finish", headers=auth(s)), 409)
    summary = client.get("/api/admin/participants", headers={"X-Admin-Token": ADMIN}).json()
    assert summary[0]["phase"] == "screened_out" and summary[0]["screened_out"] is True
    assert client.store.participant("P1").screened_out_at is not None
    # another participant who passes is exported; the screened-out one only when asked
    other = start(client, "P2").json()
    pass_practice(client, other)
    stack(client, other, 1, trials_of(client, other)[0]["sequence"])
    text, _ = export_jsonl(client.store)
    assert set(read_log_text(text).participant) == {"P2"}
    text, _ = export_jsonl(client.store, include_screened_out=True)
    log = read_log_text(text)
    mine = log[log.participant == "P1"]
    assert set(mine.phase) == {"practice"} and sorted(set(mine.attempt)) == [1, 2] and sorted(set(mine.trial)) == [1, 2]


def test_practice_without_a_limit_never_screens_out(make_client):
    client = make_client(practice_max_attempts=None)
    s = start(client).json()
    for attempt in range(1, 8):
        out = place(client, s, "practice", 1, 1, fall_x(client), 1, attempt=attempt).json()
        assert out["position"]["phase"] == "practice" and out["position"]["attempt"] == attempt + 1


def test_the_session_does_not_reveal_the_practice_towers_before_they_are_played(client):
    s = start(client).json()
    assert all(set(pt) == {"trial", "task_id", "sequence"} for pt in s["practice"])


# another browser: a new link ---------------------------------------------------------------------------------
def test_a_reissued_token_resumes_and_the_old_one_is_refused(client):
    s = start(client).json()
    place(client, s, "practice", 1, 1, *practice_tower(client, 1)[1][1:])
    refused = start(client)  # a fresh browser: no token
    assert refused.status_code == 403 and refused.json()["reason"] == "session_elsewhere"
    assert refused.json()["contact"] == client.app.state.settings.contact
    error(client.post("/api/admin/participants/P1/reissue"), 401)
    assert "no participant 'P9'" in error(client.post("/api/admin/participants/P9/reissue",
                                                      headers={"X-Admin-Token": ADMIN}), 404)
    new = client.post("/api/admin/participants/P1/reissue", headers={"X-Admin-Token": ADMIN}).json()
    assert new["token"] != s["token"] and f"token={new['token']}" in new["resume_url"]
    assert "participant=P1" in new["resume_url"]
    error(client.get("/api/session", headers=auth(s)), 403)  # the old token no longer works
    error(start(client, token=s["token"]), 403)
    resumed = start(client, token=new["token"])
    assert resumed.status_code == 200 and resumed.json()["position"]["step"] == 2
    rows_ = client.get("/api/admin/participants", headers={"X-Admin-Token": ADMIN}).json()
    assert rows_[0]["tokens_issued"] == 2


def test_a_reissued_link_for_a_recruitment_platform_keeps_its_parameters(client):
    client.post("/api/sessions", json={"params": {"PROLIFIC_PID": "5f1a", "STUDY_ID": "st", "SESSION_ID": "se"}})
    link = client.post("/api/admin/participants/5f1a/reissue", headers={"X-Admin-Token": ADMIN}).json()["resume_url"]
    assert "PROLIFIC_PID=5f1a" in link and "STUDY_ID=st" in link and "SESSION_ID=se" in link


# every refusal is {"error": ...} --------------------------------------------------------------------------------
def test_unknown_paths_and_methods_are_refused_in_one_line(client):
    assert "no such path: /api/nothing" in error(client.get("/api/nothing"), 404)
    assert "not allowed" in error(client.get("/api/placements"), 405)


def test_the_pages_outside_the_task_have_the_experiments_look(client):
    for path in ("/complete", "/screened-out"):
        page = client.get(path)
        assert page.status_code == 200 and "<style>" in page.text and "<h1>" in page.text


def test_a_placement_is_timed_as_it_arrives_not_after_it_waited_for_the_database(make_client):
    clock = FakeClock()
    client = make_client(clock=clock, conditions=["time_limited"])
    s = start(client).json()
    begin(client, s, "practice", 1, 1)
    clock.now += 4.0
    slow = client.store.steps

    def waiting_for_the_database(pid):
        clock.now += 10.0  # the request waits for a lock
        return slow(pid)

    client.store.steps = waiting_for_the_database
    out = place(client, s, "practice", 1, 1, 0.0, 1, start=False).json()
    assert out["timed_out"] is False and out["server_time"] == 4.0


def test_a_timeout_claimed_before_the_limit_is_refused(make_client):
    clock = FakeClock()
    client = make_client(clock=clock, conditions=["time_limited"])
    s = start(client).json()
    begin(client, s, "practice", 1, 1)
    clock.now += 1.0
    assert "too early" in error(place(client, s, "practice", 1, 1, None, None, start=False, timed_out=True), 422)
    clock.now += 3.9  # 4.9 s: the page's countdown ends with the reply's latency taken off
    out = place(client, s, "practice", 1, 1, None, None, start=False, timed_out=True).json()
    assert out["timed_out"] is True and out["trial_over"] is True


def test_a_participant_keeps_the_time_limit_they_started_with(make_client):
    from overhang_framework.experiment.export import export_jsonl

    clock = FakeClock()
    first = make_client(clock=clock, conditions=["time_limited"])
    s = start(first).json()
    pass_practice(first, s)
    restarted = make_client(clock=clock, conditions=["time_limited"], time_limit=3.0,  # same database
                            allow_settings_change=True)
    assert restarted.get("/api/session", headers=auth(s)).json()["time_limit"] == 5.0
    assert begin(restarted, s, "main", 1, 1).json()["clock"]["time_left"] == 5.0
    clock.now += 5.3  # within the grace of 5 s, over 3 s
    out = place(restarted, s, "main", 1, 1, 0.0, 1, start=False).json()
    assert out["timed_out"] is False
    rows_ = [r for r in restarted.store.placements("P1") if r.phase == "main"]
    assert rows_[0].server_time == pytest.approx(5.3)
    stack_rest = [place(restarted, s, "main", 1, step, 0.0, step) for step in range(2, len(trials_of(restarted, s)[0]["sequence"]))]
    assert all(r.status_code == 200 for r in stack_rest)
    text, _ = export_jsonl(restarted.store)
    log = read_log_text(text)
    assert log.decision_time.max() <= 5.0  # the grace is the network's, not the participant's
    assert log.server_time.max() == pytest.approx(5.3)


def test_screening_out_is_recorded_once_and_a_later_setting_moves_nobody(make_client):
    client = make_client(practice_max_attempts=1)
    s = start(client).json()
    out = place(client, s, "practice", 1, 1, fall_x(client), 1).json()
    assert out["position"]["phase"] == "screened_out"
    other = start(client, "P2").json()
    pass_practice(client, other)
    relaxed = make_client(practice_max_attempts=5, allow_settings_change=True)  # the same database, a laxer setting
    assert relaxed.get("/api/session", headers=auth(s)).json()["position"]["phase"] == "screened_out"
    strict = make_client(practice_max_attempts=1, allow_settings_change=True)
    assert strict.get("/api/session", headers=auth(other)).json()["position"]["phase"] == "main"
    assert "screened out" in error(client.post("/api/finish", headers=auth(s)), 409)


def test_api_paths_are_refused_in_one_line_behind_the_front_end(make_client, tmp_path):
    web = tmp_path / "web"
    web.mkdir()
    (web / "index.html").write_text("<!doctype html><title>page</title>")
    client = make_client(web_dir=web)
    assert client.get("/").status_code == 200
    assert "no such path: /api/nothing" in error(client.get("/api/nothing"), 404)
    assert "no such path" in error(client.post("/api/nothing"), 404)
    assert "use POST" in error(client.get("/api/placements"), 405)
    assert "no such path" in error(client.get("/api/admin/nothing"), 404)


def test_a_database_of_an_earlier_schema_is_refused_in_one_line(tmp_path):
    import sqlite3

    from overhang_framework.errors import ConfigError

    path = tmp_path / "old.sqlite"
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE participants (id VARCHAR(200) PRIMARY KEY, condition VARCHAR(100))")
    with pytest.raises(ConfigError, match="table participants lacks the column"):
        Store(f"sqlite:///{path}")


def test_two_server_processes_taking_newcomers_at_once_keep_the_conditions_balanced(database):
    from overhang_framework.experiment.store import Participant, token_hash

    conditions = ["time_limited", "unconstrained"]
    first, second = Store(database), Store(database)  # two server processes' connections to one database
    made = {}

    def newcomer(pid):
        def make(counts):
            made[pid] = dict(counts)
            condition = min(conditions, key=lambda c: counts[c])
            return Participant(id=pid, token_hash=token_hash(pid), condition=condition, order=[])
        return make

    def first_newcomer(counts):
        # the second process takes its newcomer while the first has counted but not yet stored its own
        late.start()
        late.join(timeout=1.0)
        return newcomer("A")(counts)

    stored = {}
    late = threading.Thread(target=lambda: stored.setdefault("B", second.add_newcomer(conditions, newcomer("B"))))
    try:
        stored["A"] = first.add_newcomer(conditions, first_newcomer)
        late.join()
        assert {stored["A"].condition, stored["B"].condition} == set(conditions)
        assert made["B"] == {stored["A"].condition: 1, stored["B"].condition: 0}  # B counted A
        assert sorted(p.id for p in first.participants()) == ["A", "B"]
    finally:
        first.close()
        second.close()


@pytest.mark.parametrize("change", ["drop the level", "change its limit", "change the tasks"])
def test_a_participant_in_progress_keeps_what_they_started_with_through_every_allowed_change(make_client, base_settings,
                                                                                            change):
    """A lab changes a running study (allow_settings_change=true) while someone plays a level: their level, its
    limit and their tasks stay theirs; every placement is stored, exported, and carries a settings hash that
    resolves to the settings they played under."""
    from overhang_framework.experiment.export import export_jsonl

    clock = FakeClock()
    level = {"conditions": ["limit_2_5s"], "time_limits": {"limit_2_5s": 2.5}}
    first = make_client(clock=clock, **level)
    s = start(first).json()
    assert s["condition"] == "limit_2_5s" and s["time_limit"] == 2.5
    pass_practice(first, s)
    trials = trials_of(first, s)
    assert place(first, s, "main", 1, 1, 0.0, 1).status_code == 200  # one block placed, then the change
    changed = {"drop the level": {"conditions": ["unconstrained"], "time_limits": {}},
               "change its limit": {**level, "time_limits": {"limit_2_5s": 4.0}},
               "change the tasks": {**level, "tasks": load_settings(
                   [f"run_dir={base_settings.run_dir}", f"admin_token={ADMIN}", "tasks.only=[paper01,paper02]",
                    "physics_processes=0"]).tasks}}[change]
    later = make_client(clock=clock, allow_settings_change=True, **changed)
    session = later.get("/api/session", headers=auth(s))
    assert session.status_code == 200, session.text
    resumed = session.json()
    assert resumed["condition"] == "limit_2_5s" and resumed["time_limit"] == 2.5
    assert resumed["position"]["phase"] == "main" and resumed["position"]["step"] == 2
    assert begin(later, s, "main", 1, 2).json()["clock"]["time_left"] == 2.5
    for trial in trials:
        for step in range(2 if trial["trial"] == 1 else 1, len(trial["sequence"])):
            reply = place(later, s, "main", trial["trial"], step, 0.0, step)
            assert reply.status_code == 200, reply.text
    assert reply.json()["position"]["phase"] == "done"
    log = read_log_text(export_jsonl(later.store)[0])
    main = log[log.participant == "P1"]
    assert len(main) == sum(len(t["sequence"]) - 1 for t in trials)
    assert set(main.condition) == {"limit_2_5s"} and set(main.task_id) == {t["task_id"] for t in trials}
    kept = later.store.played_settings()
    after = main[(main.trial > 1) | (main.step > 1)]
    assert after.settings_hash.nunique() == 1 and after.settings_hash.iloc[0] in kept
    played = kept[after.settings_hash.iloc[0]]
    assert "limit_2_5s" in played["conditions"] and played["time_limits"]["limit_2_5s"] == 2.5
    assert sorted(i for i, _ in played["tasks"]) == sorted(t["task_id"] for t in trials)
    assert later.store.study().settings["conditions"] == changed["conditions"]  # the study's own did change


def test_guessing_the_admin_token_is_refused_after_ten_wrong_tokens_a_minute(make_client):
    """Wrong admin tokens from one address, at /api/admin/* or in a simulated session's request, count together; the
    eleventh try in a minute is refused (429), the right token too, until the first wrong one is a minute old."""
    from overhang_framework.experiment.api import ADMIN_GUESSES, ADMIN_WINDOW

    clock = FakeClock()
    client = make_client(clock=clock)
    listed = lambda token: client.get("/api/admin/participants", headers={"X-Admin-Token": token})  # noqa: E731
    assert listed(ADMIN).status_code == 200
    for k in range(ADMIN_GUESSES):
        if k % 2:
            reply = client.post("/api/sessions", json={"params": {"participant": f"S{k}"}, "simulated": True},
                                headers={"X-Admin-Token": f"guess-{k}"})
        else:
            reply = listed(f"guess-{k}")
        assert reply.status_code == 403
        clock.now += 1.0
    message = error(listed(ADMIN), 429)
    assert f"{ADMIN_GUESSES} wrong admin tokens from this address in 60 s; try again in" in message
    assert start(client, "P1").status_code == 201  # participants are not held up
    clock.now += ADMIN_WINDOW - ADMIN_GUESSES + 0.5  # the first guess is a minute old
    assert listed(ADMIN).status_code == 200


def test_a_pilots_planning_is_taken_off_the_servers_clock_and_nobody_elses(make_client):
    """A simulated participant's placement says how long its planner computed (simulator_time): the server's clock
    leaves it out, so the time recorded is the participant's; a person's placement may not say it."""
    clock = FakeClock()
    client = make_client(clock=clock)
    person = start(client, "H1").json()
    assert "simulator_time is a pilot's" in error(
        place(client, person, "practice", 1, 1, *practice_tower(client, 1)[1][1:], simulator_time=2.0), 422)
    reply = client.post("/api/sessions", json={"params": {"participant": "S1"}, "simulated": True},
                        headers={"X-Admin-Token": ADMIN})
    pilot = reply.json()
    client.post("/api/consent", json={"version": pilot["consent"]["version"]}, headers=auth(pilot))
    begin(client, pilot, "practice", 1, 1)
    clock.now += 3.5  # 2.0 s of planning, then 1.5 s of the simulated participant's decision
    out = place(client, pilot, "practice", 1, 1, *practice_tower(client, 1)[1][1:], start=False, simulator_time=2.0)
    assert out.status_code == 200, out.text
    assert out.json()["server_time"] == pytest.approx(1.5)
    assert client.store.placements("S1")[0].server_time == pytest.approx(1.5)
