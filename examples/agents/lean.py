#!/usr/bin/env python3
"""An Overhang Tower agent in plain Python, speaking the benchmark's JSON Lines protocol.

It reads one JSON object per line from stdin. For each "decision" it answers one line,
{"x": ..., "layer": ...}, chosen among the legal placements: the one that reaches furthest out
while its centre stays over the block below it and, for every layer, the centre of mass of all the
blocks from that layer up stays at least MARGIN inside the span of the layer below (a rule of thumb, not physics; the world decides what
stands). "end" messages say how the episode went; nothing is answered.

    python -m overhang_framework.benchmark split=test agent=command 'agent.command=[python,examples/agents/lean.py]'
"""

import json
import sys

MARGIN = 0.2


def balanced(tower):
    """Whether, layer by layer, the blocks above rest their centre of mass inside the layer below."""
    top = max(layer for _, _, layer in tower)
    for layer in range(1, top + 1):
        above = [(w, x) for w, x, l in tower if l >= layer]
        centre = sum(w * x for w, x in above) / sum(w for w, _ in above)
        below = [(w, x) for w, x, l in tower if l == layer - 1]
        left = min(x - w / 2 for w, x in below)
        right = max(x + w / 2 for w, x in below)
        if not left + MARGIN <= centre <= right - MARGIN:
            return False
    return True


def supported(tower, x, layer):
    """Whether a block centred at ``x`` has its centre over a block of the layer below, MARGIN inside."""
    return any(l == layer - 1 and abs(x - bx) <= bw / 2 - MARGIN for bw, bx, l in tower)


def choose(message):
    width, tower, legal = message["width"], message["tower"], message["legal"]
    safe = [(x, layer) for x, layer in legal
            if supported(tower, x, layer) and balanced(tower + [[width, x, layer]])]
    if safe:
        x, layer = max(safe, key=lambda a: (abs(a[0]) + width / 2, -a[1], a[0]))
    else:  # nothing balanced: the most central placement on the highest layer
        top = max(layer for _, layer in legal)
        x, layer = min((a for a in legal if a[1] == top), key=lambda a: (abs(a[0]), a[0]))
    return {"x": x, "layer": layer}


def main():
    for line in sys.stdin:
        message = json.loads(line)
        if message.get("type") == "decision":
            print(json.dumps(choose(message)), flush=True)


if __name__ == "__main__":
    main()
