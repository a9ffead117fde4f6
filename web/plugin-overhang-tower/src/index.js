import { ParameterType } from "jspsych";

import { DEFAULT_GRID, illegalReason, overhang, previewPosition, restingPoses } from "./geometry.js";
import { TrialRecord, framePoses } from "./record.js";
import { TowerScene, fittingPixelsPerUnit } from "./scene.js";
import { SimulatedParticipant, simulateData } from "./simulate.js";

export {
  DEFAULT_GRID, groundTower, illegalReason, isLegal, overhang, previewPosition, restingPoses,
} from "./geometry.js";
export { COLORS, TowerScene, fittingPixelsPerUnit, renderTower } from "./scene.js";
export { SimulatedParticipant, choosePlacement } from "./simulate.js";

const info = {
  name: "overhang-tower",
  version: "0.1.0",
  parameters: {
    /**
     * Block widths in placement order; `sequence[0]` is the ground block. Empty when `begin_step` gives
     * them (a server that shows a trial's blocks only once its clock runs).
     */
    sequence: { type: ParameterType.FLOAT, array: true, default: [] },
    /**
     * `place(payload)` sends one placement and returns a Promise of its outcome.
     * payload: {step, x, layer, timed_out, decision_time, trajectory, dwell};
     * outcome: {stable, overhang, reward, trial_over, timed_out, frames: {fps, poses}, ...}; `timed_out`
     * true means the placement came too late and counts as a timeout.
     */
    place: { type: ParameterType.FUNCTION, default: undefined },
    /** The tower the next placement goes on, `[width, x, layer]` per block; null: the ground block alone. */
    tower: { type: ParameterType.COMPLEX, default: null },
    /** The next step: step k places `sequence[k]`. */
    step: { type: ParameterType.INT, default: 1 },
    /** Seconds per placement, or null for no limit. */
    time_limit: { type: ParameterType.FLOAT, default: null },
    /**
     * `begin_step({step})`, called as each decision begins, returns a Promise of the step's clock
     * `{time_left, sequence}`: the seconds really left when a server keeps the time (after a reload,
     * say), and optionally the trial's blocks. Null: every decision gets the whole `time_limit`, timed
     * by the page.
     */
    begin_step: { type: ParameterType.FUNCTION, default: null },
    /** {half_width, height, block_height, max_layer}, in task units. */
    grid: { type: ParameterType.OBJECT, default: DEFAULT_GRID },
    /** Samples per second of the mouse trajectory. */
    mouse_hz: { type: ParameterType.INT, default: 30 },
    /** Playback speed of the physics frames (2 plays twice as fast). */
    animation_speed: { type: ParameterType.FLOAT, default: 1 },
    /** CSS pixels per task unit; null fits the scene to the window. */
    pixels_per_unit: { type: ParameterType.FLOAT, default: null },
    /** HTML shown above the task. */
    prompt: { type: ParameterType.HTML_STRING, default: null },
    /** Whether the overhang and the trial's reward are shown. */
    show_reward: { type: ParameterType.BOOL, default: true },
    /** Label of the button that ends the trial once it is over. */
    continue_label: { type: ParameterType.STRING, default: "Continue" },
    /** Decimals shown for overhang and reward. */
    precision: { type: ParameterType.INT, default: 2 },
  },
  data: {
    /** The block widths. */
    sequence: { type: ParameterType.FLOAT, array: true },
    /** The step and the tower the trial started from. */
    start_step: { type: ParameterType.INT },
    start_tower: { type: ParameterType.COMPLEX, array: true },
    /** Each placement's payload as sent to `place`. */
    placements: { type: ParameterType.COMPLEX, array: true },
    /** Each placement's outcome, `frames` replaced by `frame_count`. */
    outcomes: { type: ParameterType.COMPLEX, array: true },
    /** The trial's reward (the last outcome's `reward`). */
    reward: { type: ParameterType.FLOAT },
    /** The last outcome's overhang. */
    overhang: { type: ParameterType.FLOAT },
    /** Whether every placement stood. */
    stable: { type: ParameterType.BOOL },
    timed_out: { type: ParameterType.BOOL },
    /** The standing tower at the end, `[width, x, layer]` per block. */
    final_tower: { type: ParameterType.COMPLEX, array: true },
    /** What was shown last, `[width, x, z, angle]` per block (a collapse's last frame). */
    final_poses: { type: ParameterType.COMPLEX, array: true },
  },
};

