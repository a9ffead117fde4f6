"""Speed of the CNN predictor, rendering included: ``python -m overhang_framework.cnn.bench``.

Prints, for each thread count and batch size, the towers and images per
second of :meth:`StabilityModel.probabilities` (render + forward pass, no
cache) on random towers, and of ``predictor=cnn`` scoring every legal action
of episode-like states (as a planner calls it, cache off). With mirror
averaging (``--mirror auto``, the predictor's default, for the shipped model)
a tower is two images. The last line is one JSON object with every figure.

    python -m overhang_framework.cnn.bench                 # threads 1 and 2
    python -m overhang_framework.cnn.bench --threads 1 --batches 64,512
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def main(argv=None) -> dict:
    import torch

    from overhang_framework.bench.towers import random_towers
    from overhang_framework.cnn.model import StabilityModel, parse_mirror
    from overhang_framework.interfaces import State
    from overhang_framework.plugins import Registry
    from overhang_framework.rules import legal_actions

    ap = argparse.ArgumentParser(prog="python -m overhang_framework.cnn.bench", description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", default="default")
    ap.add_argument("--threads", default="1,2", help="comma-separated torch thread counts (default 1,2)")
    ap.add_argument("--batches", default="70,512", help="comma-separated batch sizes (default 70,512)")
    ap.add_argument("--images", type=int, default=3000, help="towers per measurement (default 3000)")
    ap.add_argument("--mirror", default="auto", choices=["auto", "true", "false"],
                    help="mirror averaging, as predictor=cnn's mirror (default auto)")
    args = ap.parse_args(argv)
    threads = [int(t) for t in args.threads.split(",")]
    batches = [int(b) for b in args.batches.split(",")]
    towers = random_towers(args.images, seed=11)
    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    states = [State(g, (1.2,)) for g in random_towers(40, seed=12, min_blocks=2, max_blocks=6)]
    mirror = parse_mirror(args.mirror)
    results = {"towers": args.images, "render_and_forward": {}, "predict_legal_actions": {}}
    for t in threads:
        torch.set_num_threads(t)
        for b in batches:
            model = StabilityModel(args.checkpoint, device="cpu", batch_size=b, mirror=mirror)
            k = model.images_per_tower
            results["mirror"] = model.mirror
            step = max(1, b // k)  # b images a pass
            chunks = [towers[i:i + step] for i in range(0, len(towers), step)]
            model.probabilities(chunks[0])
            start = time.perf_counter()
            for c in chunks:
                model.probabilities(c)
            rate = len(towers) / (time.perf_counter() - start)
            results["render_and_forward"][f"threads={t},batch={b}"] = {"towers_per_s": rate, "images_per_s": k * rate}
            print(f"threads {t}, batch {b:4d} images: {rate:8.0f} towers/s, {k * rate:8.0f} images/s (render + forward)")
        predictor = Registry().create("predictor", {"name": "cnn", "device": "cpu", "cache_size": 0,
                                                    "checkpoint": args.checkpoint, "mirror": mirror}, world=world)
        calls = [(s, legal_actions(s.geometry, 1.2, 0.1)) for s in states]
        predictor.predict(*calls[0], np.random.default_rng(0))
        start = time.perf_counter()
        n = 0
        for s, actions in calls:
            predictor.predict(s, actions, np.random.default_rng(0))
            n += len(actions)
        seconds = time.perf_counter() - start
        k = predictor.model.images_per_tower
        results["predict_legal_actions"][f"threads={t}"] = {"towers_per_s": n / seconds, "images_per_s": k * n / seconds,
                                                            "actions_per_call": n / len(calls),
                                                            "ms_per_call": 1000 * seconds / len(calls)}
        print(f"threads {t}: predictor=cnn on {len(calls)} states, {n / len(calls):.0f} actions per call: "
              f"{n / seconds:8.0f} towers/s, {k * n / seconds:8.0f} images/s, {1000 * seconds / len(calls):.1f} ms per call")
    print(json.dumps(results))
    return results


if __name__ == "__main__":
    main()
