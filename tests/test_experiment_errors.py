"""What a participant meets when something goes wrong: JSON in their words with the lab's contact, never a bare
500; bodies the server will not read; links the study cannot take."""

from __future__ import annotations

import pytest

from overhang_framework.experiment.settings import load_settings

ADMIN = "long-enough-token"
CONTACT = "overhang-lab@uni.example"


@pytest.fixture
def client(tmp_path):
    from fastapi.testclient import TestClient

    from overhang_framework.experiment.api import create_app

    settings = load_settings([f"run_dir={tmp_path}", "tasks.only=[paper03,paper00]", "physics_processes=0",
                              f"admin_token={ADMIN}", f"contact={CONTACT}"])
    with TestClient(create_app(settings), raise_server_exceptions=False) as c:
        c.settings = settings
        yield c


def said_to_a_participant(reply, status, reason=None):
    assert reply.status_code == status, reply.text
    assert reply.headers["content-type"].startswith("application/json"), reply.headers["content-type"]
    data = reply.json()
    assert data["error"] and data["contact"] == CONTACT
    assert data["message"].endswith(f"please contact {CONTACT}.") and "Traceback" not in reply.text
    if reason is not None:
        assert data["reason"] == reason
    return data


@pytest.mark.parametrize("params,words", [
    ({"participant": "P1", "STUDY_ID": "x" * 5000}, "This link is not one the study can take."),
    ({"PROLIFIC_PID": "P1", "SESSION_ID": "y" * 201}, "This link is not one the study can take."),
    ({}, "This link does not say who you are."),
    ({"participant": "not an id!"}, "The participant id in this link is not one the study can take."),
], ids=["long-study-id", "long-session-id", "no-id", "bad-id"])
def test_a_link_the_study_cannot_take_is_told_in_the_participants_words(client, params, words):
    data = said_to_a_participant(client.post("/api/sessions", json={"params": params}), 422, "bad_link")
    assert data["message"].startswith(words) and "Please open the study from the link you were given" in data["message"]
    assert "PROLIFIC_PID" not in data["message"] and "letters, digits" not in data["message"]


def test_a_database_outage_is_a_503_in_words_not_a_500(client, monkeypatch):
    from sqlalchemy.exc import OperationalError

    def down(*args, **kwargs):
        raise OperationalError("SELECT 1", {}, ConnectionRefusedError("connection refused"))

    monkeypatch.setattr(client.app.state.store, "participant", down)
    data = said_to_a_participant(client.post("/api/sessions", json={"params": {"participant": "P1"}}), 503,
                                 "unavailable")
    assert "cannot store your answers just now" in data["message"]


def test_an_unexpected_failure_is_json_with_the_contact(client, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("a bug")

    monkeypatch.setattr(client.app.state.store, "add_newcomer", broken)
    data = said_to_a_participant(client.post("/api/sessions", json={"params": {"participant": "P1"}}), 500,
                                 "server_error")
    assert "RuntimeError" in data["error"] and "a bug" not in data["message"]


def test_a_body_over_the_cap_is_refused_before_it_is_read(client):
    from overhang_framework.experiment.api import MAX_BODY

    headers = {"content-type": "application/json"}
    big = b'{"params": {"participant": "' + b"x" * MAX_BODY + b'"}}'
    said_to_a_participant(client.post("/api/sessions", content=big, headers=headers), 413, "too_large")

    def chunks():  # no Content-Length: counted as it arrives
        yield b'{"params": {"participant": "'
        for _ in range(MAX_BODY // 65536 + 2):
            yield b"x" * 65536
        yield b'"}}'

    said_to_a_participant(client.post("/api/sessions", content=chunks(), headers=headers), 413, "too_large")
    ok = client.post("/api/sessions", json={"params": {"participant": "P1"}})
    assert ok.status_code == 201


def test_every_refusal_a_page_can_meet_says_what_to_do(client):
    s = client.post("/api/sessions", json={"params": {"participant": "P1"}}).json()
    h = {"Authorization": f"Bearer {s['token']}"}
    said_to_a_participant(client.post("/api/steps/start", json={"phase": "practice", "trial": 1, "step": 1},
                                      headers=h), 403)  # no consent yet
    said_to_a_participant(client.post("/api/consent", json={"version": "sha256:other"}, headers=h), 409)
    said_to_a_participant(client.get("/api/session", headers={"Authorization": "Bearer nonsense"}), 403)
    said_to_a_participant(client.get("/api/session"), 401)
    said_to_a_participant(client.post("/api/placements", json={"phase": "practice"}, headers=h), 422)


def test_someone_with_only_the_id_of_a_participant_who_finished_is_not_told_they_took_part(client):
    """The id alone gets the answer a participant half way gets (another browser holds the session): nothing says
    the person finished; their own session token opens their end page."""
    finished = client.post("/api/sessions", json={"params": {"participant": "P9"}}).json()
    client.app.state.store.complete("P9", 1.0, 0.5)
    client.post("/api/sessions", json={"params": {"participant": "P8"}})
    guessed, half_way = (client.post("/api/sessions", json={"params": {"participant": p}}) for p in ("P9", "P8"))
    assert guessed.status_code == half_way.status_code == 403
    assert guessed.json() == {**half_way.json(), "error": half_way.json()["error"].replace("P8", "P9")}
    assert "finish" not in guessed.text and finished["token"] not in guessed.text
    own = client.post("/api/sessions", json={"params": {"participant": "P9"}},
                      headers={"Authorization": f"Bearer {finished['token']}"})
    assert own.status_code == 200 and own.json()["completed"]


def test_an_exhausted_database_pool_is_a_503_too(client, monkeypatch):
    from sqlalchemy.exc import TimeoutError as PoolTimeout

    def busy(*args, **kwargs):
        raise PoolTimeout("QueuePool limit of size 5 overflow 10 reached")

    monkeypatch.setattr(client.app.state.store, "participant", busy)
    said_to_a_participant(client.post("/api/sessions", json={"params": {"participant": "P1"}}), 503, "unavailable")
