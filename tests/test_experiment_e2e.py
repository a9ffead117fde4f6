"""The experiment end to end: the real page in headless Chromium (Python Playwright, the system's browser),
against the real server on loopback.

Two scripted participants take the whole procedure (consent, instructions, the tutorial, practice until
passed, the main trials, the debriefing and the completion redirect), one in each condition. Both let
two seconds pass and reload the page mid-trial; the time-limited one sees the server's clock go on, and
lets the timer end a trial. The export of both loads in the analysis toolkit. A third fails the practice
until screened out; a fourth opens the study in a second browser, is told whom to contact, and resumes
with a reissued link.

With ``E2E_SHOTS=DIR`` set, the screens the participants meet are saved there as PNGs; with
``E2E_CONSOLE=1``, the page's console and errors are printed.

The page is built from ``web/`` when needed (npm). Without Chromium or npm the test is skipped, except
under CI, where it fails.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import threading
import time
from pathlib import Path

import pytest

from overhang_framework.experiment.settings import load_settings

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--disable-quic"]
ADMIN = "e2e-admin-token-1"
TASKS = ["paper03", "paper08"]  # two main trials per participant
ROBUST = 0.04  # a scripted placement must stand with the block this far to either side (mouse pixels)


#: How to get what the browser tests need, on Debian.
INSTALL = {"chromium": "apt-get install chromium", "npm": "apt-get install npm"}


def _needs(what: str, ok: bool) -> None:
    if not ok:
        if os.environ.get("CI"):
            pytest.fail(f"{what} is missing ({INSTALL[what]}); under CI the browser tests run, never skip")
        pytest.skip(f"{what} is missing: the browser tests need it ({INSTALL[what]})")


@pytest.fixture(scope="module")
def dist():
    _needs("npm", shutil.which("npm") is not None)
    from overhang_framework.experiment.web import ensure_built

    return ensure_built()


@pytest.fixture(scope="module")
def server(dist, tmp_path_factory):
    import uvicorn

    from overhang_framework.experiment.api import create_app

    run = tmp_path_factory.mktemp("e2e")
    settings = load_settings([f"run_dir={run}", f"admin_token={ADMIN}", f"tasks.only=[{','.join(TASKS)}]",
                              "practice.max_attempts=3", "contact=lab@example.org"])
    settings.web_dir = dist
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    settings.public_url = f"http://127.0.0.1:{port}"
    app = create_app(settings)
    srv = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    deadline = time.time() + 30
    while not srv.started and time.time() < deadline:
        time.sleep(0.05)
    assert srv.started, "the server did not start"
    yield {"url": f"http://127.0.0.1:{port}", "app": app, "settings": settings, "store": app.state.store,
           "world": app.state.outcomes.world()}
    srv.should_exit = True
    thread.join(timeout=10)


@pytest.fixture(scope="module")
def browser():
    _needs("chromium", Path(CHROMIUM).exists())
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        yield b
        b.close()


def shot(page, name):
    if os.environ.get("E2E_SHOTS"):
        Path(os.environ["E2E_SHOTS"]).mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(Path(os.environ["E2E_SHOTS"]) / f"{name}.png"))


class ScriptedParticipant:
    """Clicks through the page as a participant would, placing blocks with the mouse.

    Tutorial blocks go centred on the block below. Practice and main blocks go where the tower reaches
    furthest while it stands with the block ``ROBUST`` to either side (a mouse lands within a pixel of
    where it aims). In ``time_limited``, ``hold`` names main (trial, step) pairs where the participant
    never clicks; ``reload_at`` is one where the page is reloaded before the placement.
    """

    def __init__(self, page, server, pid, hold=(), reload_at=None, collapse_first_practice=True,
                 collapse_practice=False, reload_wait=2.0):
        self.page, self.server, self.pid = page, server, pid
        self.hold, self.reload_at, self.reload_wait = set(hold), reload_at, reload_wait
        self.collapse_first_practice = collapse_first_practice
        self.collapse_practice = collapse_practice
        self.timer_after_reload = None
        self.after_reload = False
        self.in_tutorial = True
        self.events: list[str] = []
        self.waits: dict = {}

    # what the server knows -------------------------------------------------------------------------------------
    def position(self):
        from overhang_framework.experiment.api import position

        store = self.server["store"]
        participant = store.participant(self.pid)
        return position(self.server["settings"], participant, store.placements(self.pid)), participant

    def sequence(self, pos, participant):
        settings = self.server["settings"]
        if pos.phase == "practice":
            return settings.practice[pos.trial - 1].task.sequence
        by_id = {t.id: t for t in settings.tasks}
        return by_id[participant.order[pos.trial - 1]].sequence

    # choosing -----------------------------------------------------------------------------------------------
    def robust_action(self, tower, width):
        from overhang_framework import rules
        from overhang_framework.geometry import Action, Geometry, overhang

        world = self.server["world"]
        geometry = Geometry.from_tuples(tower)
        xs, layers = rules.legal_xs(geometry, width, 0.1)
        candidates = sorted(zip(xs.tolist(), layers.tolist()),
                            key=lambda a: (-overhang(rules.place(geometry, width, Action(*a))), abs(a[0])))
        for x, layer in candidates:
            shifted = [Action(x + d, layer) for d in (-ROBUST, 0.0, ROBUST)]
            if all(rules.is_legal(geometry, width, a) and world.is_stable(rules.place(geometry, width, a))
                   for a in shifted):
                return x, layer
        return 0.0, len(tower)

    def choose(self, tower, step):
        if self.in_tutorial:
            return tower[-1][1], max(b[2] for b in tower) + 1
        pos, participant = self.position()
        width = self.sequence(pos, participant)[step]
        if pos.phase == "practice" and pos.trial == 1 and (self.collapse_practice or (
                pos.attempt == 1 and self.collapse_first_practice)):
            return tower[0][0] / 2 + width / 2 - 0.1, 1  # mostly beyond the ground block's edge: it falls
        return self.robust_action(tower, width)

    # acting ---------------------------------------------------------------------------------------------------
    def click_at(self, x, layer):
        canvas = self.page.get_by_test_id("overhang-canvas")
        box = canvas.bounding_box()
        d = canvas.evaluate("c => ({ppu: +c.dataset.pxPerUnit, ox: +c.dataset.originX, oy: +c.dataset.originY, "
                            "bh: +c.dataset.blockHeight})")
        px = box["x"] + d["ox"] + x * d["ppu"]
        py = box["y"] + d["oy"] - (layer + 0.5) * d["bh"] * d["ppu"]
        self.page.mouse.move(px - 40, py + 25)
        self.page.mouse.move(px, py, steps=6)
        self.page.wait_for_timeout(80)
        self.page.mouse.click(px, py)

    def visible(self, selector) -> bool:
        loc = self.page.locator(selector)
        return loc.count() > 0 and loc.first.is_visible()

    def clickable(self, testid) -> bool:
        """A button the participant can press now: visible and enabled (the page disables a button while its
        request is on its way, and may replace it once the answer is in)."""
        from playwright.sync_api import Error

        try:
            return self.visible(f"[data-testid={testid}]") and self.page.get_by_test_id(testid).first.is_enabled(
                timeout=1_000)
        except Error:
            return False

    def run(self, timeout=float(os.environ.get('E2E_TIMEOUT', 240))):
        page = self.page
        deadline = time.time() + timeout
        while time.time() < deadline:
            if page.url.endswith(("/complete", "/screened-out")):
                return
            if self.visible("[data-testid=error]"):
                raise AssertionError(f"the page shows an error: {page.get_by_test_id('error').inner_text()}")
            for testid in ("agree", "start-practice", "start-main", "resume", "continue", "finish", "leave"):
                if self.clickable(testid):
                    if testid in ("start-practice", "resume"):
                        self.in_tutorial = False
                    if testid == "continue" and self.visible("[data-testid=practice-feedback]"):
                        feedback = page.get_by_test_id("practice-feedback")
                        self.events.append(f"feedback passed={feedback.get_attribute('data-passed')} "
                                           f"timed_out={feedback.get_attribute('data-timed-out')}")
                        shot(page, f"{self.pid}-practice-feedback-{len(self.events)}")
                    if testid == "leave":
                        shot(page, f"{self.pid}-screened-out")
                    if testid == "finish":
                        shot(page, f"{self.pid}-debrief")
                    self.events.append(testid)
                    from playwright.sync_api import TimeoutError as ClickTimeout

                    try:
                        page.get_by_test_id(testid).first.click(timeout=10_000)
                    except ClickTimeout:  # replaced by the page meanwhile: look again
                        self.events.append(f"{testid} gone")
                    break
            else:
                if self.visible("#jspsych-instructions-next"):
                    page.locator("#jspsych-instructions-next").click()
                elif self.visible(".overhang-tower[data-state=deciding]"):
                    self.decide()
                else:
                    page.wait_for_timeout(50)
                continue
            page.wait_for_timeout(50)
        pos, _ = self.position()
        if os.environ.get("E2E_SHOT"):
            page.screenshot(path=os.environ["E2E_SHOT"])
        raise AssertionError(f"{self.pid} did not finish in {timeout} s; last events {self.events[-8:]}; "
                             f"the server has them at {pos}")

    def decide(self):
        root = self.page.locator(".overhang-tower[data-state=deciding]")
        tower = json.loads(root.get_attribute("data-tower"))
        step = int(root.get_attribute("data-step"))
        if not self.in_tutorial:
            pos, participant = self.position()
            if pos.phase == "main" and (pos.trial, step) == self.reload_at:
                self.reload_at = None
                self.events.append(f"reload main {pos.trial} {step}")
                self.page.wait_for_timeout(int(self.reload_wait * 1000))  # thinking, then F5
                self.page.reload()
                self.after_reload = True
                return
            if self.after_reload:
                self.after_reload = False
                timer = self.page.get_by_test_id("timer")
                if timer.is_visible():
                    self.timer_after_reload = float(timer.get_attribute("data-seconds"))
                    shot(self.page, f"{self.pid}-after-reload")
            if (pos.phase, pos.trial, step) in self.hold and participant.condition == "time_limited":
                self.hold.discard((pos.phase, pos.trial, step))
                self.events.append(f"hold {pos.phase} {pos.trial} {step}")
                started = time.time()
                self.page.locator(".overhang-tower[data-state=done]").wait_for(timeout=15_000)
                self.waits[(pos.phase, pos.trial, step)] = time.time() - started
                return
        x, layer = self.choose(tower, step)
        self.click_at(x, layer)
        self.page.wait_for_function("() => document.querySelector('.overhang-tower')?.dataset.state !== 'deciding'"
                                    " || document.querySelector('.overhang-tower')?.dataset.step !== '%d'" % step,
                                    timeout=15_000)


def take_part(browser, server, pid, condition_wanted=None, **kwargs):
    context = browser.new_context(viewport={"width": 1400, "height": 1000})
    page = context.new_page()
    if os.environ.get("E2E_CONSOLE"):  # the page's console and errors, to see why a participant got stuck
        page.on("console", lambda m: print(f"[{pid} console.{m.type}] {m.text}"))
        page.on("pageerror", lambda e: print(f"[{pid} page error] {e}"))
    page.goto(f"{server['url']}/?participant={pid}&animation_speed=40")
    page.get_by_test_id("agree").wait_for(timeout=30_000)
    condition = server["store"].participant(pid).condition
    if condition_wanted is not None:
        assert condition == condition_wanted
    participant = ScriptedParticipant(page, server, pid, **kwargs)
    participant.run()
    context.close()
    return participant, condition


def test_two_participants_take_the_whole_experiment(browser, server, tmp_path):
    from fastapi.testclient import TestClient

    from overhang_framework.analyze import main as analyze
    from overhang_framework.behaviour.log import read_log

    store, settings = server["store"], server["settings"]
    # conditions are balanced: the first participant's is random, the second gets the other
    hold = [("main", 1, 2), ("practice", 2, 1)]
    first, c1 = take_part(browser, server, "E2E-1", hold=hold, reload_at=(2, 3))
    second, c2 = take_part(browser, server, "E2E-2", hold=hold, reload_at=(2, 3))
    assert {c1, c2} == {"time_limited", "unconstrained"}
    timed = first if c1 == "time_limited" else second
    timed_pid = timed.pid

    for who in (first, second):
        rows = store.placements(who.pid)
        practice = [r for r in rows if r.phase == "practice"]
        main = [r for r in rows if r.phase == "main"]
        # practice: the first attempt collapsed, the next passed; all three practice trials passed
        assert [r.passed for r in practice if r.trial_over and r.trial == 1] == [False, True]
        # the practice feedback says when the time ran out
        timed_feedback = "feedback passed=false timed_out=true" in who.events
        assert timed_feedback == (who.pid == timed_pid)
        assert sorted(r.trial for r in practice if r.trial_over and r.passed) == [1, 2, 3]
        # the main trials are over, in the participant's order
        assert {r.trial for r in main if r.trial_over} == {1, 2}
        # the reload resumed at the same step of the same trial
        # (the step's clock was running: the page went straight back to it, without a welcome screen)
        assert "reload main 2 3" in who.events and "resume" not in who.events
        assert [r.step for r in main if r.trial == 2][:3] == [1, 2, 3]
        # what the page records: mouse samples in task units, forward in time, and dwell times
        placed = [r for r in main if not r.timed_out]
        assert all(len(r.trajectory) >= 2 for r in placed)
        for r in placed:
            t = [s[0] for s in r.trajectory]
            assert t == sorted(t) and all(-5 < s[1] < 5 and -1 < s[2] < 9 for s in r.trajectory)
            assert abs(r.trajectory[-1][1] - r.x) < 0.1
        assert all(r.dwell for r in placed)
        assert store.participant(who.pid).completed_at is not None
        assert "finish" in who.events

    # the timer: in time_limited, the held step timed out at 5 s and ended the trial with reward 0
    timed_rows = {(r.trial, r.step): r for r in store.placements(timed.pid) if r.phase == "main"}
    assert [r.passed for r in store.placements(timed.pid) if r.phase == "practice" and r.trial == 2
            and r.trial_over] == [False, True]
    held = timed_rows[(1, 2)]
    assert held.timed_out and held.reward == 0 and held.trial_over and (1, 3) not in timed_rows
    assert 4.9 <= held.server_time <= 5.0 + settings.time_grace
    assert 4.5 <= timed.waits[("main", 1, 2)] <= 8.0
    # the reload: the server's clock went on through the two seconds before it and the reload itself
    assert timed.timer_after_reload is not None and timed.timer_after_reload <= 5.0 - 2.0 + 0.2
    resumed = timed_rows[(2, 3)]
    assert resumed.server_time >= 2.0 and resumed.server_time - resumed.decision_time >= 1.8
    untimed = first if timed is second else second
    assert not any(r.timed_out for r in store.placements(untimed.pid)) and untimed.waits == {}

    # the export loads in the analysis toolkit
    reply = TestClient(server["app"]).get("/api/admin/export", headers={"X-Admin-Token": ADMIN})
    assert reply.status_code == 200
    log_path = tmp_path / "log.jsonl"
    log_path.write_text(reply.text)
    log = read_log(log_path)
    assert set(log.participant) == {"E2E-1", "E2E-2"} and set(log.condition) == {"time_limited", "unconstrained"}
    assert set(log.task_id) == set(TASKS)
    assert analyze([str(log_path), "--out", str(tmp_path / "analysis"), "--only", "table1", "--quiet"]) == 0
    assert (tmp_path / "analysis" / "report.md").exists()



def test_a_participant_who_fails_the_practice_is_screened_out(browser, server):
    participant, _ = take_part(browser, server, "E2E-3", collapse_practice=True)
    store = server["store"]
    assert store.participant("E2E-3").screened_out_at is not None
    attempts = [r for r in store.placements("E2E-3") if r.phase == "practice" and r.trial_over]
    assert len(attempts) == 3 and not any(r.passed for r in attempts)
    assert participant.events.count("leave") == 1
    assert not any(r.phase == "main" for r in store.placements("E2E-3"))
    # the notice comes straight after the last attempt's feedback, without the main part's introduction
    assert "start-main" not in participant.events
    assert participant.events[participant.events.index("leave") - 1] == "continue"


def test_another_browser_is_told_whom_to_contact_and_a_reissued_link_resumes(browser, server):
    from overhang_framework.experiment.api import reissue

    url = f"{server['url']}/?participant=E2E-4&animation_speed=40"
    first = browser.new_context(viewport={"width": 1400, "height": 1000})
    page = first.new_page()
    page.goto(url)
    page.get_by_test_id("agree").wait_for(timeout=30_000)
    second = browser.new_context(viewport={"width": 1400, "height": 1000})
    other = second.new_page()
    other.goto(url)
    notice = other.get_by_test_id("elsewhere")
    notice.wait_for(timeout=30_000)
    assert "lab@example.org" in notice.inner_text()
    assert other.locator("button").count() == 0  # nothing to press that cannot work
    shot(other, "E2E-4-elsewhere")

    _, link = reissue(server["settings"], server["store"], "E2E-4")
    assert link.startswith(server["url"]) and "token=" in link
    other.goto(link + "&animation_speed=40")
    other.get_by_test_id("agree").wait_for(timeout=30_000)
    assert "token=" not in other.url  # taken from the address bar and kept in the browser
    stored = other.evaluate("() => localStorage.getItem('overhang-tower:token:E2E-4')")
    assert stored and stored in link
    # the first browser's token no longer works
    page.reload()
    page.get_by_test_id("elsewhere").wait_for(timeout=30_000)
    first.close()
    second.close()


def test_a_participant_who_does_not_agree_leaves_for_the_decline_page_and_nothing_is_kept(browser, server):
    context = browser.new_context(viewport={"width": 1400, "height": 1000})
    page = context.new_page()
    page.goto(f"{server['url']}/?participant=E2E-5")
    page.get_by_test_id("decline").wait_for(timeout=30_000)
    assert server["store"].participant("E2E-5") is not None  # the session the page opened
    page.get_by_test_id("decline").click()
    page.wait_for_url("**/declined", timeout=30_000)
    assert "Nothing about you is kept" in page.content()
    assert server["store"].participant("E2E-5") is None
    context.close()


def test_a_participant_meets_each_error_in_words_with_the_contact(browser, server, monkeypatch):
    """Every error a participant can meet is a sentence saying what to do and whom to contact, with a Try again
    button only where trying again can help; the screens are saved with E2E_SHOTS."""
    from sqlalchemy.exc import OperationalError

    store = server["store"]
    base = server["url"]

    def meet(path, name, route=None):
        context = browser.new_context(viewport={"width": 1000, "height": 700})
        page = context.new_page()
        if route is not None:
            page.route("**/api/sessions", route)
        page.goto(base + path)
        error = page.get_by_test_id("error").or_(page.get_by_test_id("finished")).or_(page.get_by_test_id("elsewhere"))
        error.wait_for(timeout=30_000)
        shot(page, f"E2E-error-{name}")
        return context, page, error.inner_text()

    for path, name, words in [
        (f"/?PROLIFIC_PID=E2E-6&STUDY_ID={'x' * 5000}&SESSION_ID=s", "long-study-id",
         "This link is not one the study can take."),
        ("/?STUDY_ID=s", "no-id", "This link does not say who you are."),
        ("/?participant=not%20an%20id!", "bad-id", "The participant id in this link is not one the study can take."),
    ]:
        context, page, text = meet(path, name)
        assert text.startswith(words) and "lab@example.org" in text, text
        assert page.get_by_test_id("retry").count() == 0  # trying again cannot help
        context.close()

    # the database is away: words, the contact, and a Try again that works once it is back
    real = store.participant

    def down(*args, **kwargs):
        raise OperationalError("SELECT 1", {}, ConnectionRefusedError("connection refused"))

    monkeypatch.setattr(store, "participant", down)
    context, page, text = meet("/?participant=E2E-7", "database-away")
    assert "cannot store your answers just now" in text and "lab@example.org" in text, text
    monkeypatch.setattr(store, "participant", real)
    page.get_by_test_id("retry").click()
    page.get_by_test_id("agree").wait_for(timeout=30_000)
    context.close()

    # a failure of the server's own: words and the contact, with a Try again
    def broken(*args, **kwargs):
        raise RuntimeError("a bug")

    monkeypatch.setattr(store, "add_newcomer", broken)
    context, page, text = meet("/?participant=E2E-9", "server-error")
    assert "The study's server had a problem with this step" in text and "lab@example.org" in text, text
    assert "RuntimeError" not in text and page.get_by_test_id("retry").count() == 1
    context.close()
    monkeypatch.undo()

    # a participant who finished, their id in another browser: nothing says they took part, let alone finished
    store.complete("E2E-7", 0.0, 0.0)
    context, page, text = meet("/?participant=E2E-7", "finished-elsewhere")
    assert "This link cannot open the study here" in text and "lab@example.org" in text, text
    assert "finish" not in text.lower(), text
    assert page.locator("button").count() == 0
    context.close()

    # what a proxy answers in its own words (nginx's HTML 413 and 502 pages)
    for status, name, words, retry in [(413, "proxy-413", "The page sent more than the study's server takes.", 0),
                                       (502, "proxy-502", "did not answer properly (error 502)", 1)]:
        def proxy(route, *_, status=status):
            route.fulfill(status=status, content_type="text/html", body=f"<html><h1>{status}</h1></html>")

        context, page, text = meet("/?participant=E2E-8", name, route=proxy)
        assert words in text and "please contact lab@example.org." in text and "<html>" not in text, text
        assert page.get_by_test_id("retry").count() == retry
        context.close()
