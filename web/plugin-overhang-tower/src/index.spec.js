import { afterEach, describe, expect, jest, test } from "@jest/globals";
import { clickTarget, dispatchEvent, flushPromises, simulateTimeline, startTimeline } from "@jspsych/test-utils";
import { initJsPsych } from "jspsych";

import OverhangTowerPlugin, { choosePlacement, illegalReason, overhang } from "./index.js";

const SEQUENCE = [1.8, 1.2, 0.6];
const GRID = { half_width: 4, height: 8, block_height: 0.6, max_layer: 12 };

/**
 * A stand-in for the server's physics, enough to drive the plugin: a tower stands while its overhang
 * is at most `reach`; a tower that falls is answered with three frames in which its last block drops
 * to the ground. Every outcome has the fields `place` documents.
 */
function physics({ sequence = SEQUENCE, tower = [[sequence[0], 0, 0]], reach = 2 } = {}) {
  let standing = tower.map((block) => [...block]);
  const place = jest.fn(async (payload) => {
    if (payload.timed_out) {
      return { stable: true, overhang: overhang(standing), reward: 0, trial_over: true, frames: { fps: 30, poses: [] } };
    }
    const placed = [...standing, [sequence[payload.step], payload.x, payload.layer]];
    const rest = placed.map(([, x, layer]) => [x, (layer + 0.5) * 0.6, 0]);
    const stable = overhang(placed) <= reach;
    const last = payload.step === sequence.length - 1;
    if (!stable) {
      const fall = [0, 1, 2].map((f) => rest.map((pose, i) => (i === rest.length - 1 ? [pose[0] + f, pose[1] - f * 0.2, f * 0.5] : pose)));
      return { stable, overhang: overhang(standing), reward: 0, trial_over: true, frames: { fps: 30, poses: fall } };
    }
    standing = placed;
    return {
      stable,
      overhang: overhang(placed),
      reward: last ? overhang(placed) : null,
      trial_over: last,
      frames: { fps: 30, poses: [rest] },
    };
  });
  return place;
}

const canvasOf = (displayElement) => displayElement.querySelector('[data-testid="overhang-canvas"]');
const stateOf = (displayElement) => displayElement.querySelector(".overhang-tower").dataset.state;
const byTestId = (displayElement, id) => displayElement.querySelector(`[data-testid="${id}"]`);

/** Moves the pointer to where a block at (x, layer) goes, as the README says a test should. */
async function pointTo(displayElement, x, layer, type = "pointermove") {
  const canvas = canvasOf(displayElement);
  const rect = canvas.getBoundingClientRect();
  const { pxPerUnit, originX, originY, blockHeight } = canvas.dataset;
  await dispatchEvent(
    new MouseEvent(type, {
      bubbles: true,
      clientX: rect.left + Number(originX) + x * Number(pxPerUnit),
      clientY: rect.top + Number(originY) - (layer + 0.5) * Number(blockHeight) * Number(pxPerUnit),
    }),
    canvas,
  );
}

async function placeAt(displayElement, x, layer) {
  await pointTo(displayElement, x, layer);
  await pointTo(displayElement, x, layer, "click");
  await flushPromises();
}

/** Blocks `[width, x, z, angle]`, equal up to rounding. */
function expectPoses(received, expected) {
  expect(received).toHaveLength(expected.length);
  received.forEach((block, i) => block.forEach((value, j) => expect(value).toBeCloseTo(expected[i][j], 9)));
}

/** Every placement that was not a timeout is legal on the tower it was placed on. */
function expectLegalPlacements(data, grid = GRID) {
  let tower = data.start_tower.map((block) => [...block]);
  data.placements.forEach((payload, i) => {
    if (payload.timed_out) return;
    const width = data.sequence[payload.step];
    expect(illegalReason(tower, width, payload.x, payload.layer, grid)).toBeNull();
    if (data.outcomes[i].stable) tower = [...tower, [width, payload.x, payload.layer]];
  });
  expect(data.final_tower).toEqual(tower);
}

afterEach(() => {
  jest.useRealTimers();
});

