"""Distil a small student network from the stability CNN: ``python -m overhang_framework.cnn.distill``.

Knowledge distillation (Hinton et al. 2015): the student learns the teacher's answers, not the
physics' verdicts, so it can be told everything the teacher knows about a tower, including how
sure it is, on as many towers as the teacher can answer. Two sources of towers, each answered by the
teacher as ``predictor=cnn`` answers (its logit, mirror-averaged when its checkpoint says so):

* **questions**: random partial towers drawn as the teacher's own training set draws them
  (:func:`overhang_framework.cnn.data.sample_questions`, a share near the static model's tipping
  point), in parts of ``data.part_size``;
* **visited**: every tower the teacher judged while the headline model (``predictor=hybrid
  planner=lookahead planner.depth=3``, the teacher as its late predictor) played the first
  ``data.tasks`` tasks of the benchmark's ``train`` split: the towers planners actually ask about,
  at the edge of stability where their decisions are made. ``paper20``, ``test`` and ``cross`` are
  never used, so the student's agreement is measured on tasks it never saw.

Each part is written as soon as it is made (``data.dir``; a rerun skips the parts on disk). The student
(:mod:`overhang_framework.cnn.student`) then learns the teacher's logits by least squares, with the
towers mirrored in x half the time (the teacher's answer is the same for both). The last
``data.val_parts`` question parts and ``data.val_tasks`` tasks are held out; each epoch prints and
appends to ``out_dir/metrics.jsonl`` the held-out agreement, and ``best.pt`` keeps the epoch closest
to the teacher on the visited towers (the checkpoint format of :mod:`overhang_framework.cnn.model`, so
``predictor=cnn predictor.checkpoint=PATH`` runs it). Rerunning continues after the last finished
epoch; another config in the same ``out_dir`` is refused unless ``overwrite=true``.

Examples::

    python -m overhang_framework.cnn.distill                          # the shipped student's recipe
    python -m overhang_framework.cnn.distill architecture=layerconv_m out_dir=outputs/cnn/distill/m
    python -m overhang_framework.cnn.distill data.questions=40000 data.tasks=4 epochs=2   # a quick one
"""

from __future__ import annotations

import json
import math
import shutil
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np

from overhang_framework.results import atomic_write_json

CONFIG_PATH = "conf"
KEYS = ("widths", "xs", "layers", "n_blocks")


# --------------------------------------------------------------------------------------------------
# The teacher's answers


def teacher_logits(model, data: dict) -> np.ndarray:
    """The teacher's verdict logit for every tower of ``data`` (arrays as :func:`cnn.data.to_arrays`)."""
    widths, xs, layers, mask = as_rows(data, slice(None))
    return model.logits_of_arrays(widths, xs, layers, mask).astype(np.float32)


def as_rows(data: dict, idx):
    """Padded block arrays of the rows ``idx`` of ``data``, as the renderer takes them."""
    widths = data["widths"][idx].astype(np.float64)
    layers = data["layers"][idx].astype(np.float64)
    mask = np.arange(widths.shape[1])[None, :] < data["n_blocks"][idx][:, None]
    return widths, data["xs"][idx], layers, mask


def keys_to_arrays(keys) -> dict:
    """Canonical geometry keys (sorted ``(width, x, layer)`` rows) as :func:`cnn.data.to_arrays` arrays."""
    from overhang_framework.cnn.data import MAX_BLOCKS_STORED

    n = len(keys)
    widths = np.zeros((n, MAX_BLOCKS_STORED), dtype=np.float32)
    xs = np.zeros((n, MAX_BLOCKS_STORED), dtype=np.float64)
    layers = np.zeros((n, MAX_BLOCKS_STORED), dtype=np.int8)
    counts = np.zeros(n, dtype=np.int8)
    for i, key in enumerate(keys):
        rows = np.asarray(key, dtype=np.float64).reshape(-1, 3)
        k = len(rows)
        widths[i, :k], xs[i, :k], layers[i, :k], counts[i] = rows[:, 0], rows[:, 1], rows[:, 2], k
    return {"widths": widths, "xs": xs, "layers": layers, "n_blocks": counts}


def question_part(cfg, index: int) -> dict:
    """Question part ``index``: random towers of the teacher's training distribution (no labels yet)."""
    from overhang_framework.cnn.data import DataSpec, sample_questions, to_arrays
    from overhang_framework.physics.static_backend import StaticBackend

    d = cfg.data
    spec = DataSpec(seed=int(cfg.seed), min_blocks=int(d.min_blocks), max_blocks=int(d.max_blocks),
                    near_critical=float(d.near_critical), window=float(d.window), resolution=float(d.resolution),
                    physics="static")
    rng = np.random.default_rng(np.random.SeedSequence([int(cfg.seed), 7919, int(index)]))
    towers, critical = sample_questions(rng, int(d.part_size), spec, StaticBackend())
    data = to_arrays(towers)
    data["near_critical"] = critical
    return data


