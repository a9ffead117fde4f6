/**
 * The paper's procedure: session, consent, instructions, tutorial, practice until passed, the
 * main trials in the server's order, and the debriefing with the bonus and the completion link.
 *
 * The server's `position` drives the practice and main phases: every placement's response carries
 * the next position, and each trial starts from it. A reopened tab therefore continues where the
 * participant stopped.
 */

import { initJsPsych } from "jspsych";
import HtmlButtonResponsePlugin from "@jspsych/plugin-html-button-response";
import InstructionsPlugin from "@jspsych/plugin-instructions";
import OverhangTowerPlugin, { renderTower } from "@overhang-framework/jspsych-plugin-overhang-tower";

import { openSession, post } from "./api.js";
import { CONSENT_HTML, instructionPages } from "./text.js";
import { tutorialTimeline } from "./tutorial.js";

const target = document.getElementById("experiment");

function showError(message, retry = null) {
  target.replaceChildren();
  const box = document.createElement("div");
  box.className = "error-box";
  const text = document.createElement("p");
  text.dataset.testid = "error";
  text.textContent = message;
  box.append(text);
  if (retry) {
    const button = document.createElement("button");
    button.className = "jspsych-btn";
    button.dataset.testid = "retry";
    button.textContent = "Try again";
    button.addEventListener("click", retry);
    box.append(button);
  }
  target.append(box);
}

const button = (testid) => (choice) => `<button class="jspsych-btn" data-testid="${testid}">${choice}</button>`;

const isAtStart = (session) => {
  const { phase, trial, attempt, step } = session.position;
  return phase === "practice" && trial === session.practice[0]?.trial && attempt === 1 && step === 1;
};

function buildTimeline(jsPsych, session, { animationSpeed }) {
  const token = session.token;
  const money = (amount) => `${session.currency}${amount.toFixed(2)}`;
  let position = session.position;
  let totalReward = position.total_reward ?? 0;
  let lastOutcome = null;
  let context = null;

  const taskAt = ({ phase, trial }) =>
    (phase === "practice" ? session.practice : session.trials).find((task) => task.trial === trial);

  const place = async (payload) => {
    const body = { phase: position.phase, trial: position.trial, attempt: position.attempt, ...payload };
    const outcome = await post("api/placements", body, token);
    if (outcome.position) position = outcome.position;
    if (typeof outcome.total_reward === "number") totalReward = outcome.total_reward;
    lastOutcome = outcome;
    return outcome;
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
    sequence: () => taskAt(position).sequence,
    tower: () => position.tower,
    step: () => position.step,
    place,
    time_limit: session.time_limit,
    grid: session.grid,
    mouse_hz: session.mouse_hz,
    animation_speed: animationSpeed,
    prompt,
    on_start: () => {
      const { phase, trial, attempt } = position;
      context = { phase, trial, attempt, task_id: taskAt(position).task_id };
    },
    on_finish: (data) => Object.assign(data, context),
  };

  const practiceFeedback = {
    type: HtmlButtonResponsePlugin,
    stimulus: () => {
      const passed = Boolean(lastOutcome?.passed);
      const reward = lastOutcome?.reward ?? 0;
      const optimum = lastOutcome?.optimum ?? taskAt(context).optimum;
      const needed = session.practice_threshold * optimum;
      return `
        <div class="practice-feedback" data-testid="practice-feedback" data-passed="${passed}">
          <h2>${passed ? "Passed!" : "Not passed yet"}</h2>
          <p>Your reward: <b>${reward.toFixed(2)}</b>. The best possible tower reaches
          <b>${optimum.toFixed(2)}</b>; to pass you need at least ${needed.toFixed(2)}.</p>
          <div class="tower-pair">
            <figure><canvas id="practice-yours"></canvas><figcaption>Your tower</figcaption></figure>
            <figure><canvas id="practice-optimal"></canvas><figcaption>The best tower</figcaption></figure>
          </div>
          <p>${passed ? "Well done." : "Have another go at the same blocks."}</p>
        </div>`;
    },
    choices: () => [lastOutcome?.passed ? "Continue" : "Try again"],
    button_html: button("continue"),
    on_load: () => {
      const last = jsPsych.data.get().filter({ trial_type: "overhang-tower" }).last(1).values()[0];
      const task = taskAt(context);
      const optimalTower = lastOutcome?.optimal_tower ?? task.optimal_tower;
      const ppu = Math.min(32, Math.floor((window.innerWidth - 120) / 20));
      renderTower(document.getElementById("practice-yours"), { poses: last.final_poses, grid: session.grid, pixelsPerUnit: ppu });
      renderTower(document.getElementById("practice-optimal"), { tower: optimalTower, grid: session.grid, pixelsPerUnit: ppu });
    },
    data: { phase: "practice-feedback" },
  };

  const practice = {
    timeline: [towerTrial, practiceFeedback],
    conditional_function: () => position.phase === "practice",
    loop_function: () => position.phase === "practice",
  };

  const mainIntro = {
    type: HtmlButtonResponsePlugin,
    stimulus: `<div class="text-page">
      <h2>The main part</h2>
      <p>You will now build ${session.trials.length} towers, each from a new sequence of blocks.
      There is one attempt per tower. Your bonus is ${money(session.bonus_per_unit)} per unit of reward.</p>
      ${session.time_limit == null ? "" : `<p>You have <b>${session.time_limit} seconds</b> per block.</p>`}
      </div>`,
    choices: ["Start"],
    button_html: button("start-main"),
  };

  const main = {
    timeline: [towerTrial],
    conditional_function: () => position.phase === "main",
    loop_function: () => position.phase === "main",
  };

  if (isAtStart(session)) {
    return [
      { type: HtmlButtonResponsePlugin, stimulus: CONSENT_HTML, choices: ["I agree"], button_html: button("agree") },
      { type: InstructionsPlugin, pages: instructionPages(session), show_clickable_nav: true, allow_backward: true },
      ...tutorialTimeline(session, { animationSpeed }),
      practiceIntro(session),
      practice,
      mainIntro,
      main,
    ];
  }
  const startedInPractice = position.phase === "practice";
  return [
    resumeScreen(session),
    practice,
    { timeline: [mainIntro], conditional_function: () => startedInPractice && position.phase === "main" },
    main,
  ];
}

function practiceIntro(session) {
  return {
    type: HtmlButtonResponsePlugin,
    stimulus: `<div class="text-page">
      <h2>Practice</h2>
      <p>Now ${session.practice.length} practice towers. After each one you will see the best
      possible tower beside yours. To pass a practice tower you need a reward of at least
      ${Math.round(session.practice_threshold * 100)}% of the best one; if you do not, you try the
      same blocks again.</p></div>`,
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
    showError(error.message, () => debrief(session));
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

async function start() {
  const params = Object.fromEntries(new URLSearchParams(window.location.search));
  target.innerHTML = `<p class="loading">Loading…</p>`;
  let session;
  try {
    session = await openSession(params);
  } catch (error) {
    showError(error.message, () => start());
    return;
  }
  const animationSpeed = Number(params.animation_speed) > 0 ? Number(params.animation_speed) : 1;
  if (session.position.phase !== "done" && !session.completed) {
    target.replaceChildren();
    const jsPsych = initJsPsych({ display_element: target });
    await jsPsych.run(buildTimeline(jsPsych, session, { animationSpeed }));
  }
  await debrief(session);
}

start();
