"""Score a CNN checkpoint on a fresh held-out set: ``python -m overhang_framework.cnn.evaluate``.

The held-out set is generated like the training set (:mod:`overhang_framework.cnn.data`,
same settings as the checkpoint's data unless overridden) but with a seed
the training never used (``seed``, default 1000; refused when it equals the
checkpoint's data seed). It is kept in ``data_dir`` so that a rerun scores
the same towers. The accuracy is measured with the checkpoint's own
renderer; ``images_per_s`` times batched inference, rendering included, over
the whole set, on ``threads`` torch threads. ``fused`` and ``runtime`` are
``predictor=cnn``'s: by default the network folded and run by ONNX Runtime;
``fused=false`` scores with the network as trained.

The last line printed is one JSON object with ``accuracy``,
``accuracy_near_critical``, ``n``, ``images_per_s`` and ``towers_per_s`` (and more); it is also
written to ``out`` when given.

Examples::

    python -m overhang_framework.cnn.evaluate
    python -m overhang_framework.cnn.evaluate checkpoint=outputs/cnn/train/regnetx_002-seed0/best.pt n=4000
    python -m overhang_framework.cnn.evaluate fused=false
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from overhang_framework.results import atomic_write_json


def evaluate(checkpoint: str = "default", seed: int = 1000, n: int = 2000, shard_size: int = 500,
             threads: int = 1, device: str = "cpu", workers: int = 2, data_dir: str = "outputs/cnn/heldout",
             batch_size: int = 64, mirror: str = "auto", fused: bool = True, runtime: str = "onnxruntime",
             progress: bool = True) -> dict:
    """Accuracy of ``checkpoint`` on a fresh held-out set of about ``n`` questions, and its speed."""
    import torch

    from overhang_framework.cnn.data import DataSpec, generate, load
    from overhang_framework.cnn.model import StabilityModel, parse_mirror
    from overhang_framework.cnn.train import scores

    for name, value, low in (("n", n, 2), ("shard_size", shard_size, 2), ("threads", threads, 1),
                             ("workers", workers, 1), ("seed", seed, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name} must be a whole number >= {low}, got {value!r}")
    model = StabilityModel(checkpoint, device=device, threads=threads, batch_size=batch_size,
                           mirror=parse_mirror(mirror), fused=fused, runtime=runtime)
    trained = dict(model.info.get("data") or {})
    if trained.get("seed") == seed:
        raise ValueError(f"seed {seed} is the seed of the checkpoint's training data; choose another")
    base = DataSpec(**{k: v for k, v in trained.items() if k in DataSpec.__dataclass_fields__ and k != "shards"})
    spec = replace(base, seed=seed, shards=max(1, -(-n // shard_size)), shard_size=shard_size)
    directory = Path(data_dir) / f"seed{seed}-n{spec.shards * shard_size}"
    generate(spec, directory, workers=workers, progress=progress)
    data = load(directory)
    widths = data["widths"].astype(np.float64)
    layers = data["layers"].astype(np.float64)
    mask = np.arange(widths.shape[1])[None, :] < data["n_blocks"][:, None]
    model.logits_of_arrays(widths[:64], data["xs"][:64], layers[:64], mask[:64])  # warm up
    started = time.perf_counter()
    logits = model.logits_of_arrays(widths, data["xs"], layers, mask)
    seconds = time.perf_counter() - started
    probs = 1.0 / (1.0 + np.exp(-logits.astype(np.float64)))
    result = scores(probs, data)
    crit = data["near_critical"].astype(bool)
    result.update(calibration(probs, data["stable"]))
    result["near_critical"] = calibration(probs[crit], data["stable"][crit])
    by_blocks = {}
    for k in np.unique(data["n_blocks"]):
        rows = data["n_blocks"] == k
        by_blocks[int(k)] = float(((probs[rows] >= 0.5) == data["stable"][rows]).mean())
    result.update({"images_per_s": len(probs) * model.images_per_tower / seconds,
                   "towers_per_s": len(probs) / seconds, "mirror": model.mirror, "fused": model.fused,
                   "runtime": model.runtime, "threads": threads, "device": str(model.device),
                   "torch_threads": torch.get_num_threads(), "accuracy_by_blocks": by_blocks,
                   "checkpoint": str(model.path), "seed": seed, "data_dir": str(directory)})
    return result


def auc(probs: np.ndarray, stable: np.ndarray) -> float:
    """The area under the ROC curve: the chance that a standing tower gets a higher probability than a
    falling one (ties count half); NaN without both kinds."""
    from scipy.stats import rankdata

    y = np.asarray(stable, dtype=bool)
    pos, neg = int(y.sum()), int((~y).sum())
    if not pos or not neg:
        return float("nan")
    ranks = rankdata(np.asarray(probs, dtype=float))
    return float((ranks[y].sum() - pos * (pos + 1) / 2) / (pos * neg))


def calibration(probs: np.ndarray, stable: np.ndarray, bins: int = 10) -> dict:
    """How well the probabilities rank and match the verdicts: ``auc``, the Brier score, and the expected
    calibration error ``ece`` (the mean over ``bins`` equal-width probability bins, weighted by their
    towers, of |mean probability - share standing|)."""
    p = np.asarray(probs, dtype=float)
    y = np.asarray(stable, dtype=bool).astype(float)
    if not len(p):
        return {"auc": float("nan"), "brier": float("nan"), "ece": float("nan")}
    which = np.minimum((p * bins).astype(int), bins - 1)
    ece = sum(abs(p[which == b].mean() - y[which == b].mean()) * (which == b).sum()
              for b in range(bins) if (which == b).any()) / len(p)
    return {"auc": auc(p, y.astype(bool)), "brier": float(np.mean((p - y) ** 2)), "ece": float(ece)}


def main(argv=None) -> None:
    """``key=value`` arguments, as in the other apps; unknown keys are refused."""
    import inspect

    params = inspect.signature(evaluate).parameters
    args = sys.argv[1:] if argv is None else argv
    if any(arg in ("-h", "--help") for arg in args):
        defaults = ", ".join(f"{k}={v.default}" for k, v in params.items())
        print(f"{(__doc__ or '').strip()}\n\nSettings and their defaults: {defaults}, "
              f"out=None (a JSON file for the result).")
        return
    kwargs, out = {}, None
    for arg in args:
        key, sep, value = arg.partition("=")
        if not sep or (key not in params and key != "out"):
            print(f"error: bad argument {arg!r}; use key=value with key one of: "
                  f"{', '.join(list(params) + ['out'])}", file=sys.stderr)
            sys.exit(2)
        if key == "out":
            out = value
            continue
        default = params[key].default
        if isinstance(default, bool):
            kwargs[key] = value.lower() in ("1", "true", "yes")
        elif isinstance(default, int):
            try:
                kwargs[key] = int(value)
            except ValueError:
                print(f"error: {key} must be a whole number, got {value!r}", file=sys.stderr)
                sys.exit(2)
        else:
            kwargs[key] = value
    try:
        result = evaluate(**kwargs)
    except (ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    if out:
        atomic_write_json(out, result)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
