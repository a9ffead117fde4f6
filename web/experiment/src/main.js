/**
 * The paper's procedure: session, consent, instructions, tutorial, practice until passed, the
 * main trials in the server's order, and the debriefing with the bonus and the completion link.
 *
 * The consent text comes from the server (the study's `consent_file`), and "I agree" is recorded by
 * the server with its time and the text's version before anything else happens: the server places
 * nothing for a participant without it. "I do not agree" has the server delete the session, and
 * leaves for the study's `decline_url`.
 *
 * The server's `position` drives the practice and main phases: every placement's response carries
 * the next position, and each trial starts from it. A reopened tab therefore continues where the
 * participant stopped. The server also keeps each step's clock: a trial's first step is started
 * with `POST /api/steps/start` (whose reply brings the trial's blocks), later steps by the previous
 * placement's reply, and the time left shown is the server's, so a reload does not give more time.
 * A refusal that means the page is out of step with the server (409: another tab went on; 403: a
 * new link was issued) reloads the page or says whom to contact, rather than retrying for ever.
 */

import { initJsPsych } from "jspsych";
import HtmlButtonResponsePlugin from "@jspsych/plugin-html-button-response";
import InstructionsPlugin from "@jspsych/plugin-instructions";
import OverhangTowerPlugin, { renderTower } from "@overhang-framework/jspsych-plugin-overhang-tower";

import { ApiError, openSession, post, takeTokenFromUrl } from "./api.js";
import { instructionPages } from "./text.js";
import { tutorialTimeline } from "./tutorial.js";

const target = document.getElementById("experiment");

function showMessage(title, html, testid) {
  target.innerHTML = `<div class="text-page notice" data-testid="${testid}"><h2>${title}</h2>${html}</div>`;
}

const escapeHtml = (text) =>
  String(text).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);

function showElsewhere(contact) {
  showMessage(
    "This link cannot open the study here",
    `<p>A session with this link was started in another browser or on another device, so it cannot be
    opened here.</p>
    <p>Please contact <b>${escapeHtml(contact || "the researcher")}</b> and ask for a new link. A new
    link opens your session in this browser, where it stands.</p>`,
    "elsewhere",
  );
}

function showScreenedOut(url) {
  showMessage(
    "Thank you for your time",
    `<p>The main part of the study needs each practice tower to be passed, and the attempts for
    this one are used up, so the study ends here for you.</p>
    <p>This is no fault of yours: the task is hard to get used to. Please press the button to
    return to the study platform.</p>`,
    "screened-out",
  );
  const leave = document.createElement("button");
  leave.className = "jspsych-btn";
  leave.dataset.testid = "leave";
  leave.dataset.href = url;
  leave.textContent = "Return to the study platform";
  leave.addEventListener("click", () => window.location.assign(url));
  target.querySelector(".notice").append(leave);
}

/**
 * An error in the participant's words, with whom to contact, and a Try again button only when trying
 * again can help (no answer, or the server's own failure).
 */
function showError(error, retry = null, contact = null) {
  target.replaceChildren();
  const box = document.createElement("div");
  box.className = "error-box";
  const text = document.createElement("p");
  text.dataset.testid = "error";
  let message = error?.message || "Something went wrong.";
  if (!/contact/i.test(message)) {
    const lab = document.querySelector('meta[name="overhang-contact"]')?.content;
    message += ` If this keeps happening, please contact ${error?.contact || contact || lab || "the researcher"}.`;
  }
  text.textContent = message;
  box.append(text);
  if (retry && !(error instanceof ApiError && !error.retryable)) {
    const button = document.createElement("button");
    button.className = "jspsych-btn";
    button.dataset.testid = "retry";
    button.textContent = "Try again";
    button.addEventListener("click", retry);
    box.append(button);
  }
  target.append(box);
}

/** A request whose refusal means the page is out of step with the server: reload, or say whom to contact. */
async function synced(request, session) {
  try {
    return await request();
  } catch (error) {
    if (error instanceof ApiError && error.status === 409) {
      window.location.reload();
      return new Promise(() => {});
    }
    if (error instanceof ApiError && error.status === 403) {
      showElsewhere(session.contact);
      return new Promise(() => {});
    }
    throw error;
  }
}

