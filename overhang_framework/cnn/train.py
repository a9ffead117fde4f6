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
    v = cfg.processes
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"processes must be a whole number >= 1, got {v!r}")
    if v > 1 and cfg.batch_size % v:
        raise ValueError(f"batch_size ({cfg.batch_size}) must be a multiple of processes ({v}): each process "
                         f"takes an equal share of every batch")
    if v > 1 and pick_device(cfg.device).type != "cpu":
        raise ValueError(f"processes={v} trains on the CPU's cores; on a GPU use processes=1")
    v = cfg.ema
    if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < 1):
        raise ValueError(f"ema must be null or a decay between 0 and 1 (e.g. 0.999), got {v!r}")
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
    from overhang_framework.cnn.model import tower_logits

    n = len(data["stable"])
    single, mirrored = np.empty(n), np.empty(n)
    net.eval()
    buf = np.empty((batch_size, *renderer.shape), dtype=np.float32)
    step = max(1, batch_size // (2 if mirror else 1))
    for start in range(0, n, step):
        idx = np.arange(start, min(n, start + step))
        one, other = tower_logits(net, renderer, *_rows(data, idx), device, buf, mirror)
        single[idx] = one
        if mirror:
            mirrored[idx] = (one + other) / 2
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


def init_weights(init, backbone: str, renderer_spec: dict, outputs: int) -> tuple[dict, dict]:
    """The weights of checkpoint ``init`` and what made it (its record, without the weights);
    ``ValueError`` when it was made for another backbone, renderer or number of outputs."""
    from overhang_framework.cnn.model import read_checkpoint, resolve_checkpoint

    path = resolve_checkpoint(init)
    payload = read_checkpoint(path)
    theirs = {"backbone": payload.get("backbone"), "renderer": payload.get("renderer"),
              "outputs": int(payload.get("outputs", 1))}
    ours = {"backbone": backbone, "renderer": dict(renderer_spec), "outputs": outputs}
    for key in ours:
        if theirs[key] != ours[key]:
            raise ValueError(f"init checkpoint {path} has {key} {theirs[key]!r} but this training has "
                             f"{ours[key]!r}; start from a checkpoint made with the same {key}")
    keep = ("backbone", "epoch", "metrics", "mirror", "weights", "train_seconds", "data_seconds", "data",
            "data_size", "train_config", "init_from")
    return payload["state_dict"], {"path": str(path), **{k: payload[k] for k in keep if k in payload}}


def config_record(cfg) -> dict:
    """The config as plain data, without the settings that do not change the result."""
    from omegaconf import OmegaConf

    d = OmegaConf.to_container(cfg, resolve=True)
    for k in ("out_dir", "overwrite", "threads", "device", "progress", "workers", "hydra"):
        d.pop(k, None)
    if d.get("ema") is None:  # trainings without an average record the config they had before ema existed
        d.pop("ema", None)
    return d


def train(cfg) -> dict:
    """Run the training ``cfg`` describes; return its summary (the best epoch's metrics under ``best``)."""
    from omegaconf import OmegaConf

    from overhang_framework.cnn.data import generate, load, margin_verdicts

    check(cfg)
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
    aux = margin_verdicts(train_data, margins, int(cfg.workers)).astype(np.float32) if margins else None
    init_state, init_from = (init_weights(cfg.init, cfg.backbone.name, renderer_of(cfg).spec(), 1 + len(margins))
                             if cfg.init else (None, None))
    job = {"cfg": OmegaConf.to_container(cfg, resolve=True), "record": record, "spec": spec.settings(),
           "train": train_data, "val": val_data, "aux": aux, "data_seconds": data_seconds,
           "init_state": init_state, "init_from": init_from}
    processes = int(cfg.processes)
    if processes == 1:
        best, train_seconds, device = fit(0, 1, job)
    else:
        best, train_seconds, device = fit_in_processes(processes, job)
    summary = {"best": best, "train_seconds": train_seconds, "data": manifest, "out_dir": str(out_dir),
               "device": device, "processes": processes}
    atomic_write_json(out_dir / "summary.json", summary)
    return summary


class TrainingProcessFailed(RuntimeError):
    """A process of a data-parallel training failed; the epochs already finished are kept in ``last.pt``."""


def fit_in_processes(processes: int, job: dict):
    """:func:`fit` on ``processes`` CPU processes, data-parallel (``torch.distributed`` over gloo)."""
    import socket

    import torch.multiprocessing as mp
    from torch.multiprocessing.spawn import ProcessException

    with socket.socket() as sock:  # a free port on this machine for the processes to meet on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    result = mp.get_context("spawn").SimpleQueue()
    try:
        mp.spawn(_fit_process, args=(processes, job, port, result), nprocs=processes, join=True)
    except ProcessException as err:
        lines = [line for line in str(err).strip().splitlines() if line.strip()]
        raise TrainingProcessFailed(f"a training process failed ({lines[-1] if lines else err}); "
                                    f"{job['cfg']['out_dir']}/last.pt keeps the finished epochs, "
                                    f"rerun to resume") from err
    return result.get()


def _fit_process(rank: int, processes: int, job: dict, port: int, result) -> None:
    import torch.distributed as dist

    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=processes)
    try:
        out = fit(rank, processes, job)
        if rank == 0:
            result.put(out)
        dist.barrier()  # leave together: a process tearing gloo down while a peer still talks to it aborts
    finally:
        dist.destroy_process_group()


