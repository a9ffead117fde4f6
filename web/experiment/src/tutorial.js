/**
 * The interactive tutorial: two small towers built with a local `place` function, so nothing of it
 * reaches the server. The first teaches the interface (legality only, every tower stands); the
 * second shows a block tipping over the edge of the block below.
 */

import HtmlButtonResponsePlugin from "@jspsych/plugin-html-button-response";
import OverhangTowerPlugin, { overhang, restingPoses } from "@overhang-framework/jspsych-plugin-overhang-tower";

const GRAVITY = 9.81;

/** A `place` function that accepts every legal placement as standing. */
function standingPlace(sequence, grid) {
  let tower = [[sequence[0], 0, 0]];
  return async ({ step, x, layer }) => {
    if (step === 1) tower = [[sequence[0], 0, 0]];
    tower = [...tower, [sequence[step], x, layer]];
    const trialOver = step === sequence.length - 1;
    const reach = overhang(tower);
    return {
      stable: true,
      overhang: reach,
      reward: trialOver ? reach : null,
      trial_over: trialOver,
      frames: { fps: 30, poses: [restingPoses(tower, grid)] },
    };
  };
}

/**
 * Frames of a block tipping off the edge of the ground block and dropping to the ground: a
 * rotation about the edge, then free flight, then lying still.
 */
function tippingFrames(groundWidth, width, x, blockHeight, fps = 30) {
  const dt = 1 / fps;
  const side = Math.sign(x) || 1;
  const ground = [0, blockHeight / 2, 0];
  const pivot = [side * groundWidth / 2, blockHeight];
  const arm = [x - pivot[0], blockHeight / 2];
  const frames = [];
  let angle = 0;
  let spin = 0;
  let centre = [x, 1.5 * blockHeight];
  while (Math.abs(angle) < 0.6) {
    spin += -side * 6 * dt;
    angle += spin * dt;
    const [c, s] = [Math.cos(angle), Math.sin(angle)];
    centre = [pivot[0] + c * arm[0] - s * arm[1], pivot[1] + s * arm[0] + c * arm[1]];
    frames.push([ground, [...centre, angle]]);
  }
  const r = [centre[0] - pivot[0], centre[1] - pivot[1]];
  let velocity = [-spin * r[1], spin * r[0]];
  const lowest = () => {
    const [c, s] = [Math.abs(Math.cos(angle)), Math.abs(Math.sin(angle))];
    return centre[1] - (c * blockHeight + s * width) / 2;
  };
  while (lowest() > 0 && frames.length < 5 * fps) {
    velocity = [velocity[0], velocity[1] - GRAVITY * dt];
    centre = [centre[0] + velocity[0] * dt, centre[1] + velocity[1] * dt];
    angle += spin * dt;
    frames.push([ground, [...centre, angle]]);
  }
  const flat = Math.round(angle / (Math.PI / 2)) * (Math.PI / 2);
  const upright = Math.round(flat / (Math.PI / 2)) % 2 === 0;
  const rest = [centre[0], (upright ? blockHeight : width) / 2, flat];
  for (let i = 0; i < fps / 2; i += 1) frames.push([ground, rest]);
  return frames;
}

/** A `place` function for one block on the ground block: it stands when its centre is over it. */
function tippingPlace(sequence, grid) {
  return async ({ step, x, layer }) => {
    const tower = [[sequence[0], 0, 0], [sequence[step], x, layer]];
    const stands = Math.abs(x) <= sequence[0] / 2;
    const reach = overhang(tower);
    return {
      stable: stands,
      overhang: reach,
      reward: stands ? reach : 0,
      trial_over: true,
      frames: {
        fps: 30,
        poses: stands ? [restingPoses(tower, grid)] : tippingFrames(sequence[0], sequence[step], x, grid.block_height),
      },
    };
  };
}

const page = (html) => ({
  type: HtmlButtonResponsePlugin,
  stimulus: `<div class="text-page">${html}</div>`,
  choices: ["Continue"],
  button_html: (choice) => `<button class="jspsych-btn" data-testid="continue">${choice}</button>`,
  data: { phase: "tutorial" },
});

export function tutorialTimeline(session, { animationSpeed = 1 } = {}) {
  const grid = session.grid;
  const towerTrial = (sequence, place, prompt) => ({
    type: OverhangTowerPlugin,
    sequence,
    place,
    grid,
    mouse_hz: session.mouse_hz,
    animation_speed: animationSpeed,
    prompt,
    continue_label: "Continue",
    data: { phase: "tutorial" },
  });

  const interfaceSequence = [1.8, 1.2, 0.6];
  const tippingSequence = [1.2, 1.8];
  let fell = false;
  let tries = 0;

  return [
    page(`
      <h2>Tutorial: placing blocks</h2>
      <p>You will now build a small tower yourself. The row of blocks at the top of the screen is
      the whole sequence; grey blocks are already placed and the orange one is the block you place next.</p>
      <p>Move the mouse over the grid: a preview of the next block follows it. Moving left and right
      moves the block freely; moving up and down moves it from one layer to the next.</p>
      <p>The preview is <span class="legal">green</span> where the block may go and
      <span class="illegal">red</span> where it may not: a block must stay inside the grid, must not
      overlap another block, and must rest on a block in the layer just below. Click to place it.</p>`),
    towerTrial(
      interfaceSequence,
      standingPlace(interfaceSequence, grid),
      `<b>Try it.</b> Place the two blocks. Try a red position too: clicking there does nothing.`,
    ),
    page(`
      <h2>Tutorial: towers can fall</h2>
      <p>The blocks obey real physics. After every block you place, the tower is left to stand for
      a few seconds. If it is unstable, you will see it fall.</p>
      <p>Next, place a long block on a short one so that its middle lies <b>beyond the edge</b> of
      the block below, and watch what happens.</p>`),
    {
      timeline: [
        towerTrial(
          tippingSequence,
          tippingPlace(tippingSequence, grid),
          `Place the long block with its middle beyond the edge of the block below.`,
        ),
      ],
      loop_function: (data) => {
        tries += 1;
        fell ||= data.values().some((trial) => trial.stable === false);
        return !fell && tries < 3;
      },
    },
    page(`
      <h2>Tutorial: what you see and what you earn</h2>
      <p>The green preview only tells you whether a block <i>fits</i> somewhere. It never tells you
      whether the tower will stand: you find that out only after you have placed the block.</p>
      <p>Your score for a tower is its <b>overhang</b>: how far the tower reaches sideways from the
      centre of the ground (the small mark under the first block), to the outer edge of its
      furthest block, on either side.</p>
      <p>If every block you place stays put, the trial's reward is the final overhang. If anything
      falls, the trial ends at once and its reward is 0.</p>
      <p>Each unit of reward you earn in the main trials adds
      ${session.currency}${session.bonus_per_unit.toFixed(2)} to your bonus.</p>
      ${session.time_limit == null ? "" : `<p>You have <b>${session.time_limit} seconds</b> for each
      block; a clock above the grid counts down. If it runs out, the trial ends with a reward of 0.</p>`}`),
  ];
}