describe("overhang-tower", () => {
  test("renders the task: the canvas, the step, the tower and the prompt", async () => {
    const place = physics();
    const { displayElement } = await startTimeline([
      { type: OverhangTowerPlugin, sequence: SEQUENCE, place, prompt: "<p id='p'>Build out</p>", pixels_per_unit: 40 },
    ]);
    expect(stateOf(displayElement)).toBe("deciding");
    expect(canvasOf(displayElement).dataset.pxPerUnit).toBe("40");
    expect(displayElement.querySelector("#p").textContent).toBe("Build out");
    expect(byTestId(displayElement, "step").textContent).toBe("Block 2 of 3");
    expect(JSON.parse(displayElement.querySelector(".overhang-tower").dataset.tower)).toEqual([[1.8, 0, 0]]);
    expect(byTestId(displayElement, "timer").hidden).toBe(true);
    expect(byTestId(displayElement, "overhang").dataset.value).toBe("0.9");
    expect(place).not.toHaveBeenCalled();
  });

  test("an illegal click is refused with its reason and nothing is sent", async () => {
    const place = physics();
    const { displayElement, expectRunning } = await startTimeline([{ type: OverhangTowerPlugin, sequence: SEQUENCE, place }]);
    await placeAt(displayElement, 2, 1); // no support under x = 2 in layer 0
    expect(byTestId(displayElement, "message").textContent).toBe("The block must rest on a block in the layer below.");
    await placeAt(displayElement, 0, 3); // floating two layers above the tower
    expect(place).not.toHaveBeenCalled();
    expect(stateOf(displayElement)).toBe("deciding");
    await expectRunning();
  });

  test("placements through the canvas end the trial with the documented data", async () => {
    const place = physics();
    const { displayElement, getData, expectFinished } = await startTimeline([
      { type: OverhangTowerPlugin, sequence: SEQUENCE, place, precision: 1, continue_label: "Next" },
    ]);
    await placeAt(displayElement, 0.5, 1);
    expect(place).toHaveBeenCalledTimes(1);
    expect(place.mock.calls[0][0]).toMatchObject({ step: 1, x: 0.5, layer: 1, timed_out: false });
    expect(stateOf(displayElement)).toBe("deciding");
    expect(byTestId(displayElement, "step").textContent).toBe("Block 3 of 3");

    await placeAt(displayElement, 0.9, 2);
    expect(stateOf(displayElement)).toBe("done");
    expect(byTestId(displayElement, "reward").textContent).toBe("Reward: 1.2");
    const button = byTestId(displayElement, "continue");
    expect(button.textContent).toBe("Next");
    await clickTarget(button);
    await expectFinished();

    const data = getData().values()[0];
    expect(data.sequence).toEqual(SEQUENCE);
    expect(data.start_step).toBe(1);
    expect(data.start_tower).toEqual([[1.8, 0, 0]]);
    expect(data.placements).toHaveLength(2);
    expect(data.placements.map(({ x, layer }) => [x, layer])).toEqual([[0.5, 1], [0.9, 2]]);
    for (const payload of data.placements) {
      expect(payload.decision_time).toBeGreaterThanOrEqual(0);
      expect(Array.isArray(payload.trajectory)).toBe(true);
      expect(Array.isArray(payload.dwell)).toBe(true);
    }
    expect(data.outcomes.map((o) => o.frame_count)).toEqual([1, 1]);
    expect(data.outcomes[0]).not.toHaveProperty("frames");
    expect(data.final_tower).toEqual([[1.8, 0, 0], [1.2, 0.5, 1], [0.6, 0.9, 2]]);
    expectPoses(data.final_poses, [[1.8, 0, 0.3, 0], [1.2, 0.5, 0.9, 0], [0.6, 0.9, 1.5, 0]]);
    expect(data.reward).toBeCloseTo(1.2);
    expect(data.overhang).toBeCloseTo(1.2);
    expect(data.stable).toBe(true);
    expect(data.timed_out).toBe(false);
  });

  test("the time limit ends the trial with a timeout", async () => {
    jest.useFakeTimers();
    const place = physics();
    const { displayElement, getData, expectFinished } = await startTimeline([
      { type: OverhangTowerPlugin, sequence: SEQUENCE, place, time_limit: 2 },
    ]);
    const timer = byTestId(displayElement, "timer");
    expect(timer.hidden).toBe(false);
    await pointTo(displayElement, 0.4, 1);
    jest.advanceTimersByTime(1500);
    expect(Number(timer.dataset.seconds)).toBeCloseTo(0.5, 1);
    expect(place).not.toHaveBeenCalled();
    jest.advanceTimersByTime(600);
    await flushPromises();
    expect(place).toHaveBeenCalledTimes(1);
    const payload = place.mock.calls[0][0];
    expect(payload).toMatchObject({ step: 1, x: null, layer: null, timed_out: true });
    expect(payload.decision_time).toBeCloseTo(2, 1);
    expect(payload.dwell).toEqual([[0.4, 1, 2]]);
    expect(stateOf(displayElement)).toBe("done");
    expect(byTestId(displayElement, "message").textContent).toMatch(/Time is up/);
    await clickTarget(byTestId(displayElement, "continue"));
    await expectFinished();
    const data = getData().values()[0];
    expect(data).toMatchObject({ timed_out: true, stable: false, reward: 0, final_tower: [[1.8, 0, 0]] });
  });

  test("the mouse is sampled at mouse_hz while a decision lasts", async () => {
    jest.useFakeTimers();
    const place = physics();
    const { displayElement } = await startTimeline([{ type: OverhangTowerPlugin, sequence: SEQUENCE, place, mouse_hz: 10 }]);
    await pointTo(displayElement, -0.5, 1);
    jest.advanceTimersByTime(1000);
    await pointTo(displayElement, 0.5, 1);
    jest.advanceTimersByTime(50);
    await placeAt(displayElement, 0.5, 1);
    const { trajectory, decision_time } = place.mock.calls[0][0];
    expect(trajectory.length).toBeGreaterThanOrEqual(11);
    expect(trajectory.length).toBeLessThanOrEqual(13);
    expect(trajectory[0].slice(1)).toEqual([-0.5, 0.9]);
    expect(trajectory.at(-1).slice(1)).toEqual([0.5, 0.9]);
    expect(decision_time).toBeCloseTo(1.05, 2);
  });

  test("a tower that falls is animated and ends the trial with its last frame", async () => {
    jest.useFakeTimers();
    const place = physics({ reach: 1.0 });
    const { displayElement, getData, expectFinished } = await startTimeline([
      { type: OverhangTowerPlugin, sequence: SEQUENCE, place, animation_speed: 2 },
    ]);
    await placeAt(displayElement, 0.9, 1);
    expect(stateOf(displayElement)).toBe("animating");
    jest.advanceTimersByTime(200);
    await flushPromises();
    expect(stateOf(displayElement)).toBe("done");
    expect(byTestId(displayElement, "message").textContent).toMatch(/fell/);
    await clickTarget(byTestId(displayElement, "continue"));
    await expectFinished();
    const data = getData().values()[0];
    expect(data.stable).toBe(false);
    expect(data.reward).toBe(0);
    expect(data.outcomes[0].frame_count).toBe(3);
    expect(data.final_tower).toEqual([[1.8, 0, 0]]);
    expectPoses(data.final_poses, [[1.8, 0, 0.3, 0], [1.2, 2.9, 0.5, 1]]);
  });

  test("a placement the server calls late is kept as a late timeout", async () => {
    const place = jest.fn(async () => ({ stable: true, overhang: 0.9, reward: 0, trial_over: true, timed_out: true }));
    const { displayElement, getData } = await startTimeline([{ type: OverhangTowerPlugin, sequence: SEQUENCE, place }]);
    await placeAt(displayElement, 0.2, 1);
    await clickTarget(byTestId(displayElement, "continue"));
    const data = getData().values()[0];
    expect(data.placements[0]).toMatchObject({ x: null, layer: null, timed_out: true, late: true });
    expect(data.timed_out).toBe(true);
    expect(data.final_tower).toEqual([[1.8, 0, 0]]);
  });

  test("a failed placement is shown and sent again by the retry button", async () => {
    const physicsPlace = physics();
    let failures = 1;
    const place = jest.fn(async (payload) => {
      if (failures-- > 0) throw new Error("The server is not reachable.");
      return physicsPlace(payload);
    });
    const { displayElement } = await startTimeline([{ type: OverhangTowerPlugin, sequence: SEQUENCE, place }]);
    await placeAt(displayElement, 0.3, 1);
    expect(stateOf(displayElement)).toBe("error");
    expect(byTestId(displayElement, "error").textContent).toBe("The server is not reachable.");
    await clickTarget(byTestId(displayElement, "retry"));
    expect(place).toHaveBeenCalledTimes(2);
    expect(place.mock.calls[1][0]).toBe(place.mock.calls[0][0]);
    expect(stateOf(displayElement)).toBe("deciding");
    expect(byTestId(displayElement, "step").textContent).toBe("Block 3 of 3");
  });

  test("begin_step gives the blocks and the time left, and a resumed trial starts from its tower", async () => {
    jest.useFakeTimers();
    const tower = [[1.8, 0, 0], [1.2, -0.4, 1]];
    const place = physics({ tower });
    const begin_step = jest.fn(async () => ({ time_left: 0.5, sequence: SEQUENCE }));
    const { displayElement, getData } = await startTimeline([
      { type: OverhangTowerPlugin, sequence: [], tower, step: 2, place, begin_step, time_limit: 5, show_reward: false },
    ]);
    expect(begin_step).toHaveBeenCalledWith({ step: 2 });
    expect(byTestId(displayElement, "step").textContent).toBe("Block 3 of 3");
    expect(JSON.parse(displayElement.querySelector(".overhang-tower").dataset.tower)).toEqual(tower);
    expect(byTestId(displayElement, "overhang").hidden).toBe(true);
    expect(byTestId(displayElement, "reward").hidden).toBe(true);
    jest.advanceTimersByTime(600); // the server's 0.5 s, not time_limit's 5
    await flushPromises();
    expect(place).toHaveBeenCalledTimes(1);
    expect(place.mock.calls[0][0]).toMatchObject({ step: 2, timed_out: true });
    await clickTarget(byTestId(displayElement, "continue"));
    const data = getData().values()[0];
    expect(data).toMatchObject({ start_step: 2, start_tower: tower, sequence: SEQUENCE, final_tower: tower });
  });
});