const round = (value, digits = 3) => Math.round(value * 10 ** digits) / 10 ** digits;

/**
 * **overhang-tower**: one trial of the Overhang Tower task, from a given step to the end of the
 * trial. The participant moves a preview of the next block over the grid and clicks to place it;
 * `place` reports what the physics made of it, which is then animated.
 */
class OverhangTowerPlugin {
  static info = info;

  constructor(jsPsych) {
    this.jsPsych = jsPsych;
  }

  trial(displayElement, trial) {
    new TowerTrial(this.jsPsych, displayElement, trial).start();
  }

  /**
   * Runs the trial without a person. `data-only`: a simulated participant's placements go to
   * `place` (and `begin_step`, when given) as the page would send them, and the trial's data is
   * built from the outcomes, with `simulation_options.data` laid over it. `visual`: the trial runs
   * on the page and the simulated participant moves the pointer and clicks. In both modes
   * `simulation_options.data.placements`, when given, are the decisions made in turn (`{x, layer}`,
   * `{timed_out: true}`, optionally `decision_time`); later decisions are the participant's own.
   */
  simulate(trial, simulation_mode, simulation_options, load_callback) {
    const participant = new SimulatedParticipant(this.jsPsych, simulation_options?.data?.placements);
    if (simulation_mode === "visual") {
      // settles only by failing: the trial itself ends with finishTrial
      return new Promise((_, reject) => {
        new TowerTrial(this.jsPsych, this.jsPsych.getDisplayElement(), trial, { participant, fail: reject }).start();
        load_callback();
      });
    }
    // the planned placements are sent, so the data keeps them as sent (with their pointer paths)
    const { placements, ...overrides } = simulation_options?.data ?? {};
    return simulateData(trial, participant).then((data) => {
      this.jsPsych.finishTrial(this.jsPsych.pluginAPI.mergeSimulationData(data, { data: overrides }));
    });
  }
}

class TowerTrial {
  /** `participant` (with `fail(error)`, called when it cannot go on) plays the trial in a simulation. */
  constructor(jsPsych, root, params, { participant = null, fail = null } = {}) {
    this.jsPsych = jsPsych;
    this.root = root;
    this.params = params;
    this.participant = participant;
    this.fail = fail;
    this.grid = { ...DEFAULT_GRID, ...params.grid };
    this.record = new TrialRecord(params);
    this.step = params.step;
    this.placedCount = this.tower.length;
    this.shownPoses = null;
    this.pointer = null;
    this.ghost = null;
    this.decision = null;
    this.timers = new Set();
    this.frameRequest = null;
  }

  get tower() {
    return this.record.tower;
  }

  get sequence() {
    return this.record.sequence;
  }

  start() {
    this.buildDom();
    this.listen(this.canvas, "pointermove", (event) => this.onPointerMove(event));
    this.listen(this.canvas, "pointerleave", () => this.onPointerLeave());
    this.listen(this.canvas, "click", (event) => this.onClick(event));
    this.updateScores(overhang(this.tower), null);
    this.beginDecision();
  }

  /**
   * The seconds this decision has: the server's clock when `begin_step` gives one, else `time_limit`.
   * Takes the trial's blocks from `begin_step` when it gives them.
   */
  async timeAllowed() {
    const limit = this.params.time_limit;
    if (!this.params.begin_step) return limit;
    const clock = await this.params.begin_step({ step: this.step });
    if (Array.isArray(clock?.sequence)) this.record.setSequence(clock.sequence);
    if (limit == null) return null;
    return typeof clock?.time_left === "number" ? clock.time_left : limit;
  }

  buildDom() {
    const p = this.params;
    this.root.innerHTML = `
      <div class="overhang-tower" data-state="deciding">
        ${p.prompt ? `<div class="ot-prompt">${p.prompt}</div>` : ""}
        <div class="ot-status">
          <span class="ot-step" data-testid="step"></span>
          <span class="ot-timer" data-testid="timer"></span>
          <span class="ot-score" data-testid="overhang"></span>
          <span class="ot-score" data-testid="reward"></span>
        </div>
        <canvas class="ot-canvas" data-testid="overhang-canvas"></canvas>
        <div class="ot-message" data-testid="message" aria-live="polite"></div>
        <div class="ot-actions"></div>
      </div>`;
    const $ = (selector) => this.root.querySelector(selector);
    this.container = $(".overhang-tower");
    this.canvas = $("canvas");
    this.stepText = $(".ot-step");
    this.timerText = $(".ot-timer");
    this.overhangText = $('[data-testid="overhang"]');
    this.rewardText = $('[data-testid="reward"]');
    this.message = $(".ot-message");
    this.actions = $(".ot-actions");
    this.timerText.hidden = p.time_limit == null;
    this.overhangText.hidden = !p.show_reward;
    this.rewardText.hidden = !p.show_reward;
    const ppu = p.pixels_per_unit ?? fittingPixelsPerUnit(this.grid);
    this.scene = new TowerScene(this.canvas, { grid: this.grid, pixelsPerUnit: ppu });
  }