const button = (testid) => (choice) => `<button class="jspsych-btn" data-testid="${testid}">${choice}</button>`;

const isAtStart = (session) => {
  const { phase, trial, attempt, step } = session.position;
  return phase === "practice" && trial === session.practice[0]?.trial && attempt === 1 && step === 1;
};

function buildTimeline(jsPsych, session, state, { animationSpeed }) {
  const token = session.token;
  const money = (amount) => `${session.currency}${amount.toFixed(2)}`;
  let position = session.position;
  state.position = position;
  let totalReward = position.total_reward ?? 0;
  let lastOutcome = null;
  let lastOutcomeAt = 0;
  let context = null;

  const place = async (payload) => {
    const body = { phase: position.phase, trial: position.trial, attempt: position.attempt, ...payload };
    const outcome = await synced(() => post("api/placements", body, token), session);
    if (outcome.position) position = state.position = outcome.position;
    if (typeof outcome.total_reward === "number") totalReward = outcome.total_reward;
    if (outcome.screen_out_url) state.screenOutUrl = outcome.screen_out_url;
    lastOutcome = outcome;
    lastOutcomeAt = performance.now();
    return outcome;
  };

  /** The clock of the step about to begin: from the placement reply that handed it out, else from the server. */
  const beginStep = async ({ step }) => {
    const { phase, trial, attempt } = position;
    const clock = lastOutcome?.clock;
    if (clock && clock.phase === phase && clock.trial === trial && clock.attempt === attempt && clock.step === step) {
      const since = (performance.now() - lastOutcomeAt) / 1000;
      lastOutcome.clock = null; // once: a retried decision asks the server again
      if (since < 2) return { ...clock, time_left: clock.time_left == null ? null : Math.max(0, clock.time_left - since) };
    }
    const reply = await synced(() => post("api/steps/start", { phase, trial, attempt, step }, token), session);
    if (context && reply.task) context.task_id = reply.task.task_id;
    return { ...reply.clock, sequence: reply.task?.sequence };
  };

  const prompt = () => {
    const { phase, trial, attempt } = position;
    if (phase === "practice") {
      const index = session.practice.findIndex((task) => task.trial === trial) + 1;
      const tries = attempt > 1 ? ` (attempt ${attempt})` : "";
      return `<b>Practice ${index} of ${session.practice.length}</b>${tries}: build a tower that reaches as far out as you can.`;
    }
    const index = session.trials.findIndex((task) => task.trial === trial) + 1;
    return `<b>Trial ${index} of ${session.trials.length}</b> &middot; total reward so far: ${totalReward.toFixed(2)}`;
  };

  const towerTrial = {
    type: OverhangTowerPlugin,
    sequence: [], // the server sends a trial's blocks when the trial starts

    tower: () => position.tower,
    step: () => position.step,
    place,
    begin_step: beginStep,
    time_limit: session.time_limit,
    grid: session.grid,
    mouse_hz: session.mouse_hz,
    animation_speed: animationSpeed,
    prompt,
    on_start: () => {
      const { phase, trial, attempt } = position;
      context = { phase, trial, attempt, task_id: null };
    },
    on_finish: (data) => Object.assign(data, context),
  };

  const practiceFeedback = {
    type: HtmlButtonResponsePlugin,
    stimulus: () => {
      const passed = Boolean(lastOutcome?.passed);
      const reward = lastOutcome?.reward ?? 0;
      const shown = lastOutcome?.shown_reward ?? 0;
      const needed = lastOutcome?.pass_reward ?? 0;
      const ground = (lastOutcome?.shown_tower?.[0]?.[0] ?? 0) / 2;
      const screenedOut = lastOutcome?.position?.phase === "screened_out";
      const timedOut = Boolean(lastOutcome?.timed_out);
      const what = timedOut
        ? "The time for a block ran out, so this tower earns nothing."
        : lastOutcome?.stable === false
          ? "A block fell, so this tower earns nothing."
          : `Your tower reaches <b>${reward.toFixed(2)}</b>.`;
      const next = passed
        ? "Well done."
        : screenedOut
          ? "That was the last attempt for this tower."
          : `Have another go at the same blocks.${timedOut ? " Remember: place each block within the time." : ""}`;
      return `
        <div class="practice-feedback" data-testid="practice-feedback" data-passed="${passed}"
             data-timed-out="${timedOut}">
          <h2>${passed ? "Passed!" : "Not passed yet"}</h2>
          <p>${what} The bottom block alone reaches <b>${ground.toFixed(2)}</b> and a good tower with these
          blocks <b>${shown.toFixed(2)}</b>; to pass, your tower must stand and reach at least
          <b>${needed.toFixed(2)}</b>.</p>
          <div class="tower-pair">
            <figure><canvas id="practice-yours"></canvas><figcaption>Your tower</figcaption></figure>
            <figure><canvas id="practice-optimal"></canvas><figcaption>A good tower</figcaption></figure>
          </div>
          <p>${next}</p>
        </div>`;
    },
    choices: () => [lastOutcome?.passed || lastOutcome?.position?.phase !== "practice" ? "Continue" : "Try again"],
    button_html: button("continue"),
    on_load: () => {
      const last = jsPsych.data.get().filter({ trial_type: "overhang-tower" }).last(1).values()[0];
      const shownTower = lastOutcome?.shown_tower ?? [];
      const ppu = Math.min(32, Math.floor((window.innerWidth - 120) / 20));
      renderTower(document.getElementById("practice-yours"), { poses: last.final_poses, grid: session.grid, pixelsPerUnit: ppu });
      renderTower(document.getElementById("practice-optimal"), { tower: shownTower, grid: session.grid, pixelsPerUnit: ppu });
    },
    data: { phase: "practice-feedback" },
  };

  const practice = {
    timeline: [towerTrial, practiceFeedback],
    conditional_function: () => position.phase === "practice",
    loop_function: () => position.phase === "practice",
  };

  // jsPsych asks a timeline's conditional_function, not a trial's: the screen sits in a timeline of its own,
  // so that a participant screened out in the practice never sees it
  const mainIntro = {
    timeline: [{
      type: HtmlButtonResponsePlugin,
      stimulus: `<div class="text-page">
        <h2>The main part</h2>
        <p>You will now build ${session.trials.length} towers, each from a new sequence of blocks.
        There is one attempt per tower. Your bonus is ${money(session.bonus_per_unit)} per unit of reward.</p>
        ${session.time_limit == null ? "" : `<p>You have <b>${session.time_limit} seconds</b> per block.</p>`}
        </div>`,
      choices: ["Start"],
      button_html: button("start-main"),
    }],
    conditional_function: () => position.phase === "main",
  };

  const main = {
    timeline: [towerTrial],
    conditional_function: () => position.phase === "main",
    loop_function: () => position.phase === "main",
  };

  if (isAtStart(session)) {
    return [
      { type: InstructionsPlugin, pages: instructionPages(session), show_clickable_nav: true, allow_backward: true },
      ...tutorialTimeline(session, { animationSpeed }),
      practiceIntro(session),
      practice,
      mainIntro,
      main,
    ];
  }
  // the main part's instructions (where the time limit is stated) come before its first trial
  const { phase, trial, step } = position;
  const beforeMain = phase === "practice" || (phase === "main" && trial === 1 && step === 1 && !session.clock);
  return [
    // a step whose clock runs goes on at once; otherwise the participant says when to go on
    ...(session.clock ? [] : [resumeScreen(session)]),
    practice,
    { timeline: [mainIntro], conditional_function: () => beforeMain },
    main,
  ];
}

