/**
 * A trial without a person, for `jsPsych.simulate()`: a simulated participant who places each block
 * legally (by the rules in geometry.js) after an ex-Gaussian decision time, and the data-only run of
 * a trial, which sends its placements to `place` as the page would.
 */

import { DEFAULT_GRID, illegalReason, previewPosition } from "./geometry.js";
import { TrialRecord, framePoses } from "./record.js";

const round = (value, digits = 3) => Math.round(value * 10 ** digits) / 10 ** digits + 0;

/**
 * A legal position `{x, layer}` for a block of `width` on `tower`, or null when there is none: the
 * block's centre over a block of the layer below, on top of the tower if it can go there, else in a
 * lower layer. `random()` returns numbers in [0, 1).
 */
export function choosePlacement(tower, width, grid = DEFAULT_GRID, random = Math.random) {
  const top = tower.reduce((highest, [, , layer]) => Math.max(highest, layer), -1);
  const limit = grid.half_width - width / 2;
  const layers = [top + 1];
  for (let layer = top; layer >= 1; layer -= 1) layers.push(layer);
  for (const layer of layers) {
    if (layer > grid.max_layer) continue;
    const supports = tower.filter(([, , l]) => l === layer - 1);
    if (!supports.length) continue;
    for (let attempt = 0; attempt < 20; attempt += 1) {
      const [w, bx] = supports[Math.floor(random() * supports.length)];
      const x = round(Math.min(limit, Math.max(-limit, bx + (2 * random() - 1) * (w / 2))));
      if (illegalReason(tower, width, x, layer, grid) === null) return { x, layer };
    }
  }
  // Every layer, left to right: the block fits only in a narrow gap, if anywhere.
  for (let layer = 1; layer <= Math.min(grid.max_layer, top + 1); layer += 1) {
    for (let x = -limit; x <= limit + 1e-9; x += 0.01) {
      if (illegalReason(tower, width, round(x), layer, grid) === null) return { x: round(x), layer };
    }
  }
  return null;
}

/**
 * The simulated participant. `planned` (`simulation_options.data.placements`) are the first
 * decisions, in turn: `{x, layer}` or `{timed_out: true}`, each with an optional `decision_time`
 * in seconds. Afterwards it chooses by itself; its decision times are ex-Gaussian (about 2.3 s on
 * average), and one that exceeds the time allowed is a timeout.
 */
export class SimulatedParticipant {
  constructor(jsPsych, planned = null) {
    this.jsPsych = jsPsych;
    this.planned = Array.isArray(planned) ? planned : [];
    this.count = 0;
  }

  seconds(mean, sd, tau) {
    return this.jsPsych.randomization.sampleExGaussian(mean * 1000, sd * 1000, 1 / (tau * 1000), true) / 1000;
  }

  /**
   * The next decision on `tower` for a block of `width` with `allowed` seconds (null: no limit):
   * `{timed_out: false, x, layer, decision_time}` or `{timed_out: true, decision_time}`.
   */
  decide({ tower, width, grid = DEFAULT_GRID, allowed = null }) {
    const index = this.count;
    this.count += 1;
    const plan = this.planned[index];
    if (plan) {
      if (plan.timed_out) {
        return { timed_out: true, decision_time: plan.decision_time ?? allowed ?? this.seconds(1.5, 0.4, 0.8) };
      }
      const reason = illegalReason(tower, width, plan.x, plan.layer, grid);
      if (reason !== null) {
        throw new Error(
          `overhang-tower: simulation_options.data.placements[${index}] = ${JSON.stringify(plan)} is not legal: ${reason}`,
        );
      }
      return { timed_out: false, x: plan.x, layer: plan.layer, decision_time: plan.decision_time ?? this.seconds(1.5, 0.4, 0.8) };
    }
    const time = this.seconds(1.5, 0.4, 0.8);
    const spot = choosePlacement(tower, width, grid);
    if (!spot || (allowed != null && time >= allowed)) {
      return { timed_out: true, decision_time: allowed ?? time };
    }
    return { timed_out: false, ...spot, decision_time: time };
  }