  setState(state) {
    this.state = state;
    this.container.dataset.state = state;
    this.canvas.classList.toggle("ot-deciding", state === "deciding");
  }

  listen(target, type, handler) {
    target.addEventListener(type, handler);
    (this.listeners ??= []).push(() => target.removeEventListener(type, handler));
  }

  later(callback, ms) {
    const id = setTimeout(() => {
      this.timers.delete(id);
      callback();
    }, ms);
    this.timers.add(id);
    return id;
  }

  every(callback, ms) {
    const id = setInterval(callback, ms);
    this.timers.add(id);
    return id;
  }

  stopTimer(id) {
    clearTimeout(id);
    clearInterval(id);
    this.timers.delete(id);
  }

  // ---- drawing -------------------------------------------------------------------------------

  blocksAtRest() {
    return restingPoses(this.tower, this.grid).map((pose, i) => [this.tower[i][0], ...pose]);
  }

  render() {
    this.scene.draw({
      blocks: this.shownPoses ?? this.blocksAtRest(),
      ghost: this.state === "deciding" ? this.ghost : null,
      sequence: this.sequence,
      placed: this.placedCount,
      next: this.state === "done" ? null : this.step,
    });
  }

  updateScores(overhangValue, reward) {
    const digits = this.params.precision;
    const show = (value) => (typeof value === "number" ? value.toFixed(digits) : "–");
    this.overhangText.textContent = `Overhang: ${show(overhangValue)}`;
    this.overhangText.dataset.value = typeof overhangValue === "number" ? String(overhangValue) : "";
    this.rewardText.textContent = `Reward: ${show(reward)}`;
    this.rewardText.dataset.value = typeof reward === "number" ? String(reward) : "";
  }

  // ---- one decision --------------------------------------------------------------------------

  async beginDecision() {
    this.message.textContent = "";
    this.actions.replaceChildren();
    let allowed;
    try {
      this.setState("waiting");
      this.render();
      allowed = await this.timeAllowed();
    } catch (error) {
      this.showError(error, () => this.beginDecision());
      return;
    }
    this.stepText.textContent = `Block ${this.step + 1} of ${this.sequence.length}`;
    this.container.dataset.step = String(this.step);
    this.container.dataset.tower = JSON.stringify(this.tower);
    const start = performance.now();
    this.decision = { start, allowed, trajectory: [], dwell: new Map(), dwellKey: null, dwellSince: start };
    this.setState("deciding");
    this.updateGhost();
    this.render();

    const hz = Math.max(1, this.params.mouse_hz);
    this.decision.sampler = this.every(() => this.sampleMouse(), 1000 / hz);
    this.sampleMouse();

    if (allowed != null) {
      this.decision.countdown = this.every(() => this.showTimeLeft(), 100);
      this.decision.deadline = this.later(() => this.timeOut(), Math.max(0, allowed) * 1000);
      this.showTimeLeft();
    }
    if (this.participant) this.act(allowed);
  }

  /** The simulated participant's decision, made with the pointer: moves over the canvas, then a click. */
  act(allowed) {
    let choice;
    try {
      choice = this.participant.decide({ tower: this.tower, width: this.sequence[this.step], grid: this.grid, allowed });
    } catch (error) {
      this.cleanUp();
      this.fail(error);
      return;
    }
    const point = this.participant.startPoint(this.grid);
    const aim = choice.timed_out ? point : { x: choice.x, z: (choice.layer + 0.5) * this.grid.block_height };
    const ms = choice.decision_time * 1000;
    this.later(() => this.pointAt("pointermove", point), 0);
    this.later(() => this.pointAt("pointermove", { x: (point.x + aim.x) / 2, z: (point.z + aim.z) / 2 }), ms * 0.3);
    this.later(() => this.pointAt("pointermove", aim), ms * 0.6);
    if (!choice.timed_out) this.later(() => this.pointAt("click", aim), ms);
    else if (allowed == null) this.later(() => this.timeOut(), ms);
  }

