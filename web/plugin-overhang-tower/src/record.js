/**
 * What a trial keeps of its placements and outcomes, and the data it ends with. The trial on the
 * page and its simulation keep the same record, so both produce the same data.
 */

import { groundTower, restingPoses } from "./geometry.js";

/** A frame of poses (`[x, z, angle]` per block) as blocks `[width, x, z, angle]` of `tower`. */
export function framePoses(tower, frame) {
  return frame.slice(0, tower.length).map((pose, i) => [tower[i][0], ...pose]);
}

export class TrialRecord {
  /**
   * `sequence` (null or empty: not known yet), `tower` (null or empty: the ground block alone) and
   * `step`, the trial's parameters.
   */
  constructor({ sequence, tower, step }) {
    this.sequence = null;
    this.tower = (tower ?? []).map((block) => [...block]);
    this.startStep = step;
    this.startTower = [];
    this.placements = [];
    this.outcomes = [];
    if (sequence?.length) this.setSequence(sequence);
  }

  /** The trial's blocks, once known; a trial without a tower starts from the ground block. */
  setSequence(sequence) {
    this.sequence = sequence;
    if (!this.tower.length) this.tower = groundTower(sequence);
    if (!this.placements.length) this.startTower = this.tower.map((block) => [...block]);
  }

  /**
   * Records one placement's payload as sent and `place`'s outcome. A placement that reached the
   * server after its time ran out (`outcome.timed_out`) is recorded as a late timeout. Returns the
   * recorded payload, the tower with the block on it (the tower itself after a timeout) and whether
   * the trial is over. The standing tower changes only with `keep`.
   */
  add(sent, outcome) {
    const payload =
      outcome.timed_out && !sent.timed_out ? { ...sent, x: null, layer: null, timed_out: true, late: true } : sent;
    this.placements.push(payload);
    const { frames, ...rest } = outcome;
    this.outcomes.push({ ...rest, frame_count: frames?.poses?.length ?? 0 });
    const placed = payload.timed_out
      ? this.tower
      : [...this.tower, [this.sequence[payload.step], payload.x, payload.layer]];
    const stands = !payload.timed_out && outcome.stable;
    const trialOver = Boolean(outcome.trial_over || payload.timed_out || !outcome.stable);
    return { payload, placed, stands, trialOver };
  }

  keep(tower) {
    this.tower = tower;
  }

  /** The trial's data once `last` (the last outcome) ended it; `poses` is what was shown last. */
  data(last, grid, poses = null) {
    const lastPayload = this.placements.at(-1);
    return {
      sequence: this.sequence,
      start_step: this.startStep,
      start_tower: this.startTower,
      placements: this.placements,
      outcomes: this.outcomes,
      reward: last.reward ?? 0,
      overhang: last.overhang ?? null,
      stable: this.outcomes.every((o) => o.stable !== false) && !lastPayload.timed_out,
      timed_out: Boolean(lastPayload.timed_out),
      final_tower: this.tower,
      final_poses: poses ?? restingPoses(this.tower, grid).map((pose, i) => [this.tower[i][0], ...pose]),
    };
  }
}