describe("overhang-tower simulation", () => {
  test("data-only: a simulated participant places legal blocks through place until the trial ends", async () => {
    const sequence = [1.8, 1.2, 0.6, 1.2, 0.6, 1.8];
    initJsPsych().randomization.setSeed("overhang");
    for (let run = 0; run < 20; run += 1) {
      const place = physics({ sequence, reach: 3 });
      const { getData, expectFinished, finished } = await simulateTimeline(
        [{ type: OverhangTowerPlugin, sequence, place, mouse_hz: 20 }],
        "data-only",
        {},
        initJsPsych(),
      );
      await finished;
      await expectFinished();
      const data = getData().values()[0];
      expect(place).toHaveBeenCalledTimes(data.placements.length);
      expect(place.mock.calls.map(([payload]) => payload)).toEqual(data.placements);
      expectLegalPlacements(data);
      const last = data.outcomes.at(-1);
      expect(data.stable).toBe(last.stable);
      expect(data.timed_out).toBe(false);
      expect(data.placements.length === sequence.length - 1 || !data.stable).toBe(true);
      for (const payload of data.placements) {
        expect(payload.decision_time).toBeGreaterThan(0);
        expect(payload.trajectory.at(-1)[0]).toBeCloseTo(payload.decision_time, 3);
        const dwelt = payload.dwell.reduce((sum, [, , seconds]) => sum + seconds, 0);
        expect(dwelt).toBeCloseTo(payload.decision_time, 1);
      }
    }
  });

  test("data-only: planned placements are followed and simulation_options.data overrides the data", async () => {
    const place = physics();
    const { getData, finished } = await simulateTimeline(
      [
        {
          type: OverhangTowerPlugin,
          sequence: SEQUENCE,
          place,
          time_limit: 4,
          simulation_options: { data: { placements: [{ x: -0.6, layer: 1, decision_time: 1.25 }, { timed_out: true }], rt: 99 } },
        },
      ],
      "data-only",
    );
    await finished;
    expect(place.mock.calls.map(([p]) => [p.x, p.layer, p.timed_out])).toEqual([[-0.6, 1, false], [null, null, true]]);
    expect(place.mock.calls[0][0].decision_time).toBe(1.25);
    expect(place.mock.calls[1][0].decision_time).toBe(4);
    const data = getData().values()[0];
    expect(data.rt).toBe(99);
    expect(data.placements).toEqual(place.mock.calls.map(([p]) => p));
    expect(data.timed_out).toBe(true);
    expect(data.final_tower).toEqual([[1.8, 0, 0], [1.2, -0.6, 1]]);
  });

  test("data-only: an illegal planned placement is refused with its reason", async () => {
    const jsPsych = initJsPsych();
    const run = jsPsych.simulate(
      [{ type: OverhangTowerPlugin, sequence: SEQUENCE, place: physics(), simulation_options: { data: { placements: [{ x: 3, layer: 1 }] } } }],
      "data-only",
    );
    await expect(run).rejects.toThrow(/placements\[0\].*must rest on a block/);
  });

  test("visual: an illegal planned placement is refused with its reason", async () => {
    const run = initJsPsych().simulate(
      [{ type: OverhangTowerPlugin, sequence: SEQUENCE, place: physics(), simulation_options: { data: { placements: [{ x: 0, layer: 2 }] } } }],
      "visual",
    );
    await expect(run).rejects.toThrow(/placements\[0\].*must rest on a block/);
  });

  test("data-only: begin_step's clock is honoured", async () => {
    const place = physics();
    const begin_step = jest.fn(async () => ({ time_left: 0.001, sequence: SEQUENCE }));
    const { getData, finished } = await simulateTimeline(
      [{ type: OverhangTowerPlugin, sequence: [], place, begin_step, time_limit: 5 }],
      "data-only",
    );
    await finished;
    expect(begin_step).toHaveBeenCalledWith({ step: 1 });
    const data = getData().values()[0];
    expect(data.placements).toEqual([expect.objectContaining({ timed_out: true, decision_time: 0.001 })]);
    expect(data.start_tower).toEqual([[1.8, 0, 0]]);
  });

  test("visual: the simulated participant plays the trial on the page with the pointer", async () => {
    jest.useFakeTimers();
    const place = physics({ reach: 3 });
    const jsPsych = initJsPsych();
    jsPsych.randomization.setSeed("visual");
    const { displayElement, getData, expectFinished } = await simulateTimeline(
      [{ type: OverhangTowerPlugin, sequence: SEQUENCE, place, simulation_options: { data: { placements: [{ x: 0.7, layer: 1 }] } } }],
      "visual",
      {},
      jsPsych,
    );
    expect(stateOf(displayElement)).toBe("deciding");
    for (let i = 0; i < 600 && place.mock.calls.length < 1; i += 1) {
      jest.advanceTimersByTime(50);
      await flushPromises();
    }
    expect(place.mock.calls[0][0]).toMatchObject({ step: 1, x: 0.7, layer: 1, timed_out: false });
    expect(place.mock.calls[0][0].trajectory.length).toBeGreaterThan(2);
    for (let i = 0; i < 600 && !getData().count(); i += 1) {
      jest.advanceTimersByTime(50);
      await flushPromises();
    }
    await expectFinished();
    const data = getData().values()[0];
    expect(data.placements).toEqual(place.mock.calls.map(([p]) => p));
    expectLegalPlacements(data);
  });

  test("choosePlacement finds the one gap left in a full layer, and reports none when there is none", () => {
    const grid = { ...GRID, max_layer: 1 };
    const tower = [[1.8, 0, 0], [0.6, -0.6, 1], [0.6, 0.6, 1]];
    expect(choosePlacement(tower, 0.6, grid)).toEqual({ x: 0, layer: 1 });
    expect(choosePlacement(tower, 1.2, grid)).toBeNull();
  });
});
