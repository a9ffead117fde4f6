"""The distilled student against its teacher, side by side: ``python -m overhang_framework.bench.student``.

Two measurements, each running both networks in one process on the same cases, alternating which
goes first (:mod:`overhang_framework.bench.sidebyside`):

* ``speed``: microseconds per image of the forward pass alone (ONNX Runtime, as ``predictor=cnn`` runs
  it) and of rendering plus the forward pass, per image and per tower (the teacher draws each tower
  and its mirror image when its checkpoint says so), on ``--threads`` threads, in passes of
  ``--batch`` images over ``--towers`` random towers, ``--rounds`` times each;
* ``decisions``: the headline model (``predictor=hybrid planner=lookahead planner.depth=3``) with the
  teacher as its late predictor plays every task of ``--tasks`` (``paper20``, or a benchmark split such
  as ``test``); at every state of its episodes both versions decide from the same generator, and the
  share of decisions whose chosen action is the same is printed, with each version's seconds per
  decision. A decision of the student's that differs is listed with both root scores.

The last line is one JSON object with every figure (``--out FILE`` writes it too).

    python -m overhang_framework.bench.student speed
    python -m overhang_framework.bench.student decisions --tasks paper20
    python -m overhang_framework.bench.student decisions --tasks test --limit 40
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Optional, Sequence

import numpy as np

from overhang_framework.bench.sidebyside import ratio, side_by_side


def speed(checkpoints: Sequence[str], threads: int = 1, batch: int = 64, towers: int = 4096, rounds: int = 5) -> dict:
    """Per-image and per-tower microseconds of each checkpoint, the forward pass alone and with rendering."""
    import torch

    from overhang_framework.physics.towers import random_towers
    from overhang_framework.cnn.model import StabilityModel
    from overhang_framework.render import block_arrays

    torch.set_num_threads(threads)
    sample = random_towers(towers, seed=11)
    arrays = block_arrays(sample)
    models = {c: StabilityModel(c, device="cpu", threads=threads, batch_size=batch) for c in checkpoints}
    images = {}
    for c, m in models.items():  # the images each network takes, drawn once, for the forward pass alone
        buf = np.empty((towers * m.images_per_tower, *m.renderer.shape), dtype=np.float32)
        m.renderer.render_arrays(*arrays, out=buf[:towers])
        if m.mirror:
            m.renderer.mirror_images(buf[:towers], out=buf[towers:])
        images[c] = buf
        m.logits_of_arrays(*(a[:batch] for a in arrays))  # warm up

    def forward(c):
        def run(_):
            x = images[c]
            for s in range(0, len(x), batch):
                models[c].net(x[s:s + batch])
            return None
        return run

    def render_forward(c):
        def run(_):
            models[c].logits_of_arrays(*arrays)
            return None
        return run

    out = {"threads": threads, "batch": batch, "towers": towers, "rounds": rounds}
    for label, make in (("forward", forward), ("render_and_forward", render_forward)):
        figures = side_by_side(range(rounds), {c: make(c) for c in checkpoints}, quiet=True)
        row = {}
        for c in checkpoints:
            per_round = float(np.median(figures["versions"][c]["seconds"]))
            k = models[c].images_per_tower
            row[c] = {"us_per_image": 1e6 * per_round / (towers * k), "us_per_tower": 1e6 * per_round / towers,
                      "images_per_tower": k}
        if len(checkpoints) == 2:
            a, b = checkpoints
            row["image_ratio"] = row[a]["us_per_image"] / row[b]["us_per_image"]
            row["tower_ratio"] = row[a]["us_per_tower"] / row[b]["us_per_tower"]
            row["total_ratio"] = ratio(figures, a, b)
        out[label] = row
        for c in checkpoints:
            print(f"{label:>19}: {c:>8} {row[c]['us_per_image']:7.1f} us/image, {row[c]['us_per_tower']:7.1f} us/tower "
                  f"({row[c]['images_per_tower']} image{'s' if row[c]['images_per_tower'] > 1 else ''} a tower)",
                  flush=True)
        if len(checkpoints) == 2:
            print(f"{label:>19}: {checkpoints[1]} is {row['image_ratio']:.1f}x faster per image, "
                  f"{row['tower_ratio']:.1f}x per tower", flush=True)
    return out


def task_list(name: str, limit: Optional[int] = None):
    """``paper20``'s tasks, or a benchmark split's (``test``, ``cross``, ``train``), the first ``limit``."""
    from overhang_framework.benchmark.splits import split_ids, task as benchmark_task
    from overhang_framework.config import compose_config
    from overhang_framework.tasks import tasks_from_config

    if name == "paper20":
        tasks = tasks_from_config(compose_config(["tasks=paper20"]).tasks)
    else:
        tasks = [benchmark_task(t) for t in split_ids(name)]
    return tasks[:limit] if limit else tasks


def models_with(checkpoint: str, depth: int, extra: Sequence[str] = ()) -> dict:
    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config

    return build_models(compose_config(["predictor=hybrid", "planner=lookahead", f"planner.depth={depth}",
                                        f"+predictor.late_params.checkpoint={checkpoint}", *extra]))


def softmax(z: np.ndarray) -> np.ndarray:
    e = np.exp(z - z.max())
    return e / e.sum()


def decisions(tasks: str = "paper20", limit: Optional[int] = None, checkpoints: Sequence[str] = ("teacher", "student"),
              depth: int = 3, seed: int = 0, extra: Sequence[str] = (), tables: bool = True,
              beta: float = 2.4) -> dict:
    """The share of the first checkpoint's decisions that each other checkpoint makes alike, at every state
    of the first checkpoint's own episodes of ``tasks`` (see the module docstring). With ``tables``, also
    what a different choice costs by the first's own scores (``regret``: how far below its best root score
    the other's choice is), the total variation between the two versions' softmax choice probabilities at
    inverse temperature ``beta`` (per metre; 2.4, as docs/cnn.md measured it), and the relative gap between the first's two
    best root scores."""
    from overhang_framework.interfaces import Budget
    from overhang_framework.search import Expander, root_scores

    models = {}
    for c in checkpoints:  # a network's name or path, or NAME=OVERRIDE;OVERRIDE (the headline model's config)
        name, sep, overrides = c.partition("=")
        models[c] = models_with_overrides(depth, [o for o in overrides.split(";") if o] + list(extra)) if sep \
            else models_with(c, depth, extra)
    lead = checkpoints[0]
    world = models[lead]["world"]
    rows, cases = [], []
    for n, task in enumerate(task_list(tasks, limit)):
        state = world.initial_state(task)
        step = 0
        while not state.done:
            cases.append((task.id, step, state))
            rng_seed = int(np.random.SeedSequence([seed, n, step]).generate_state(1)[0])

            def decide(c, state=state, rng_seed=rng_seed):
                m = models[c]
                d = m["planner"].plan(state, m["predictor"], m["value"], Budget(), np.random.default_rng(rng_seed))
                return (round(d.action.x, 6), d.action.layer)

            figures = side_by_side([state], {c: (lambda s, c=c: decide(c)) for c in checkpoints}, quiet=True)
            got = {c: figures["versions"][c]["results"][0] for c in checkpoints}
            secs = {c: figures["versions"][c]["seconds"][0] for c in checkpoints}
            rows.append({"task": task.id, "step": step, "actions": got, "seconds": secs})
            if tables:  # every root action's exact score under each version
                exact = {}
                for c in checkpoints:
                    m = models[c]
                    ex = Expander(m["world"], m["predictor"], Budget(), seed=0)
                    exact[c] = root_scores(ex, m["value"], state, min(depth, len(state.remaining)), True)
                    acts = [(round(a.x, 6), a.layer) for a in ex.expand(state, force=True).actions]
                ref = exact[lead]
                rows[-1]["regret"], rows[-1]["tv"] = {}, {}
                for c in checkpoints[1:]:
                    pick = acts.index(got[c]) if got[c] in acts else int(np.argmax(exact[c]))
                    rows[-1]["regret"][c] = float(1 - ref[pick] / ref.max()) if ref.max() > 0 else 0.0
                    rows[-1]["tv"][c] = float(0.5 * np.abs(softmax(beta * ref) - softmax(beta * exact[c])).sum())
                top = np.sort(ref)[::-1]
                rows[-1]["gap"] = float((top[0] - top[1]) / top[0]) if len(top) > 1 and top[0] > 0 else float("nan")
            if any(got[c] != got[lead] for c in checkpoints):
                print(f"  {task.id} step {step}: " + ", ".join(f"{c} {got[c]}" for c in checkpoints), flush=True)
            action = got[lead]
            legal = world.legal_actions(state)
            chosen = min(legal, key=lambda a: (abs(a.x - action[0]), a.layer != action[1]))
            state = world.step(state, chosen)
            if not world.is_stable(state.geometry):
                break
            step += 1
        done = len(rows)
        same = {c: sum(r["actions"][c] == r["actions"][lead] for r in rows) for c in checkpoints[1:]}
        print(f"{task.id}: {done} decisions, the same: " + ", ".join(f"{c} {same[c]}" for c in same), flush=True)
    out = {"tasks": tasks, "limit": limit, "depth": depth, "decisions": len(rows), "checkpoints": list(checkpoints),
           "beta": beta, "rows": rows}
    if tables and rows:
        gaps = np.array([r["gap"] for r in rows if np.isfinite(r["gap"])])
        out["gap_median"] = float(np.median(gaps))
        out["gap_below_1pct"] = float((gaps < 0.01).mean())
        print(f"{lead}'s two best root scores differ by a median {100 * out['gap_median']:.2f}%; by less than 1% in "
              f"{100 * out['gap_below_1pct']:.0f}% of decisions", flush=True)
    for c in checkpoints:
        secs = [r["seconds"][c] for r in rows]
        out[c] = {"median_seconds": float(np.median(secs)), "max_seconds": float(np.max(secs)),
                  "mean_seconds": float(np.mean(secs))}
        if c != lead:
            same = sum(r["actions"][c] == r["actions"][lead] for r in rows)
            out[c]["same_action"] = same / max(1, len(rows))
            if tables and rows:
                regret = np.array([r["regret"][c] for r in rows])
                tv = np.array([r["tv"][c] for r in rows])
                out[c].update({"regret_mean": float(regret.mean()), "regret_p90": float(np.quantile(regret, 0.9)),
                               "regret_max": float(regret.max()), "tv_mean": float(tv.mean()),
                               "tv_p90": float(np.quantile(tv, 0.9))})
                print(f"{c}: its choice scores on average {100 * regret.mean():.2f}% below {lead}'s best by {lead}'s "
                      f"own scores (90th percentile {100 * out[c]['regret_p90']:.2f}%); softmax choice probabilities "
                      f"at beta {beta:g} differ by a total variation of {tv.mean():.3f} on average", flush=True)
            print(f"{c}: the same action as {lead} in {same} of {len(rows)} decisions ({100 * same / max(1, len(rows)):.1f}%); "
                  f"median decision {out[c]['median_seconds']:.3f} s against {out[lead]['median_seconds']:.3f} s",
                  flush=True)
    return out


#: ``headline``'s versions: the card's command as it was (the teacher, eager) and the ways it can run now.
HEADLINE = {
    "teacher": ["+predictor.late_params.checkpoint=teacher", "+predictor.late_params.lazy=false"],
    "teacher_lazy": ["+predictor.late_params.checkpoint=teacher", "+predictor.late_params.lazy=true"],
    "student": ["+predictor.late_params.checkpoint=student", "+predictor.late_params.lazy=false"],
    "student_lazy": ["+predictor.late_params.checkpoint=student", "+predictor.late_params.lazy=true"],
    "default": [],
}


def headline(versions: Sequence[str], tasks: str = "paper20", limit: Optional[int] = None, seed: int = 0,
             depth: int = 3) -> dict:
    """Whole episodes of ``python -m overhang_framework predictor=hybrid planner=lookahead planner.depth=3``
    (seeded as the run seeds them) under each version of :data:`HEADLINE` (or ``name=override;override``),
    task by task, alternating which version plays first. Per version: every decision's seconds, their
    median and maximum, the reward; and whether the versions placed every block alike."""
    from overhang_framework.episode import play_run_episode

    specs = {}
    for v in versions:
        name, sep, overrides = v.partition("=")
        specs[name] = [o for o in overrides.split(";") if o] if sep else HEADLINE[name]
    models = {name: models_with_overrides(depth, specs[name]) for name in specs}
    cases = list(enumerate(task_list(tasks, limit)))

    def play(name):
        def run(case):
            index, task = case
            record = play_run_episode(models[name], task, index, 0, seed, None, None)
            return [(round(st["x"], 6), st["layer"], round(st["decision_time"], 9)) for st in record["steps"]], \
                record["reward"]
        return run

    figures = side_by_side(cases, {name: play(name) for name in specs}, label=lambda c: c[1].id, quiet=True)
    out = {"tasks": tasks, "limit": limit, "seed": seed, "depth": depth, "versions": {}}
    first = list(specs)[0]
    for name in specs:
        results = figures["versions"][name]["results"]
        times = [t for steps, _ in results for *_, t in steps]
        placements = [[(x, layer) for x, layer, _ in steps] for steps, _ in results]
        lead = [[(x, layer) for x, layer, _ in steps] for steps, _ in figures["versions"][first]["results"]]
        alike = sum(a == b for ep, ref in zip(placements, lead) for a, b in zip(ep, ref))
        out["versions"][name] = {
            "overrides": specs[name], "decisions": len(times), "median_seconds": float(np.median(times)),
            "max_seconds": float(np.max(times)), "mean_seconds": float(np.mean(times)),
            "episode_seconds": figures["versions"][name]["total"],
            "reward": float(np.mean([r for _, r in results])), "placements_alike_first": alike,
            "placements": int(sum(len(ep) for ep in placements))}
        v = out["versions"][name]
        print(f"{name:>13}: median decision {v['median_seconds']:.3f} s, max {v['max_seconds']:.2f} s, "
              f"episodes {v['episode_seconds']:.1f} s, reward {v['reward']:.3f}, "
              f"{alike} of {v['placements']} placements as {first}", flush=True)
    return out


def models_with_overrides(depth: int, overrides: Sequence[str]) -> dict:
    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config

    return build_models(compose_config(["predictor=hybrid", "planner=lookahead", f"planner.depth={depth}",
                                        *overrides]))


def main(argv: Optional[Sequence[str]] = None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.student",
                                 description=(__doc__ or "").splitlines()[0])
    ap.add_argument("what", choices=["speed", "decisions", "headline"])
    ap.add_argument("--versions", default="teacher,default",
                    help=f"headline: comma-separated versions, the reference first, from {', '.join(HEADLINE)} "
                         "or NAME=OVERRIDE;OVERRIDE (default teacher,default)")
    ap.add_argument("--checkpoints", default="teacher,student",
                    help="comma-separated networks (names or paths) or NAME=OVERRIDE;OVERRIDE versions of the "
                         "headline model, the reference first (default teacher,student)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--batch", type=int, default=64, help="images a forward pass (default 64)")
    ap.add_argument("--towers", type=int, default=4096)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--tasks", default="paper20", help="paper20 or a benchmark split (default paper20)")
    ap.add_argument("--limit", type=int, default=None, help="the first N tasks only")
    ap.add_argument("--depth", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--beta", type=float, default=2.4,
                    help="decisions: the softmax inverse temperature per metre for the choice probabilities (2.4)")
    ap.add_argument("--no-tables", action="store_true",
                    help="decisions: only the chosen actions, without every root action's exact score")
    ap.add_argument("--out", default=None, help="also write the JSON result to this file")
    args = ap.parse_args(argv)
    checkpoints = [c.strip() for c in args.checkpoints.split(",") if c.strip()]
    for name, value in (("--threads", args.threads), ("--batch", args.batch), ("--towers", args.towers),
                        ("--rounds", args.rounds), ("--depth", args.depth)):
        if value < 1:
            ap.error(f"{name} takes a whole number >= 1, got {value}")
    if len(checkpoints) < 2:
        ap.error(f"--checkpoints takes at least two networks, got {args.checkpoints!r}")
    started = time.perf_counter()
    if args.what == "speed":
        result = speed(checkpoints, args.threads, args.batch, args.towers, args.rounds)
    elif args.what == "headline":
        versions = [v.strip() for v in args.versions.split(",") if v.strip()]
        unknown = [v for v in versions if "=" not in v and v not in HEADLINE]
        if unknown:
            ap.error(f"--versions: unknown version {unknown[0]!r}; known: {', '.join(HEADLINE)}, or NAME=OVERRIDES")
        result = headline(versions, args.tasks, args.limit, args.seed, args.depth)
    else:
        result = decisions(args.tasks, args.limit, checkpoints, args.depth, args.seed, tables=not args.no_tables,
                           beta=args.beta)
    result["wall_seconds"] = time.perf_counter() - started
    if args.out:
        from overhang_framework.results import atomic_write_json

        atomic_write_json(args.out, result)
    print(json.dumps({k: v for k, v in result.items() if k != "rows"}))
    return result


if __name__ == "__main__":
    main()
