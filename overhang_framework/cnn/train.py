"""Train the stability CNN: ``python -m overhang_framework.cnn.train [overrides]``.

The data set of ``data`` is generated first where it is missing (resumable;
:mod:`overhang_framework.cnn.data`), then a timm ``backbone`` with random
weights learns to tell standing towers from falling ones in the images of
``renderer``. The last ``data.val_shards`` shards are held out for choosing
the best epoch.

Everything goes to ``out_dir``: ``metrics.jsonl`` (one line per epoch),
``last.pt`` (for resuming) and ``best.pt`` (the epoch with the best held-out
accuracy), all written atomically. Rerunning with the same config continues
an interrupted training from ``last.pt``; a different config is refused unless
``overwrite=true``. A GPU is used when present (``device=auto``).

Examples::

    python -m overhang_framework.cnn.train                       # the shipped model's recipe
    python -m overhang_framework.cnn.train backbone=inception_v4  # the paper's backbone (use a GPU)
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np

from overhang_framework.results import atomic_write_json

log = logging.getLogger(__name__)
CONFIG_PATH = "conf"


def spec_of(cfg) -> "DataSpec":
    from overhang_framework.cnn.data import DataSpec

    d = cfg.data
    return DataSpec(seed=int(d.seed), shards=int(d.shards), shard_size=int(d.shard_size),
                    min_blocks=int(d.min_blocks), max_blocks=int(d.max_blocks),
                    near_critical=float(d.near_critical), window=float(d.window),
                    resolution=float(d.resolution), physics=str(d.physics),
                    physics_params=dict(d.physics_params or {}))


def renderer_of(cfg):
    from omegaconf import OmegaConf

    from overhang_framework.render import make_renderer

    return make_renderer(OmegaConf.to_container(cfg.renderer, resolve=True))


def check(cfg) -> None:
    """Refuse a bad config before any work: one line naming the setting and what is allowed."""
    from overhang_framework.cnn.model import check_backbone, pick_device

    spec_of(cfg)
    renderer = renderer_of(cfg)
    check_backbone(cfg.backbone.name, (renderer.height, renderer.width))
    pick_device(cfg.device)
    for name, low in (("epochs", 1), ("batch_size", 2)):
        v = cfg[name]
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            raise ValueError(f"{name} must be a whole number >= {low}, got {v!r}")
    v = cfg.data.val_shards
    if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v < cfg.data.shards:
        raise ValueError(f"data.val_shards must be a whole number from 1 to data.shards - 1 "
                         f"({cfg.data.shards - 1}), got {v!r}")
    margins = cfg.aux.margins
    if margins is not None and (isinstance(margins, (str, bytes)) or not hasattr(margins, "__iter__")):
        raise ValueError(f"aux.margins must be a list of numbers of metres, got {margins!r}")
    for m in margins or []:
        if isinstance(m, bool) or not isinstance(m, (int, float)) or not math.isfinite(m) or abs(m) >= 1:
            raise ValueError(f"aux.margins must be numbers of metres in (-1, 1), got {m!r}")
    for name, v in (("optim.lr", cfg.optim.lr), ("optim.weight_decay", cfg.optim.weight_decay),
                    ("aux.weight", cfg.aux.weight)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise ValueError(f"{name} must be a number >= 0, got {v!r}")
    if cfg.threads is not None and (isinstance(cfg.threads, bool) or not isinstance(cfg.threads, int)
                                    or cfg.threads < 1):
        raise ValueError(f"threads must be a whole number >= 1 or null, got {cfg.threads!r}")


def _rows(data: dict, idx: np.ndarray):
    widths = data["widths"][idx].astype(np.float64)
    xs = data["xs"][idx]
    layers = data["layers"][idx].astype(np.float64)
    mask = np.arange(widths.shape[1])[None, :] < data["n_blocks"][idx][:, None]
    return widths, xs, layers, mask


def evaluate_arrays(net, renderer, data: dict, device, batch_size: int = 512, mirror: bool = False) -> dict:
    """Accuracy (overall and near-critical) and loss on a loaded data set, from a single image. With
    ``mirror``, also of the mean logit of each tower and its mirror image (as
    :class:`~overhang_framework.cnn.model.StabilityModel`), from the same pass: the better of the two
    is returned, with ``mirror`` saying which, and ``accuracy_single`` and ``accuracy_mirror``."""
    import torch

    from overhang_framework.cnn.model import as_input

    n = len(data["stable"])
    single, mirrored = np.empty(n), np.empty(n)
    net.eval()
    buf = np.empty((batch_size, *renderer.shape), dtype=np.float32)
    with torch.inference_mode():
        for start in range(0, n, batch_size):
            idx = np.arange(start, min(n, start + batch_size))
            widths, xs, layers, mask = _rows(data, idx)
            images = renderer.render_arrays(widths, xs, layers, mask, out=buf[:len(idx)])
            single[idx] = net(as_input(images, device))[:, 0].float().cpu().numpy()
            if mirror:
                images = renderer.render_arrays(widths, -xs, layers, mask, out=buf[:len(idx)])
                mirrored[idx] = (single[idx] + net(as_input(images, device))[:, 0].float().cpu().numpy()) / 2
    probability = lambda logits: 1.0 / (1.0 + np.exp(-logits))  # noqa: E731
    result = {**scores(probability(single), data), "mirror": False}
    if mirror:
        both = scores(probability(mirrored), data)
        accuracies = {"accuracy_single": result["accuracy"], "accuracy_mirror": both["accuracy"]}
        result = {**both, "mirror": True} if both["accuracy"] > result["accuracy"] else result
        result.update(accuracies)
    return result


def scores(probs: np.ndarray, data: dict) -> dict:
    y = data["stable"].astype(bool)
    right = (probs >= 0.5) == y
    crit = data["near_critical"].astype(bool)
    eps = 1e-7
    loss = -np.mean(np.where(y, np.log(probs + eps), np.log(1 - probs + eps))) if len(y) else float("nan")
    return {"accuracy": float(right.mean()) if len(y) else float("nan"),
            "accuracy_near_critical": float(right[crit].mean()) if crit.any() else float("nan"),
            "accuracy_random": float(right[~crit].mean()) if (~crit).any() else float("nan"),
            "loss": float(loss), "n": int(len(y)), "n_near_critical": int(crit.sum())}


def config_record(cfg) -> dict:
    """The config as plain data, without the settings that do not change the result."""
    from omegaconf import OmegaConf

    d = OmegaConf.to_container(cfg, resolve=True)
    for k in ("out_dir", "overwrite", "threads", "device", "progress", "workers", "hydra"):
        d.pop(k, None)
    return d


def train(cfg) -> dict:
    """Run the training ``cfg`` describes; return the best epoch's metrics."""
    import torch
    from tqdm import tqdm

    from overhang_framework.cnn.data import generate, load, margin_verdicts
    from overhang_framework.cnn.model import as_input, build_model, pick_device, save_checkpoint

    check(cfg)
    if cfg.threads is not None:
        torch.set_num_threads(int(cfg.threads))
    out_dir = Path(cfg.out_dir)
    record = config_record(cfg)
    state_file = out_dir / "config.json"
    if out_dir.exists() and state_file.exists():
        if cfg.overwrite:
            shutil.rmtree(out_dir)
        elif json.loads(state_file.read_text()) != json.loads(json.dumps(record)):
            raise ValueError(f"{out_dir} holds a training with another config; "
                             f"use another out_dir or overwrite=true")
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_json(state_file, record)

    spec = spec_of(cfg)
    started = time.perf_counter()
    manifest = generate(spec, cfg.data.dir, workers=int(cfg.workers), progress=bool(cfg.progress))
    data_seconds = time.perf_counter() - started
    n_shards = spec.shards
    val_ids = list(range(n_shards - int(cfg.data.val_shards), n_shards))
    train_data = load(cfg.data.dir, [i for i in range(n_shards) if i not in val_ids])
    val_data = load(cfg.data.dir, val_ids)

    margins = [float(m) for m in (cfg.aux.margins or [])]
    aux_weight = float(cfg.aux.weight)
    aux = margin_verdicts(train_data, margins, int(cfg.workers)).astype(np.float32) if margins else None
    device = pick_device(cfg.device)
    renderer = renderer_of(cfg)
    torch.manual_seed(int(cfg.seed))
    outputs = 1 + len(margins)
    net = build_model(cfg.backbone.name, outputs, renderer.channels).to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=float(cfg.optim.lr), weight_decay=float(cfg.optim.weight_decay))
    n_train = len(train_data["stable"])
    steps_per_epoch = max(1, n_train // int(cfg.batch_size))
    total = steps_per_epoch * int(cfg.epochs)
    warmup = min(steps_per_epoch, total // 10 + 1)

    def lr_at(step):
        if step < warmup:
            return (step + 1) / warmup
        return 0.5 * (1 + math.cos(math.pi * (step - warmup) / max(1, total - warmup)))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_at)
    start_epoch, best, history = 0, None, []
    last = out_dir / "last.pt"
    if last.exists():
        payload = torch.load(last, map_location="cpu", weights_only=False)
        net.load_state_dict(payload["state_dict"])
        opt.load_state_dict(payload["optimizer"])
        sched.load_state_dict(payload["scheduler"])
        torch.set_rng_state(payload["torch_rng"])
        start_epoch, best, history = payload["epoch"], payload["best"], payload["history"]
        log.info("resuming after epoch %d", start_epoch)
        print(f"resuming {out_dir} after epoch {start_epoch}", file=sys.stderr)

    extra_common = {"outputs": outputs, "data": spec.settings(),
                    "data_size": {"train": n_train, "val": len(val_data["stable"])}, "train_config": record}
    train_seconds = sum(h["seconds"] for h in history)
    for epoch in range(start_epoch, int(cfg.epochs)):
        t0 = time.perf_counter()
        net.train()
        rng = np.random.default_rng(np.random.SeedSequence([int(cfg.seed), epoch]))
        order = rng.permutation(n_train)
        flips = rng.random(n_train) < float(cfg.augment.mirror)
        buf = np.empty((int(cfg.batch_size), *renderer.shape), dtype=np.float32)
        total_loss, seen = 0.0, 0
        bar = tqdm(range(steps_per_epoch), desc=f"epoch {epoch + 1}/{cfg.epochs}", unit="batch",
                   disable=not cfg.progress, file=sys.stderr)
        for step in bar:
            idx = order[step * int(cfg.batch_size):(step + 1) * int(cfg.batch_size)]
            widths, xs, layers, mask = _rows(train_data, idx)
            xs = np.where(flips[idx][:, None], -xs, xs)  # mirroring in x keeps the verdict
            images = renderer.render_arrays(widths, xs, layers, mask, out=buf[:len(idx)])
            x = as_input(images, device)
            y = torch.from_numpy(train_data["stable"][idx].astype(np.float32)).to(device)
            out = net(x)
            loss = torch.nn.functional.binary_cross_entropy_with_logits(out[:, 0], y)
            if aux is not None:
                loss = loss + aux_weight * torch.nn.functional.binary_cross_entropy_with_logits(
                    out[:, 1:], torch.from_numpy(aux[idx]).to(device))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            total_loss += float(loss.detach()) * len(idx)
            seen += len(idx)
            if step % 20 == 0:
                bar.set_postfix(loss=f"{total_loss / seen:.4f}")
        bar.close()
        seconds = time.perf_counter() - t0
        train_seconds += seconds
        # Validation picks how the model is used: mirror averaging (when it trained on mirrored images)
        # only if it scores higher than a single image; the checkpoint records the choice.
        val = evaluate_arrays(net, renderer, val_data, device, mirror=float(cfg.augment.mirror) > 0)
        mirror = val.pop("mirror")
        row = {"epoch": epoch + 1, "train_loss": total_loss / max(1, seen), "val_accuracy": val["accuracy"],
               "val_accuracy_near_critical": val["accuracy_near_critical"], "val_loss": val["loss"],
               "mirror": mirror, "val_accuracy_single": val.get("accuracy_single", val["accuracy"]),
               "val_accuracy_mirror": val.get("accuracy_mirror"),
               "lr": opt.param_groups[0]["lr"], "seconds": seconds, "images_per_s": seen / seconds}
        history.append(row)
        with open(out_dir / "metrics.jsonl", "a") as fh:
            fh.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)
        extra = {**extra_common, "epoch": epoch + 1, "metrics": val, "mirror": mirror, "train_seconds": train_seconds,
                 "data_seconds": data_seconds}
        if best is None or val["accuracy"] > best["val_accuracy"]:
            best = dict(row)
            save_checkpoint(out_dir / "best.pt", net, renderer.spec(), cfg.backbone.name, **extra)
        save_checkpoint(last, net, renderer.spec(), cfg.backbone.name, **extra,
                        optimizer=opt.state_dict(), scheduler=sched.state_dict(),
                        torch_rng=torch.get_rng_state(), best=best, history=history)
    summary = {"best": best, "train_seconds": train_seconds, "data": manifest, "out_dir": str(out_dir),
               "device": str(device)}
    atomic_write_json(out_dir / "summary.json", summary)
    return summary


def main() -> None:
    import hydra

    @hydra.main(version_base=None, config_path=CONFIG_PATH, config_name="train")
    def _main(cfg) -> None:
        try:
            summary = train(cfg)
        except (ValueError, FileNotFoundError) as err:
            print(f"error: {err}", file=sys.stderr)
            sys.exit(2)
        print(json.dumps({"best": summary["best"], "out_dir": summary["out_dir"]}))

    _main()


if __name__ == "__main__":
    main()
