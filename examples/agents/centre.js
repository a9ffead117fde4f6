#!/usr/bin/env node
// An Overhang Tower agent in JavaScript (Node.js), speaking the benchmark's JSON Lines protocol.
//
// It reads one JSON object per line from stdin. For each "decision" it answers one line,
// {"x": ..., "layer": ...}: the legal placement on the highest layer whose centre is nearest the
// centre of the block below it, shifted one grid step outward where it can be (a cautious tower).
// "end" messages say how the episode went; nothing is answered.
//
//   python -m overhang_framework.benchmark split=cross agent=command 'agent.command=[node,examples/agents/centre.js]'
"use strict";
const readline = require("readline");

function choose(message) {
  const legal = message.legal; // [[x, layer], ...]
  const tower = message.tower; // [[width, x, layer], ...]
  const top = Math.max(...legal.map(([, layer]) => layer));
  const below = tower.filter(([, , layer]) => layer === top - 1);
  const distance = (x) => Math.min(...below.map(([, bx]) => Math.abs(x - bx)));
  const candidates = legal.filter(([, layer]) => layer === top);
  candidates.sort((a, b) => distance(a[0]) - distance(b[0]) || Math.abs(b[0]) - Math.abs(a[0]) || b[0] - a[0]);
  const [x, layer] = candidates[0];
  return { x, layer };
}

const lines = readline.createInterface({ input: process.stdin });
lines.on("line", (line) => {
  const message = JSON.parse(line);
  if (message.type === "decision") {
    process.stdout.write(JSON.stringify(choose(message)) + "\n");
  }
});