function practiceIntro(session) {
  return {
    type: HtmlButtonResponsePlugin,
    stimulus: `<div class="text-page">
      <h2>Practice</h2>
      <p>Now ${session.practice.length} practice towers. A tower that stands is not enough to pass: it
      must also reach out well beyond its bottom block. After each one you will see a good
      tower beside yours, and the reward you need to pass; if you do not pass, you try the same
      blocks again${session.practice_max_attempts ? ` (up to ${session.practice_max_attempts} attempts per tower)` : ""}.</p></div>`,
    choices: ["Start practice"],
    button_html: button("start-practice"),
  };
}

function resumeScreen(session) {
  const { phase } = session.position;
  const where = phase === "practice" ? "the practice" : "the main part";
  return {
    type: HtmlButtonResponsePlugin,
    stimulus: `<div class="text-page"><h2>Welcome back</h2>
      <p>You continue in ${where} where you stopped.</p></div>`,
    choices: ["Continue"],
    button_html: button("resume"),
  };
}

async function debrief(session) {
  target.replaceChildren();
  let result;
  try {
    result = await post("api/finish", {}, session.token);
  } catch (error) {
    showError(error, () => debrief(session), session.contact);
    return;
  }
  const money = `${session.currency}${Number(result.bonus).toFixed(2)}`;
  target.innerHTML = `
    <div class="text-page debrief">
      <h2>Thank you!</h2>
      <p>You have finished the experiment. Your total reward is
      <b data-testid="total-reward">${Number(result.total_reward).toFixed(2)}</b>, which earns you a
      bonus of <b data-testid="bonus">${money}</b>.</p>
      <p>The study looked at how people plan a sequence of physical actions: how far they let a
      tower reach out while keeping it standing, and how this changes with time pressure.</p>
      ${result.completion_url ? "<p>Click the button to return to the study platform and record your completion.</p>" : "<p>You may now close this window.</p>"}
    </div>`;
  if (result.completion_url) {
    const finish = document.createElement("button");
    finish.className = "jspsych-btn";
    finish.dataset.testid = "finish";
    finish.dataset.href = result.completion_url;
    finish.textContent = "Finish";
    finish.addEventListener("click", () => {
      window.location.assign(result.completion_url);
    });
    target.querySelector(".debrief").append(finish);
  }
}

