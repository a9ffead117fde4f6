"""How well the heuristic agrees with a world's physics on seeded random towers.

    python -m overhang_com_margin.accuracy --towers 300 --physics tiered

Two sets of towers of 2 to 7 blocks, both from
:mod:`overhang_framework.bench.towers`, seeded:

* ``--set episode`` (default): episode-like questions, a standing tower plus
  one block at a random legal action, as a planner asks them
  (:func:`~overhang_framework.bench.towers.episode_questions`, ``--towers / 6``
  per block count);
* ``--set random``: random legal towers
  (:func:`~overhang_framework.bench.towers.random_towers`), most of which fall.

The built-in ``overhang`` world with ``--physics`` says whether each stands;
the predictor's probability at ``--scale`` and ``--bias`` is compared with
that. Prints the base rate, the accuracy of the verdict ``p >= 0.5`` beside
that of always guessing the majority verdict, the Brier score, the log loss,
and the predictor's speed.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from overhang_framework.bench.towers import episode_questions, random_towers
from overhang_framework.plugins import Registry

from overhang_com_margin import ComMarginPredictor, com_margins


def tower_margins(towers) -> np.ndarray:
    """The margin of every tower, batched by block count."""
    out = np.empty(len(towers))
    by_size: dict[int, list[int]] = {}
    for i, g in enumerate(towers):
        by_size.setdefault(len(g), []).append(i)
    for idx in by_size.values():
        arr = np.stack([towers[i].as_array() for i in idx])
        out[idx] = com_margins(arr[:, :, 0], arr[:, :, 1], arr[:, :, 2].astype(int))
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m overhang_com_margin.accuracy", description=__doc__.split("\n")[0])
    parser.add_argument("--towers", type=int, default=300, help="number of random towers (default 300)")
    parser.add_argument("--set", choices=("episode", "random"), default="episode", dest="towers_set",
                        help="episode-like questions (default) or random legal towers")
    parser.add_argument("--seed", type=int, default=0, help="seed of the towers (default 0)")
    parser.add_argument("--physics", default="tiered", help="the world's physics: tiered, pybullet or static")
    parser.add_argument("--scale", type=float, default=0.05, help="logistic scale in metres (default 0.05)")
    parser.add_argument("--bias", type=float, default=0.0, help="logit bias (default 0)")
    args = parser.parse_args(argv)

    world = Registry().create("world", {"name": "overhang", "physics": args.physics})
    predictor = ComMarginPredictor(world, scale=args.scale, bias=args.bias)
    start = time.perf_counter()
    if args.towers_set == "random":
        towers = random_towers(args.towers, seed=args.seed)
        truth = np.asarray(world.backend.stable_batch(towers), dtype=bool)
    else:
        questions = episode_questions(world.backend.stable_batch, per_height=max(1, args.towers // 6),
                                      seed=args.seed)
        towers = [q.geometry for q in questions]
        truth = np.array([q.stable for q in questions])
    physics_seconds = time.perf_counter() - start
    start = time.perf_counter()
    p = 0.5 * (1.0 + np.tanh(0.5 * (tower_margins(towers) / args.scale + args.bias)))
    batched_seconds = time.perf_counter() - start
    calls_per_second = None
    if args.towers_set == "episode":  # the same through the Predictor interface, one call per question
        start = time.perf_counter()
        single = np.concatenate([predictor.predict(q.state, [q.action], np.random.default_rng(0))
                                 for q in questions])
        calls_per_second = round(len(questions) / (time.perf_counter() - start))
        np.testing.assert_allclose(single, p, atol=1e-12)
    q = np.clip(p, 1e-6, 1 - 1e-6)
    result = {
        "set": args.towers_set, "towers": len(towers), "physics": args.physics, "seed": args.seed, "scale": args.scale, "bias": args.bias,
        "stable_fraction": round(float(truth.mean()), 4),
        "accuracy": round(float(((p >= 0.5) == truth).mean()), 4),
        "majority_accuracy": round(float(max(truth.mean(), 1 - truth.mean())), 4),
        "brier": round(float(np.mean((p - truth) ** 2)), 4),
        "log_loss": round(float(-np.mean(np.where(truth, np.log(q), np.log(1 - q)))), 4),
        "towers_per_second_batched": round(len(towers) / batched_seconds),
        "calls_per_second_one_action": calls_per_second,
        "physics_seconds": round(physics_seconds, 2),
    }
    label = "episode questions" if args.towers_set == "episode" else "random towers"
    print(f"{len(towers)} {label} (seed {args.seed}), {args.physics} physics: "
          f"{100 * result['stable_fraction']:.1f}% stand")
    print(f"com_margin (scale {args.scale:g}, bias {args.bias:g}): accuracy {100 * result['accuracy']:.1f}% "
          f"(majority guess {100 * result['majority_accuracy']:.1f}%), "
          f"Brier {result['brier']:.3f}, log loss {result['log_loss']:.3f}")
    print(f"speed: {result['towers_per_second_batched']:,} towers/s batched"
          + (f", {calls_per_second:,} one-action predict calls/s" if calls_per_second else ""))
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