  pointAt(type, { x, z }) {
    const rect = this.canvas.getBoundingClientRect();
    const { scene } = this;
    const Pointer = type !== "click" && typeof PointerEvent === "function" ? PointerEvent : MouseEvent;
    this.canvas.dispatchEvent(
      new Pointer(type, {
        bubbles: true,
        clientX: rect.left + scene.originX + x * scene.ppu,
        clientY: rect.top + scene.originY - z * scene.ppu,
      }),
    );
  }

  elapsed() {
    return (performance.now() - this.decision.start) / 1000;
  }

  showTimeLeft() {
    const left = Math.max(0, this.decision.allowed - this.elapsed());
    this.timerText.textContent = `Time left: ${left.toFixed(1)} s`;
    this.timerText.dataset.seconds = left.toFixed(1);
    this.timerText.classList.toggle("ot-urgent", left <= 1.5);
  }

  sampleMouse() {
    const { decision, pointer } = this;
    if (!decision || !pointer) return;
    const t = round(this.elapsed());
    const last = decision.trajectory.at(-1);
    if (last && t <= last[0]) return;
    decision.trajectory.push([t, round(pointer.x), round(pointer.z)]);
  }

  onPointerMove(event) {
    this.pointer = this.scene.toTask(event);
    if (this.state !== "deciding") return;
    this.updateGhost();
    this.render();
  }

  onPointerLeave() {
    this.pointer = null;
    if (this.state !== "deciding") return;
    this.updateGhost();
    this.render();
  }

  /** The preview for the current pointer: x clamped into the grid, the layer under the pointer. */
  ghostAt(point) {
    const { grid } = this;
    const width = this.sequence[this.step];
    const position = previewPosition(point, width, grid);
    if (!position) return null;
    const { x, layer } = position;
    const reason = illegalReason(this.tower, width, x, layer, grid);
    return { width, x, layer, legal: reason === null, reason };
  }

  updateGhost() {
    this.ghost = this.ghostAt(this.pointer);
    this.trackDwell(this.ghost ? `${round(this.ghost.x, 1)}|${this.ghost.layer}` : null);
    if (this.ghost?.legal) this.message.textContent = "";
  }

  trackDwell(key) {
    const { decision } = this;
    if (!decision || key === decision.dwellKey) return;
    const now = performance.now();
    if (decision.dwellKey !== null) {
      const seconds = (now - decision.dwellSince) / 1000;
      decision.dwell.set(decision.dwellKey, (decision.dwell.get(decision.dwellKey) ?? 0) + seconds);
    }
    decision.dwellKey = key;
    decision.dwellSince = now;
  }

  /** Closes the decision: stops its timers and returns its trajectory, dwell times and duration. */
  endDecision() {
    const { decision } = this;
    const decisionTime = this.elapsed();
    this.sampleMouse();
    this.trackDwell(null);
    for (const id of [decision.sampler, decision.countdown, decision.deadline]) {
      if (id !== undefined) this.stopTimer(id);
    }
    this.decision = null;
    const dwell = [...decision.dwell].map(([key, seconds]) => {
      const [x, layer] = key.split("|");
      return [Number(x), Number(layer), round(seconds)];
    });
    return { decisionTime, trajectory: decision.trajectory, dwell };
  }

  onClick(event) {
    if (this.state !== "deciding") return;
    this.pointer = this.scene.toTask(event);
    this.updateGhost();
    this.render();
    const ghost = this.ghost;
    if (!ghost) return;
    if (!ghost.legal) {
      this.message.textContent = ghost.reason;
      this.message.classList.add("ot-warning");
      return;
    }
    this.message.classList.remove("ot-warning");
    const allowed = this.decision.allowed;
    if (allowed != null && this.elapsed() >= allowed) {
      this.timeOut();
      return;
    }
    const { decisionTime, trajectory, dwell } = this.endDecision();
    this.submit({
      step: this.step, x: ghost.x, layer: ghost.layer, timed_out: false,
      decision_time: round(decisionTime), trajectory, dwell,
    });
  }