/** The consent page until "I agree" is recorded by the server (at once when it was, in an earlier visit). */
function askConsent(session) {
  if (session.consent.given) return Promise.resolve();
  return new Promise((resolve) => {
    const show = () => {
      // laid out as jsPsych lays out a trial (its display element, centred content), before jsPsych starts
      target.classList.add("jspsych-display-element");
      target.innerHTML = `<div class="jspsych-content-wrapper"><div class="jspsych-content">${session.consent.html}
        <div class="consent-actions"></div></div></div>`;
      const agree = document.createElement("button");
      agree.className = "jspsych-btn";
      agree.dataset.testid = "agree";
      agree.textContent = "I agree";
      agree.addEventListener("click", async () => {
        agree.disabled = true;
        try {
          await synced(() => post("api/consent", { version: session.consent.version }, session.token), session);
          resolve();
        } catch (error) {
          showError(error, show, session.contact);
        }
      });
      const decline = document.createElement("button");
      decline.className = "jspsych-btn";
      decline.dataset.testid = "decline";
      decline.textContent = "I do not agree";
      decline.addEventListener("click", async () => {
        decline.disabled = agree.disabled = true;
        try {
          const { decline_url: url } = await post("api/decline", {}, session.token);
          window.location.assign(url);
        } catch (error) {
          showError(error, show, session.contact);
        }
      });
      target.querySelector(".consent-actions").append(agree, " ", decline);
    };
    show();
  });
}

async function start() {
  const { params, token } = takeTokenFromUrl();
  target.innerHTML = `<p class="loading">Loading…</p>`;
  let session;
  try {
    session = await openSession(params, token);
  } catch (error) {
    if (error.reason === "session_elsewhere") showElsewhere(error.data?.contact);
    else if (error.reason === "finished") showMessage("You have finished", `<p>${escapeHtml(error.message)}</p>`, "finished");
    else showError(error, () => start());
    return;
  }
  const animationSpeed = Number(params.animation_speed) > 0 ? Number(params.animation_speed) : 1;
  const state = { position: session.position };
  if (!["done", "screened_out"].includes(session.position.phase) && !session.completed) {
    await askConsent(session);
    target.replaceChildren();
    const jsPsych = initJsPsych({ display_element: target });
    await jsPsych.run(buildTimeline(jsPsych, session, state, { animationSpeed }));
  }
  if (state.position.phase === "screened_out") {
    showScreenedOut(session.screen_out_url ?? state.screenOutUrl ?? "/screened-out");
    return;
  }
  await debrief(session);
}

start();