  /** Where the pointer enters the grid: near its top, somewhere over its middle half. */
  startPoint(grid = DEFAULT_GRID) {
    return { x: round((Math.random() - 0.5) * grid.half_width), z: grid.height - grid.block_height / 2 };
  }

  /** Seconds spent reading the trial's end before pressing the continue button. */
  readingTime() {
    return this.seconds(0.6, 0.2, 0.4);
  }

  /**
   * The pointer's path for `choice` as the page records it: `trajectory` ([t, x, z] at `hz`, a
   * straight move from the start point to the block's position over 60% of the decision time, then
   * still) and `dwell` ([x rounded to 0.1, layer, seconds] per preview position).
   */
  pointerPath(choice, width, grid = DEFAULT_GRID, hz = 30) {
    const start = this.startPoint(grid);
    const aim = choice.timed_out ? start : { x: choice.x, z: (choice.layer + 0.5) * grid.block_height };
    const total = choice.decision_time;
    const times = [];
    for (let k = 0; k / Math.max(1, hz) < total; k += 1) times.push(k / Math.max(1, hz));
    times.push(total);
    const at = (t) => {
      const f = Math.min(1, t / (0.6 * total || 1));
      return { x: start.x + f * (aim.x - start.x), z: start.z + f * (aim.z - start.z) };
    };
    const trajectory = times.map((t) => {
      const p = at(t);
      return [round(t), round(p.x), round(p.z)];
    });
    const dwell = new Map();
    for (let i = 0; i + 1 < times.length; i += 1) {
      const preview = previewPosition(at(times[i]), width, grid);
      if (!preview) continue;
      const key = `${round(preview.x, 1)}|${preview.layer}`;
      dwell.set(key, (dwell.get(key) ?? 0) + times[i + 1] - times[i]);
    }
    return {
      trajectory,
      dwell: [...dwell].map(([key, seconds]) => {
        const [x, layer] = key.split("|");
        return [Number(x), Number(layer), round(seconds)];
      }),
    };
  }
}

/**
 * A trial's data with nobody at the page: each decision of `participant` goes to `trial.place`
 * (after `trial.begin_step`, when given, as on the page) until an outcome ends the trial.
 */
export async function simulateData(trial, participant) {
  const grid = { ...DEFAULT_GRID, ...trial.grid };
  const record = new TrialRecord(trial);
  for (let step = trial.step; ; step += 1) {
    let allowed = trial.time_limit;
    if (trial.begin_step) {
      const clock = await trial.begin_step({ step });
      if (Array.isArray(clock?.sequence)) record.setSequence(clock.sequence);
      if (allowed != null && typeof clock?.time_left === "number") allowed = clock.time_left;
    }
    if (!record.sequence) {
      throw new Error("overhang-tower: the trial has no blocks: give `sequence`, or a `begin_step` that returns them");
    }
    if (step >= record.sequence.length) {
      throw new Error(`overhang-tower: \`place\` did not end the trial after its last block (step ${step - 1})`);
    }
    const width = record.sequence[step];
    const choice = participant.decide({ tower: record.tower, width, grid, allowed });
    const payload = {
      step,
      x: choice.timed_out ? null : choice.x,
      layer: choice.timed_out ? null : choice.layer,
      timed_out: choice.timed_out,
      decision_time: round(choice.decision_time),
      ...participant.pointerPath(choice, width, grid, trial.mouse_hz),
    };
    const outcome = await trial.place(payload);
    const { placed, stands, trialOver } = record.add(payload, outcome);
    if (stands) record.keep(placed);
    if (trialOver) {
      const frames = outcome.frames?.poses ?? [];
      return record.data(outcome, grid, !stands && frames.length ? framePoses(placed, frames.at(-1)) : null);
    }
  }
}