def headline_models(teacher: str, depth: int):
    """The headline model with ``teacher`` as the hybrid's late predictor, its cache large enough to
    remember every tower of an episode."""
    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config

    cfg = compose_config(["predictor=hybrid", "planner=lookahead", f"planner.depth={depth}",
                          f"+predictor.late_params.checkpoint={teacher}",
                          "+predictor.late_params.cache_size=50000000"])
    return build_models(cfg)


def visited_part(models: dict, task_id: str, seed: int) -> dict:
    """Every tower the late predictor judged while the models played ``task_id`` once."""
    from overhang_framework.benchmark.splits import task as benchmark_task
    from overhang_framework.episode import run_episode

    late = models["predictor"].late
    late.clear_cache()
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 104729, int(task_id[1:])]))
    run_episode(benchmark_task(task_id), models["world"], models["predictor"], models["planner"], models["value"],
                rng)
    data = keys_to_arrays(list(late._cache))
    late.clear_cache()
    return data


def part_path(directory: Path, name: str) -> Path:
    return Path(directory) / f"{name}.npz"


def write_part(path: Path, data: dict) -> None:
    from overhang_framework.results import atomic_output

    with atomic_output(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **data)


def read_part(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as f:
        data = {k: f[k] for k in f.files}
    if "meta" in data:
        data["meta"] = json.loads(str(data["meta"]))
    return data


def data_settings(cfg, teacher_sha: str) -> dict:
    from omegaconf import OmegaConf

    d = OmegaConf.to_container(cfg.data, resolve=True)
    d.pop("dir", None)
    for k in ("questions", "tasks", "val_parts", "val_tasks"):
        d.pop(k, None)
    return {"seed": int(cfg.seed), "teacher": teacher_sha, **d}


def make_data(cfg, teacher, progress: bool = True) -> tuple[list[Path], list[Path]]:
    """Every part of the data set, made where missing: ``(question parts, visited parts)``."""
    import hashlib

    from overhang_framework.benchmark.splits import split_ids
    from overhang_framework.progress import progress_bar

    directory = Path(cfg.data.dir)
    directory.mkdir(parents=True, exist_ok=True)
    sha = hashlib.sha256(teacher.path.read_bytes()).hexdigest()[:16]
    settings = data_settings(cfg, sha)
    n_parts = -(-int(cfg.data.questions) // int(cfg.data.part_size))
    task_ids = split_ids("train")[:int(cfg.data.tasks)]
    names = [f"questions-{i:04d}" for i in range(n_parts)] + [f"visited-{t}" for t in task_ids]
    todo = []
    for name in names:
        path = part_path(directory, name)
        if path.exists():
            try:
                if read_part(path)["meta"] == settings:
                    continue
            except Exception:
                pass
        todo.append(name)
    bar = progress_bar(total=len(names), initial=len(names) - len(todo), desc="teacher's answers", unit="part",
                       disable=not progress)
    models = None
    for name in todo:
        kind, _, label = name.partition("-")
        if kind == "questions":
            data = question_part(cfg, int(label))
        else:
            models = models or headline_models(str(cfg.teacher), int(cfg.data.depth))
            data = visited_part(models, label, int(cfg.seed))
        data["logits"] = teacher_logits(teacher, data)
        data["meta"] = json.dumps(settings)
        write_part(part_path(directory, name), data)
        bar.update(1)
    bar.close()
    paths = [part_path(directory, n) for n in names]
    return paths[:n_parts], paths[n_parts:]


def concat(paths) -> dict:
    parts = [read_part(p) for p in paths]
    return {k: np.concatenate([p[k] for p in parts]) for k in (*KEYS, "logits")}


# --------------------------------------------------------------------------------------------------
# Agreement


def agreement(student_logits: np.ndarray, teacher: np.ndarray, clip: float = 10.0) -> dict:
    """How close the student's answers are to the teacher's: the mean squared difference of the
    clipped logits, the mean and 99th percentile absolute difference of the probabilities, and the
    share of towers on whose verdict (p >= 0.5) the two agree."""
    s = np.asarray(student_logits, dtype=np.float64)
    t = np.asarray(teacher, dtype=np.float64)
    ps, pt = 1 / (1 + np.exp(-s)), 1 / (1 + np.exp(-t))
    dp = np.abs(ps - pt)
    return {"n": int(len(t)), "logit_mse": float(np.mean((np.clip(s, -clip, clip) - np.clip(t, -clip, clip)) ** 2)),
            "p_mean_abs": float(dp.mean()), "p_p99_abs": float(np.quantile(dp, 0.99)) if len(dp) else float("nan"),
            "verdicts_agree": float(((ps >= 0.5) == (pt >= 0.5)).mean())}


# --------------------------------------------------------------------------------------------------
# Training


def config_record(cfg) -> dict:
    from omegaconf import OmegaConf

    record = OmegaConf.to_container(cfg, resolve=True)
    for k in ("progress", "out_dir", "overwrite", "hydra", "threads"):
        record.pop(k, None)
    record.get("data", {}).pop("dir", None)
    return record


def check(cfg) -> None:
    """Refuse a bad config before any work: one line naming the setting and what is allowed."""
    from overhang_framework.cnn.student import ARCHITECTURES

    if cfg.architecture not in ARCHITECTURES:
        raise ValueError(f"unknown architecture {cfg.architecture!r}; known: {', '.join(ARCHITECTURES)}")
    whole = {"seed": (cfg.seed, 0), "epochs": (cfg.epochs, 1), "batch_size": (cfg.batch_size, 2),
             "data.questions": (cfg.data.questions, 0), "data.part_size": (cfg.data.part_size, 2),
             "data.tasks": (cfg.data.tasks, 0), "data.depth": (cfg.data.depth, 1),
             "data.val_parts": (cfg.data.val_parts, 0), "data.val_tasks": (cfg.data.val_tasks, 0),
             "threads": (cfg.threads, 1)}
    for name, (value, low) in whole.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name} must be a whole number >= {low}, got {value!r}")
    n_parts = -(-int(cfg.data.questions) // int(cfg.data.part_size))
    if cfg.data.val_parts >= max(n_parts, 1) and cfg.data.val_tasks >= max(int(cfg.data.tasks), 1):
        raise ValueError("data.val_parts and data.val_tasks hold out everything; leave some parts or tasks "
                         "to train on")
    for name, value, lo, hi in (("optim.lr", cfg.optim.lr, 1e-7, 1.0), ("optim.weight_decay", cfg.optim.weight_decay, 0, 1),
                                ("clip", cfg.clip, 0.1, 100.0), ("mirror", cfg.mirror, 0.0, 1.0)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi:
            raise ValueError(f"{name} must be a number in [{lo:g}, {hi:g}], got {value!r}")


def distill(cfg) -> dict:
    """Make the data where missing and train the student; return the summary (best epoch's metrics)."""
    check(cfg)  # before torch loads: a bad setting is refused at once
    import torch
    from omegaconf import OmegaConf

    from overhang_framework.cnn.model import (StabilityModel, as_input, build_model, read_checkpoint,
                                              save_checkpoint)
    from overhang_framework.progress import progress_bar
    from overhang_framework.render import make_renderer

    torch.set_num_threads(int(cfg.threads))
    out = Path(cfg.out_dir)
    record = config_record(cfg)
    config_path = out / "config.json"
    if config_path.exists() and json.loads(config_path.read_text()) != record:
        if not cfg.overwrite:
            raise ValueError(f"{out} holds a distillation with another config; use another out_dir or overwrite=true")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(config_path, record)

    teacher = StabilityModel(str(cfg.teacher), device="cpu", threads=int(cfg.threads))
    started = time.perf_counter()
    question_paths, visited_paths = make_data(cfg, teacher, progress=bool(cfg.progress))
    data_seconds = time.perf_counter() - started
    vq, vt = int(cfg.data.val_parts), int(cfg.data.val_tasks)
    train_paths = question_paths[:len(question_paths) - vq] + visited_paths[:len(visited_paths) - vt]
    train = concat(train_paths)
    val = {"questions": concat(question_paths[len(question_paths) - vq:]) if vq else None,
           "visited": concat(visited_paths[len(visited_paths) - vt:]) if vt else None}
    val = {k: v for k, v in val.items() if v is not None}

    renderer = make_renderer(OmegaConf.to_container(cfg.renderer, resolve=True))
    torch.manual_seed(int(cfg.seed))
    net = build_model(str(cfg.architecture), 1, renderer.channels, (renderer.height, renderer.width))
    opt = torch.optim.AdamW(net.parameters(), lr=float(cfg.optim.lr), weight_decay=float(cfg.optim.weight_decay))
    n = len(train["logits"])
    batch = int(cfg.batch_size)
    steps_per_epoch = max(1, n // batch)
    total_steps = steps_per_epoch * int(cfg.epochs)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 0.5 * (1 + math.cos(math.pi * min(s, total_steps) / total_steps)))
    clip = float(cfg.clip)
    target = torch.from_numpy(np.clip(train["logits"], -clip, clip).astype(np.float32))
    metrics_path, last_path, best_path = out / "metrics.jsonl", out / "last.pt", out / "best.pt"
    first_epoch, best_score, rows = 0, math.inf, []
    if last_path.exists():
        state = read_checkpoint(last_path)
        net.load_state_dict(state["state_dict"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        first_epoch = int(state["epoch"]) + 1
        best_score = float(state["best_score"])
        rows = [json.loads(line) for line in metrics_path.read_text().splitlines()[:first_epoch]]
    # the rows of finished epochs only (a row written just before an interruption is made again)
    from overhang_framework.results import atomic_output

    with atomic_output(metrics_path) as tmp:
        Path(tmp).write_text("".join(json.dumps(r) + "\n" for r in rows))
    images = np.empty((batch, *renderer.shape), dtype=np.float32)
    import hashlib

    sha = hashlib.sha256(teacher.path.read_bytes()).hexdigest()
    common = {"teacher": str(cfg.teacher), "teacher_sha256": sha, "teacher_mirror": teacher.mirror,
              "distill_config": record, "mirror": False, "outputs": 1,
              "data": {"questions": int(cfg.data.questions), "tasks": int(cfg.data.tasks), "n_train": n,
                       **data_settings(cfg, sha[:16])}}

    def student_logits(data: dict) -> np.ndarray:
        net.eval()
        out_l = np.empty(len(data["logits"]), dtype=np.float32)
        buf = np.empty((1024, *renderer.shape), dtype=np.float32)
        with torch.inference_mode():
            for s in range(0, len(out_l), 1024):
                rows_ = slice(s, min(len(out_l), s + 1024))
                k = rows_.stop - s
                renderer.render_arrays(*as_rows(data, rows_), out=buf[:k])
                out_l[rows_] = net(torch.from_numpy(buf[:k]))[:, 0].numpy()
        return out_l

    for epoch in range(first_epoch, int(cfg.epochs)):
        rng = np.random.default_rng(np.random.SeedSequence([int(cfg.seed), epoch]))
        order = rng.permutation(n)
        flips = rng.random(n) < float(cfg.mirror)
        net.train()
        t0, loss_sum = time.perf_counter(), 0.0
        bar = progress_bar(total=steps_per_epoch, desc=f"epoch {epoch + 1}/{cfg.epochs}", unit="step",
                           disable=not cfg.progress)
        for step in range(steps_per_epoch):
            idx = order[step * batch:(step + 1) * batch]
            widths, xs, layers, mask = as_rows(train, idx)
            xs = np.where(flips[idx][:, None], -xs, xs)
            renderer.render_arrays(widths, xs, layers, mask, out=images[:len(idx)])
            pred = net(as_input(images[:len(idx)], "cpu"))[:, 0]
            loss = torch.mean((pred - target[idx]) ** 2)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            loss_sum += loss.item()
            bar.update(1)
        bar.close()
        row = {"epoch": epoch + 1, "train_loss": loss_sum / steps_per_epoch,
               "seconds": time.perf_counter() - t0, "lr": float(sched.get_last_lr()[0])}
        for name, data in val.items():
            row[name] = agreement(student_logits(data), data["logits"], clip)
        score = row.get("visited", row.get("questions", {})).get("logit_mse", row["train_loss"])
        rows.append(row)
        with open(metrics_path, "a") as fh:
            fh.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)
        if score < best_score:
            best_score = score
            save_checkpoint(best_path, net, renderer.spec(), str(cfg.architecture), metrics=row, epoch=epoch,
                            **common)
        save_checkpoint(last_path, net, renderer.spec(), str(cfg.architecture), metrics=row, epoch=epoch,
                        optimizer=opt.state_dict(), scheduler=sched.state_dict(), best_score=best_score, **common)
    best = min(rows, key=lambda r: r.get("visited", r.get("questions", {})).get("logit_mse", r["train_loss"]))
    return {"best": best, "out_dir": str(out), "data_seconds": data_seconds, "n_train": n}


def main() -> None:
    from overhang_framework.cnn.train import run_app

    run_app("distill", lambda cfg: {k: v for k, v in distill(cfg).items() if k in ("best", "out_dir")})


if __name__ == "__main__":
    main()
