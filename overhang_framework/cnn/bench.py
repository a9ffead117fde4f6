"""Speed of the CNN predictor, rendering included: ``python -m overhang_framework.cnn.bench``.

Prints, for each thread count and batch size, the towers and images per
second of :meth:`StabilityModel.probabilities` (render + forward pass, no
cache) on random towers, and of ``predictor=cnn`` scoring every legal action
of episode-like states (as a planner calls it, cache off). ``default`` is the
predictor's own setting (``predictor.threads`` in ``conf/predictor/cnn.yaml``).
``--busy N`` keeps N other processes busy for the whole run, each spinning on
a core, as on a shared machine. With mirror averaging (``--mirror auto``, the
predictor's default, for the shipped model) a tower is two images. The last
line is one JSON object with every figure.

    python -m overhang_framework.cnn.bench                 # the default setting, 1 and 2 threads
    python -m overhang_framework.cnn.bench --busy 1        # the same, with another process on one core
    python -m overhang_framework.cnn.bench --threads 1 --batches 64,512
    python -m overhang_framework.cnn.bench --threads 1 --inference unfused   # the network as trained
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing
import time
from typing import Iterator

import numpy as np


#: ``--inference``: the predictor settings of each way to run the network.
INFERENCE = {"onnxruntime": {"fused": True, "runtime": "onnxruntime"}, "torch": {"fused": True, "runtime": "torch"},
             "unfused": {"fused": False}}


def _spin() -> None:
    while True:
        pass


@contextlib.contextmanager
def busy_cores(n: int) -> Iterator[None]:
    """``n`` processes that each keep one core busy until the block ends."""
    procs = [multiprocessing.get_context("spawn").Process(target=_spin, daemon=True) for _ in range(n)]
    for p in procs:
        p.start()
    try:
        yield
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.join()


def thread_settings(text: str) -> list[tuple[str, int]]:
    """``default,1,2`` as (label, torch threads) pairs; ``default`` is predictor=cnn's own setting."""
    import torch

    from overhang_framework.config import compose_config

    settings = []
    for word in text.split(","):
        word = word.strip()
        if word == "default":
            configured = compose_config(["predictor=cnn"]).predictor.get("threads")
            n = int(configured) if configured is not None else torch.get_num_threads()
            settings.append((f"default ({n})", n))
            continue
        try:
            n = int(word)
        except ValueError:
            n = 0
        if n < 1:
            raise SystemExit(f"error: --threads takes 'default' or whole numbers >= 1, got {word!r}")
        settings.append((str(n), n))
    return settings


def main(argv=None) -> dict:
    from overhang_framework.physics.towers import random_towers
    from overhang_framework.cnn.model import parse_mirror
    from overhang_framework.interfaces import State
    from overhang_framework.plugins import Registry

    ap = argparse.ArgumentParser(prog="python -m overhang_framework.cnn.bench", description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", default="default")
    ap.add_argument("--threads", default="default,1,2",
                    help="comma-separated torch thread counts, or default for the predictor's own "
                         "setting (default: default,1,2)")
    ap.add_argument("--busy", type=int, default=0,
                    help="other processes kept busy on a core each during the run (default 0)")
    ap.add_argument("--batches", default="70,512", help="comma-separated batch sizes (default 70,512)")
    ap.add_argument("--images", type=int, default=3000, help="towers per measurement (default 3000)")
    ap.add_argument("--mirror", default="auto", choices=["auto", "true", "false"],
                    help="mirror averaging, as predictor=cnn's mirror (default auto)")
    ap.add_argument("--inference", default="onnxruntime", choices=list(INFERENCE),
                    help="the network folded and run by onnxruntime (the predictor's default) or torch, or "
                         "unfused: as trained, run by torch (default onnxruntime)")
    args = ap.parse_args(argv)
    if args.busy < 0:
        raise SystemExit(f"error: --busy takes a whole number of processes >= 0, got {args.busy}")
    threads = thread_settings(args.threads)
    batches = [int(b) for b in args.batches.split(",")]
    towers = random_towers(args.images, seed=11)
    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    states = [State(g, (1.2,)) for g in random_towers(40, seed=12, min_blocks=2, max_blocks=6)]
    mirror = parse_mirror(args.mirror)
    results = {"towers": args.images, "busy": args.busy, "inference": args.inference, "render_and_forward": {},
               "predict_legal_actions": {}}
    with busy_cores(args.busy):
        if args.busy:
            print(f"{args.busy} other process{'es' if args.busy > 1 else ''} busy on a core each")
        for label, t in threads:
            _measure(args, label, t, towers, world, states, mirror, batches, results)
    print(json.dumps(results))
    return results


def _measure(args, label: str, t: int, towers, world, states, mirror, batches, results) -> None:
    """One thread setting's figures, printed and put into ``results`` under ``threads=<label>``."""
    import torch

    from overhang_framework.cnn.model import StabilityModel
    from overhang_framework.plugins import Registry
    from overhang_framework.rules import legal_actions

    torch.set_num_threads(t)
    for b in batches:
        model = StabilityModel(args.checkpoint, device="cpu", threads=t, batch_size=b, mirror=mirror,
                               **INFERENCE[args.inference])
        k = model.images_per_tower
        results["mirror"] = model.mirror
        step = max(1, b // k)  # b images a pass
        chunks = [towers[i:i + step] for i in range(0, len(towers), step)]
        model.probabilities(chunks[0])
        start = time.perf_counter()
        for c in chunks:
            model.probabilities(c)
        rate = len(towers) / (time.perf_counter() - start)
        results["render_and_forward"][f"threads={label},batch={b}"] = {"towers_per_s": rate, "images_per_s": k * rate}
        print(f"threads {label}, batch {b:4d} images: {rate:8.0f} towers/s, {k * rate:8.0f} images/s "
              f"(render + forward)")
    predictor = Registry().create("predictor", {"name": "cnn", "device": "cpu", "cache_size": 0, "threads": t,
                                                "checkpoint": args.checkpoint, "mirror": mirror,
                                                **INFERENCE[args.inference]}, world=world)
    calls = [(s, legal_actions(s.geometry, 1.2, 0.1)) for s in states]
    predictor.predict(*calls[0], np.random.default_rng(0))
    start = time.perf_counter()
    n = 0
    for s, actions in calls:
        predictor.predict(s, actions, np.random.default_rng(0))
        n += len(actions)
    seconds = time.perf_counter() - start
    k = predictor.model.images_per_tower
    results["predict_legal_actions"][f"threads={label}"] = {"towers_per_s": n / seconds,
                                                            "images_per_s": k * n / seconds,
                                                            "actions_per_call": n / len(calls),
                                                            "ms_per_call": 1000 * seconds / len(calls)}
    print(f"threads {label}: predictor=cnn on {len(calls)} states, {n / len(calls):.0f} actions per call: "
          f"{n / seconds:8.0f} towers/s, {k * n / seconds:8.0f} images/s, {1000 * seconds / len(calls):.1f} ms "
          f"per call")


if __name__ == "__main__":
    main()