def fit(rank: int, processes: int, job: dict):
    """The epochs of a training, as process ``rank`` of ``processes`` (data-parallel when more than one:
    each process renders and learns from its share of every batch, and their gradients are averaged, so
    a step sees the whole batch). Process 0 validates and writes the metrics and checkpoints.
    Returns ``(best epoch's row, training seconds, device name)``."""
    import torch
    import torch.distributed as dist
    from overhang_framework.progress import progress_bar

    from overhang_framework.cnn.model import as_input, build_model, pick_device, save_checkpoint
    from overhang_framework.render import make_renderer

    cfg, record, train_data, val_data, aux = job["cfg"], job["record"], job["train"], job["val"], job["aux"]
    lead = rank == 0
    threads = cfg["threads"] if cfg["threads"] is not None else (1 if processes > 1 else None)
    if threads is not None:
        torch.set_num_threads(int(threads))
    out_dir = Path(cfg["out_dir"])
    margins = [float(m) for m in (cfg["aux"]["margins"] or [])]
    aux_weight = float(cfg["aux"]["weight"])
    device = pick_device(cfg["device"])
    renderer = make_renderer(cfg["renderer"])
    backbone, batch_size, epochs = cfg["backbone"]["name"], int(cfg["batch_size"]), int(cfg["epochs"])
    torch.manual_seed(int(cfg["seed"]))
    outputs = 1 + len(margins)
    net = build_model(backbone, outputs, renderer.channels).to(device)
    if job.get("init_state") is not None:
        net.load_state_dict(job["init_state"])
    opt = torch.optim.AdamW(net.parameters(), lr=float(cfg["optim"]["lr"]),
                            weight_decay=float(cfg["optim"]["weight_decay"]))
    n_train = len(train_data["stable"])
    steps_per_epoch = max(1, n_train // batch_size)
    total = steps_per_epoch * epochs
    warmup = min(steps_per_epoch, total // 10 + 1)

    def lr_at(step):
        if step < warmup:
            return (step + 1) / warmup
        return 0.5 * (1 + math.cos(math.pi * (step - warmup) / max(1, total - warmup)))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_at)
    ema = None
    if cfg["ema"] is not None and lead:
        from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

        ema = AveragedModel(net, multi_avg_fn=get_ema_multi_avg_fn(float(cfg["ema"])), use_buffers=True)
    start_epoch, best, history = 0, None, []
    last = out_dir / "last.pt"
    if last.exists():
        payload = torch.load(last, map_location="cpu", weights_only=False)
        net.load_state_dict(payload["state_dict"])
        opt.load_state_dict(payload["optimizer"])
        sched.load_state_dict(payload["scheduler"])
        torch.set_rng_state(payload["torch_rng"])
        start_epoch, best, history = payload["epoch"], payload["best"], payload["history"]
        if ema is not None:
            if "ema_state" not in payload:
                raise ValueError(f"{last} holds no moving average of the weights to resume; "
                                 f"use another out_dir or overwrite=true")
            ema.load_state_dict(payload["ema_state"])
        if lead:
            log.info("resuming after epoch %d", start_epoch)
            print(f"resuming {out_dir} after epoch {start_epoch}", file=sys.stderr)
    model = net
    if processes > 1:
        from torch.nn.parallel import DistributedDataParallel

        model = DistributedDataParallel(net)

    extra_common = {"outputs": outputs, "init_from": job.get("init_from"), "data": job["spec"],
                    "data_size": {"train": n_train, "val": len(val_data["stable"])}, "train_config": record}
    train_seconds = sum(h["seconds"] for h in history)
    mirror_p = float(cfg["augment"]["mirror"])
    for epoch in range(start_epoch, epochs):
        t0 = time.perf_counter()
        model.train()
        rng = np.random.default_rng(np.random.SeedSequence([int(cfg["seed"]), epoch]))
        order = rng.permutation(n_train)
        flips = rng.random(n_train) < mirror_p
        buf = np.empty((batch_size, *renderer.shape), dtype=np.float32)
        totals = torch.zeros(2, dtype=torch.float64)  # loss summed over questions, questions
        bar = progress_bar(range(steps_per_epoch), desc=f"epoch {epoch + 1}/{epochs}", unit="batch",
                   disable=not (cfg["progress"] and lead), file=sys.stderr)
        for step in bar:
            idx = order[step * batch_size:(step + 1) * batch_size][rank::processes]
            widths, xs, layers, mask = _rows(train_data, idx)
            xs = np.where(flips[idx][:, None], -xs, xs)  # mirroring in x keeps the verdict
            images = renderer.render_arrays(widths, xs, layers, mask, out=buf[:len(idx)])
            x = as_input(images, device)
            y = torch.from_numpy(train_data["stable"][idx].astype(np.float32)).to(device)
            out = model(x)
            loss = torch.nn.functional.binary_cross_entropy_with_logits(out[:, 0], y)
            if aux is not None:
                loss = loss + aux_weight * torch.nn.functional.binary_cross_entropy_with_logits(
                    out[:, 1:], torch.from_numpy(aux[idx]).to(device))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            if ema is not None:
                ema.update_parameters(net)
            totals += torch.tensor([float(loss.detach()) * len(idx), len(idx)], dtype=torch.float64)
            if step % 20 == 0:
                bar.set_postfix(loss=f"{totals[0] / totals[1]:.4f}")
        bar.close()
        if processes > 1:
            dist.all_reduce(totals)
        seconds = time.perf_counter() - t0
        train_seconds += seconds
        if lead:
            row, extra, chosen = _validate(net, ema, renderer, val_data, device, cfg, epoch, totals, seconds,
                                           opt, train_seconds, job["data_seconds"], extra_common)
            history.append(row)
            if best is None or row["val_accuracy"] > best["val_accuracy"]:
                best = dict(row)
                save_checkpoint(out_dir / "best.pt", chosen, renderer.spec(), backbone, **extra)
            save_checkpoint(last, net, renderer.spec(), backbone, **extra,
                            optimizer=opt.state_dict(), scheduler=sched.state_dict(),
                            torch_rng=torch.get_rng_state(), best=best, history=history,
                            **({"ema_state": ema.state_dict()} if ema is not None else {}))
        if processes > 1:
            dist.barrier()  # the others wait while process 0 validates and saves
    if processes > 1:
        _check_in_step(net)
    return best, train_seconds, str(device)


def _validate(net, ema, renderer, val_data, device, cfg, epoch, totals, seconds, opt, train_seconds, data_seconds,
              extra_common) -> tuple[dict, dict, object]:
    """One epoch's metrics row (appended to metrics.jsonl and printed), the record its checkpoints carry,
    and the network whose weights a best checkpoint keeps (``net``, or with ``ema`` its moving average
    when that scores higher)."""
    # Validation picks how the model is used: mirror averaging (when it trained on mirrored images)
    # only if it scores higher than a single image; the checkpoint records the choice.
    try_mirror = float(cfg["augment"]["mirror"]) > 0
    val = evaluate_arrays(net, renderer, val_data, device, mirror=try_mirror)
    chosen, weights, averaged = net, "trained", {}
    if ema is not None:
        val_ema = evaluate_arrays(ema.module, renderer, val_data, device, mirror=try_mirror)
        averaged = {"val_accuracy_trained": val["accuracy"], "val_accuracy_ema": val_ema["accuracy"]}
        if val_ema["accuracy"] > val["accuracy"]:
            val, chosen, weights = val_ema, ema.module, "ema"
    mirror = val.pop("mirror")
    seen = float(totals[1])
    row = {"epoch": epoch + 1, "train_loss": float(totals[0]) / max(1.0, seen), "val_accuracy": val["accuracy"],
           "val_accuracy_near_critical": val["accuracy_near_critical"], "val_loss": val["loss"],
           "mirror": mirror, "val_accuracy_single": val.get("accuracy_single", val["accuracy"]),
           "val_accuracy_mirror": val.get("accuracy_mirror"), "weights": weights, **averaged,
           "lr": opt.param_groups[0]["lr"], "seconds": seconds, "images_per_s": seen / seconds}
    with open(Path(cfg["out_dir"]) / "metrics.jsonl", "a") as fh:
        fh.write(json.dumps(row) + "\n")
    print(json.dumps(row), flush=True)
    extra = {**extra_common, "epoch": epoch + 1, "metrics": val, "mirror": mirror, "weights": weights,
             "train_seconds": train_seconds, "data_seconds": data_seconds}
    return row, extra, chosen


def _check_in_step(net) -> None:
    """``TrainingProcessFailed`` when the processes' weights have drifted apart (they must stay equal)."""
    import torch
    import torch.distributed as dist

    total = torch.stack([p.detach().double().sum() for p in net.parameters()]).sum().reshape(1)
    low, high = total.clone(), total.clone()
    dist.all_reduce(low, op=dist.ReduceOp.MIN)
    dist.all_reduce(high, op=dist.ReduceOp.MAX)
    if float(high - low) > 1e-6 * max(1.0, float(abs(high))):
        raise TrainingProcessFailed(f"the training processes' weights differ ({float(low)} against {float(high)})")


def run_app(config_name: str, work, errors: tuple = (ValueError, FileNotFoundError)) -> None:
    """Run ``work(cfg)`` as the Hydra app of ``conf/<config_name>.yaml``: a misspelt key is one line with the
    closest existing one (checked before Hydra starts), as for the other commands; an error of ``errors``
    is one line and exit status 2; what ``work`` returns is printed as one JSON line."""
    import hydra

    from overhang_framework.errors import OverhangError
    from overhang_framework.preflight import check_flags, compose_checked, is_multirun, split_flags, sweep_variants

    args = sys.argv[1:]
    try:
        check_flags(args)
        for variant in sweep_variants(split_flags(args)[1], is_multirun(args)):
            compose_checked(variant, config_name=config_name, config_dir=str(Path(__file__).parent / CONFIG_PATH))
    except OverhangError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)

    @hydra.main(version_base=None, config_path=str(Path(__file__).parent / CONFIG_PATH), config_name=config_name)
    def _main(cfg) -> None:
        try:
            result = work(cfg)
        except errors as err:
            print(f"error: {err}", file=sys.stderr)
            sys.exit(2)
        print(json.dumps(result))

    _main()


def main() -> None:
    run_app("train", lambda cfg: {k: v for k, v in train(cfg).items() if k in ("best", "out_dir")},
            (ValueError, FileNotFoundError, TrainingProcessFailed))


if __name__ == "__main__":
    main()