  timeOut() {
    if (this.state !== "deciding") return;
    const { decisionTime, trajectory, dwell } = this.endDecision();
    this.timerText.textContent = "Time left: 0.0 s";
    this.timerText.dataset.seconds = "0.0";
    this.submit({
      step: this.step, x: null, layer: null, timed_out: true,
      decision_time: round(decisionTime), trajectory, dwell,
    });
  }

  // ---- after a decision ----------------------------------------------------------------------

  async submit(payload) {
    this.setState("waiting");
    this.actions.replaceChildren();
    this.message.classList.remove("ot-warning");
    this.message.textContent = payload.timed_out ? "Time is up." : "";
    this.render();
    let outcome;
    try {
      outcome = await this.params.place(payload);
    } catch (error) {
      this.showError(error, () => this.submit(payload));
      return;
    }
    await this.applyOutcome(payload, outcome);
  }

  showError(error, retry) {
    this.setState("error");
    this.message.replaceChildren();
    const text = document.createElement("span");
    text.className = "ot-error";
    text.dataset.testid = "error";
    text.textContent = error?.message || String(error);
    this.message.append(text);
    this.addButton("Try again", "retry", retry);
  }

  async applyOutcome(sent, outcome) {
    const { payload, placed, stands, trialOver } = this.record.add(sent, outcome);
    if (!payload.timed_out) this.placedCount += 1;
    const { frames } = outcome;
    const poses = frames?.poses ?? [];
    const asBlocks = (frame) => framePoses(placed, frame);

    if (poses.length > 1) {
      this.setState("animating");
      await this.animate(poses.map(asBlocks), frames.fps || 30);
    }
    if (stands) {
      this.record.keep(placed);
      this.shownPoses = null;
    } else if (poses.length) {
      this.shownPoses = asBlocks(poses.at(-1));
    }

    this.updateScores(outcome.overhang ?? overhang(this.tower), trialOver ? outcome.reward ?? 0 : null);
    if (trialOver) {
      this.finishTask(payload, outcome);
    } else {
      this.step += 1;
      this.beginDecision();
    }
  }

  animate(frames, fps) {
    const rate = fps * Math.max(1e-6, this.params.animation_speed);
    return new Promise((resolve) => {
      const begin = performance.now();
      const tick = (now) => {
        const index = Math.min(frames.length - 1, Math.floor(((now - begin) / 1000) * rate));
        this.shownPoses = frames[index];
        this.render();
        if (index >= frames.length - 1) {
          this.frameRequest = null;
          resolve();
        } else {
          this.frameRequest = requestAnimationFrame(tick);
        }
      };
      this.frameRequest = requestAnimationFrame(tick);
    });
  }

  finishTask(payload, outcome) {
    this.setState("done");
    this.render();
    const reward = outcome.reward ?? 0;
    const digits = this.params.precision;
    if (payload.timed_out) {
      this.message.textContent = "Time is up: this trial ends with a reward of 0.";
    } else if (!outcome.stable) {
      this.message.textContent = "The tower fell: this trial ends with a reward of 0.";
    } else {
      this.message.textContent = this.params.show_reward
        ? `The tower stands. Reward for this trial: ${reward.toFixed(digits)}.`
        : "The tower stands.";
    }
    this.message.classList.toggle("ot-bad", Boolean(payload.timed_out || !outcome.stable));
    this.stepText.textContent = "Trial over";
    this.timerText.hidden = true;
    const button = this.addButton(this.params.continue_label, "continue", () => this.end(outcome));
    if (this.participant) this.later(() => button.click(), this.participant.readingTime() * 1000);
  }

  addButton(label, testid, onClick) {
    const button = document.createElement("button");
    button.className = "jspsych-btn";
    button.type = "button";
    button.dataset.testid = testid;
    button.textContent = label;
    button.addEventListener("click", () => {
      button.disabled = true;
      onClick();
    });
    this.actions.replaceChildren(button);
    button.focus();
    return button;
  }

  end(outcome) {
    this.cleanUp();
    this.jsPsych.finishTrial(this.record.data(outcome, this.grid, this.shownPoses));
  }

  cleanUp() {
    for (const id of this.timers) {
      clearTimeout(id);
      clearInterval(id);
    }
    this.timers.clear();
    if (this.frameRequest !== null) cancelAnimationFrame(this.frameRequest);
    for (const remove of this.listeners ?? []) remove();
  }
}

export default OverhangTowerPlugin;
