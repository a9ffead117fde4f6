"""Physical prediction by construction stage (the paper's Fig. 4).

Every executed placement is a positive sample of perceived plausibility: for each, each predictor
gives the probability that the tower stands after it, and its log-likelihood is
``log(clip(p, ε, 1 − ε))``. Timed-out records place nothing and are skipped. Predictors are asked with
the logged (continuous) ``x``, all placements made from one state (same tower, same remaining blocks)
in one batch, and the distinct states of the whole log in one ``predict_many`` call per predictor,
each state with its own generator seeded from the seed and the state's canonical key (so the IPE's
noise does not depend on what else is in the log).

By construction stage: the number of blocks in the tower after the placement (the tower being judged;
2 = the first placement on the ground block). The mean over a group's placements at that stage, with a
95% CI by bootstrap over participants (participants resampled with replacement; the pooled mean of
their placements).

The paper's two claims, tested per group on paired differences of log-likelihoods (the same
placements, so the CIs are of the difference itself):

* ``ipe_minus_cnn`` = ``LL_ipe − LL_cnn`` by stage: > 0 where the IPE fits better. The paper's
  "residual with respect to the veridical simulator", ``(LL_ipe − LL_vrd) − (LL_cnn − LL_vrd)``, is
  this same number (the veridical term cancels), so it is computed and labelled plainly. The paper:
  the IPE ahead early (a modest advantage), the CNN later (p < .001). :func:`crossover` says where
  the CI lies on each side of 0 and whether that is the paper's direction.
* ``ipe_minus_veridical`` and ``cnn_minus_veridical`` over all placements: > 0 where the approximate
  model fits better than the veridical baseline (the paper: both do, p < .001).

A difference is credible where its 95% CI excludes 0 and at least :data:`MIN_PARTICIPANTS`
participants have placements there; stages are judged one by one, without correction for their number.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.behaviour.shared import (Section, bootstrap_ci, colour, markdown_table, save_figure,
                                                 write_csv)
from overhang_framework.geometry import Action, Block, Geometry, check_width
from overhang_framework.interfaces import State

LABELS = {"veridical": "veridical", "ipe": "IPE", "cnn": "visual heuristic (CNN)", "hybrid": "hybrid"}
#: Paired differences of log-likelihoods: name, minuend, subtrahend.
DIFFERENCES = (("ipe_minus_cnn", "ipe", "cnn"), ("ipe_minus_veridical", "ipe", "veridical"),
               ("cnn_minus_veridical", "cnn", "veridical"))
#: Fewer participants than this at a stage (or overall) and no difference is called credible there.
MIN_PARTICIPANTS = 5
PAPER_DIRECTION = "the IPE ahead early, the CNN later"
PAPER_BASELINE = "both approximate models fit better than the veridical baseline, p < .001"


def _override_key(override: str) -> tuple[str, str]:
    """The prefix (``+``, ``++``, ``~`` or none) and dotted key of a Hydra override."""
    head = override.split("=", 1)[0].strip()
    key = head.lstrip("+~")
    return head[:len(head) - len(key)], key


def targets_predictor(override: str) -> bool:
    """Whether a ``--world`` override sets a predictor's parameter (``predictor.K=10``)."""
    return _override_key(override)[1].startswith("predictor.")


def predictor_configs(names: Sequence[str], overrides: Sequence[str] = ()) -> dict[str, dict]:
    """Each named predictor's config, composed as the main job composes it, with ``overrides``.

    An override of a predictor's parameter (``predictor.K=10``) goes to the predictors whose config has
    that key (``+predictor.a.b=...``: whose config has ``predictor.a``); one that no named predictor
    has is an error. Every other override goes to all of them.
    """
    from omegaconf import OmegaConf

    from overhang_framework.config import compose_config
    from overhang_framework.errors import OverhangError

    general = [o for o in overrides if not targets_predictor(o)]
    own = [o for o in overrides if targets_predictor(o)]
    missing = object()
    used: set[str] = set()
    out = {}
    for name in names:
        try:
            cfg = compose_config([*general, f"predictor={name}"])
            mine = []
            for o in own:
                prefix, key = _override_key(o)
                node = key.rsplit(".", 1)[0] if "+" in prefix else key
                if OmegaConf.select(cfg, node, default=missing) is not missing:
                    mine.append(o)
            if mine:
                cfg = compose_config([*general, f"predictor={name}", *mine])
                used.update(mine)
        except Exception as exc:  # a bad override: one line, as the main job reports it
            raise OverhangError(f"--world (predictor {name}): {' '.join(str(exc).split()) or type(exc).__name__}"
                                ) from None
        out[name] = OmegaConf.to_container(cfg.predictor, resolve=True)
    unused = [o for o in own if o not in used]
    if unused:
        raise OverhangError(f"--world {unused[0]}: none of the predictors {', '.join(names)} has that parameter")
    return out


def build_predictors(names: Sequence[str], world, overrides: Sequence[str] = ()) -> dict:
    """Each named predictor, built through the plugin registry from its config (as the main job builds it),
    on ``world``."""
    from overhang_framework.plugins import Registry

    registry = Registry()
    known = registry.names("predictor")
    unknown = [n for n in names if n not in known]
    if unknown:
        from overhang_framework.errors import OverhangError

        raise OverhangError(f"--predictors: unknown predictor {', '.join(map(repr, unknown))}; "
                            f"installed predictors: {', '.join(sorted(known))}")
    configs = predictor_configs(names, overrides)
    return {name: registry.create("predictor", configs[name], world=world) for name in names}


def physics_of(predictor, world) -> Optional[str]:
    """The physics a simulating predictor (the IPE, the veridical) runs on; ``None`` for one that does not simulate."""
    backend = getattr(predictor, "backend_name", None)
    if backend is None:
        return None
    return getattr(world, "physics_name", "world") if backend == "world" else str(backend)


def describe(name: str, predictor, world) -> str:
    """One line on what ``predictor`` is: the physics it simulates with and its noise, or its checkpoint."""
    physics = physics_of(predictor, world)
    if physics is not None:
        noise, k = getattr(predictor, "noise", None), int(getattr(predictor, "K", 1))
        where = f"the `{physics}` physics" + (" (the world's)" if predictor.backend_name == "world" else "")
        if noise is None or (noise.zero and k == 1):
            return f"`{name}`: the noise-free verdicts of {where}"
        sig = {noise.position, noise.gravity, noise.friction}
        sigma = (f"σ = {noise.position:g} (position, gravity, friction)" if len(sig) == 1 else
                 f"σ = {noise.position:g} (position), {noise.gravity:g} (gravity), {noise.friction:g} (friction)")
        return f"`{name}`: {k} noisy simulations per placement, {sigma}, on {where}"
    names, switch = getattr(predictor, "names", None), getattr(predictor, "switch", None)
    if isinstance(names, dict) and switch is not None:
        return f"`{name}`: `{names.get('early')}` below {switch} blocks, `{names.get('late')}` from {switch}"
    model = getattr(predictor, "model", None)
    path = getattr(model, "path", None)
    if path is not None:
        return f"`{name}`: the image classifier `{Path(path).name}`"
    return f"`{name}`: {type(predictor).__name__}"


def _brief(predictor, physics: str) -> str:
    """``describe`` in a figure title's few words."""
    noise, k = getattr(predictor, "noise", None), int(getattr(predictor, "K", 1))
    if noise is None or (noise.zero and k == 1):
        return f"{physics} physics, noise-free"
    return f"{physics} physics, K = {k}, σ = {max(noise.position, noise.gravity, noise.friction):g}"


def state_seed(seed: int, key: tuple) -> int:
    """A generator seed from the analysis seed and a state's canonical key (stable across runs and logs)."""
    return int.from_bytes(hashlib.sha256(repr((seed, key)).encode()).digest()[:8], "little")


def placements(df: pd.DataFrame) -> pd.DataFrame:
    """The executed placements (timed-out records left out) with ``n_blocks`` (after the placement)."""
    done = df[~df["timed_out"]].copy()
    done["n_blocks"] = done["tower_before"].map(len) + 1
    return done


def probabilities(done: pd.DataFrame, predictors: dict, seed: int) -> dict[str, np.ndarray]:
    """Each predictor's probability for every row of ``done``: one request per distinct state, all in one call."""
    states: dict[tuple, tuple[State, dict]] = {}
    index = []
    for before, seq, step, x, layer in zip(done["tower_before"], done["sequence"], done["step"], done["x"],
                                           done["layer"]):
        geometry = Geometry(tuple(Block(check_width(w), float(bx), int(bl)) for w, bx, bl in before))
        remaining = tuple(float(w) for w in seq[step:])
        key = (geometry.key, tuple(round(w, 6) for w in remaining))
        if key not in states:
            states[key] = (State(geometry, remaining), {})
        actions = states[key][1]
        action = Action(float(x), int(layer))
        actions.setdefault(action, len(actions))
        index.append((key, actions[action]))
    keys = list(states)
    requests = [(states[k][0], list(states[k][1])) for k in keys]
    position = {k: i for i, k in enumerate(keys)}
    out = {}
    for name, predictor in predictors.items():
        rngs = [np.random.default_rng(state_seed(seed, k)) for k in keys]
        answers = predictor.predict_many(requests, rngs)
        out[name] = np.array([float(answers[position[k]][j]) for k, j in index], dtype=float)
    return out


def log_likelihoods(p: np.ndarray, epsilon: float) -> np.ndarray:
    return np.log(np.clip(p, epsilon, 1 - epsilon))


def differences(values: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The paired differences of :data:`DIFFERENCES` whose two predictors are among ``values``."""
    return {name: values[a] - values[b] for name, a, b in DIFFERENCES if a in values and b in values}


def _cell(at: pd.DataFrame, name: str, n_boot: int, seed: int) -> dict:
    per = at.groupby("participant")[name].agg(["sum", "count"])
    lo, hi = bootstrap_ci(per["sum"].to_numpy(), per["count"].to_numpy(), n_boot, seed)
    return {"measure": name, "placements": len(at), "participants": len(per), "mean": float(at[name].mean()),
            "ci_low": lo, "ci_high": hi}


def _frame(done: pd.DataFrame, values: dict[str, np.ndarray]) -> pd.DataFrame:
    frame = done[["group", "participant", "n_blocks"]].copy()
    for name, v in values.items():
        frame[name] = v
    return frame


def by_stage(done: pd.DataFrame, values: dict[str, np.ndarray], order: Sequence[str], n_boot: int,
             seed: int) -> pd.DataFrame:
    """Mean of each value column by group and ``n_blocks``, with its bootstrap CI over participants."""
    rows = []
    frame = _frame(done, values)
    for g in order:
        sub = frame[frame["group"] == g]
        for n in sorted(sub["n_blocks"].unique()):
            at = sub[sub["n_blocks"] == n]
            rows += [{"group": g, "n_blocks": int(n), **_cell(at, name, n_boot, seed)} for name in values]
    return pd.DataFrame(rows)


def overall(done: pd.DataFrame, values: dict[str, np.ndarray], order: Sequence[str], n_boot: int,
            seed: int) -> pd.DataFrame:
    """Mean of each value column by group over all its placements, with its bootstrap CI over participants."""
    frame = _frame(done, values)
    rows = []
    for g in order:
        at = frame[frame["group"] == g]
        if len(at):
            rows += [{"group": g, **_cell(at, name, n_boot, seed)} for name in values]
    return pd.DataFrame(rows)


def side(row) -> int:
    """+1 where the CI lies above 0, −1 where below, 0 where it includes 0, is undefined, or rests on
    fewer than :data:`MIN_PARTICIPANTS` participants."""
    lo, hi = float(row["ci_low"]), float(row["ci_high"])
    if int(row["participants"]) < MIN_PARTICIPANTS or not (np.isfinite(lo) and np.isfinite(hi)):
        return 0
    return 1 if lo > 0 else -1 if hi < 0 else 0


@dataclass
class Crossover:
    """Where ``LL_ipe − LL_cnn`` of one group is credibly above 0 (IPE ahead), below (CNN ahead), neither
    (its CI includes 0), or not judged (too few participants), by stage."""

    group: str
    ipe_ahead: list[int] = field(default_factory=list)
    cnn_ahead: list[int] = field(default_factory=list)
    unclear: list[int] = field(default_factory=list)
    too_few: list[int] = field(default_factory=list)

    @property
    def verdict(self) -> str:
        """``matches`` (the paper's direction: every IPE-ahead stage before every CNN-ahead one),
        ``reverse``, ``alternates``, ``cnn_only``, ``ipe_only`` or ``none`` (nothing credible)."""
        if self.ipe_ahead and self.cnn_ahead:
            if max(self.ipe_ahead) < min(self.cnn_ahead):
                return "matches"
            if max(self.cnn_ahead) < min(self.ipe_ahead):
                return "reverse"
            return "alternates"
        if self.cnn_ahead:
            return "cnn_only"
        if self.ipe_ahead:
            return "ipe_only"
        return "none"

    @property
    def matches_paper(self) -> bool:
        return self.verdict == "matches"


def crossover(stage: pd.DataFrame, group: str) -> Crossover:
    """The :class:`Crossover` of ``group`` from the stage table (measure ``ipe_minus_cnn``)."""
    out = Crossover(group)
    rows = stage[(stage["group"] == group) & (stage["measure"] == "ipe_minus_cnn")].sort_values("n_blocks")
    for _, row in rows.iterrows():
        n = int(row["n_blocks"])
        if int(row["participants"]) < MIN_PARTICIPANTS:
            out.too_few.append(n)
        else:
            {1: out.ipe_ahead, -1: out.cnn_ahead, 0: out.unclear}[side(row)].append(n)
    return out


def stages_text(stages: Sequence[int]) -> str:
    """``[2, 3, 4, 6]`` as ``2–4 and 6 blocks``: runs of consecutive stages joined."""
    runs: list[list[int]] = []
    for n in sorted(stages):
        if runs and n == runs[-1][-1] + 1:
            runs[-1].append(n)
        else:
            runs.append([n])
    parts = [str(r[0]) if len(r) == 1 else f"{r[0]}–{r[-1]}" for r in runs]
    text = parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " and " + parts[-1]
    return f"{text} blocks"


def _ci(row) -> str:
    return f"{row['mean']:+.3f} [{row['ci_low']:+.3f}, {row['ci_high']:+.3f}]"


def crossover_sentence(c: Crossover, stage: pd.DataFrame) -> str:
    """Where ``LL_ipe − LL_cnn`` is credibly on each side of 0, where not, and whether that is the paper's
    direction."""
    rows = stage[(stage["group"] == c.group) & (stage["measure"] == "ipe_minus_cnn")].set_index("n_blocks")

    def cells(stages):
        if len(stages) == 1:
            return _ci(rows.loc[stages[0]])
        return "; ".join(f"{n}: {_ci(rows.loc[n])}" for n in stages)

    sides = []
    if c.ipe_ahead:
        sides.append(f"credibly above 0 (the IPE fits better) at {stages_text(c.ipe_ahead)} ({cells(c.ipe_ahead)})")
    if c.cnn_ahead:
        sides.append(f"credibly below 0 (the CNN fits better) at {stages_text(c.cnn_ahead)} ({cells(c.cnn_ahead)})")
    text = "LL_ipe − LL_cnn is " + (" and ".join(sides) if sides else "not credibly different from 0 at any stage")
    if c.unclear:
        text += f"; its CI includes 0 at {stages_text(c.unclear)}"
    if c.too_few:
        text += f"; fewer than {MIN_PARTICIPANTS} participants at {stages_text(c.too_few)} (not judged)"
    verdict = {
        "matches": f"This matches the paper's direction ({PAPER_DIRECTION}).",
        "reverse": f"This is the reverse of the paper's direction ({PAPER_DIRECTION}).",
        "alternates": f"The credible stages alternate between the two, which does not match the paper's single "
                      f"crossover ({PAPER_DIRECTION}).",
        "cnn_only": f"The IPE is credibly ahead at no stage, so there is no credible crossover: this does not match "
                    f"the paper ({PAPER_DIRECTION}).",
        "ipe_only": f"The CNN is credibly ahead at no stage, so there is no credible crossover: this does not match "
                    f"the paper ({PAPER_DIRECTION}).",
        "none": f"No credible crossover in either direction: this does not match the paper ({PAPER_DIRECTION}).",
    }[c.verdict]
    return f"{text}. {verdict}"


def baseline_sentence(group: str, total: pd.DataFrame) -> Optional[str]:
    """Whether each approximate model fits credibly better than the veridical baseline over all placements."""
    rows = total[total["group"] == group].set_index("measure")
    found = [(m, rows.loc[f"{m}_minus_veridical"]) for m in ("ipe", "cnn") if f"{m}_minus_veridical" in rows.index]
    if not found:
        return None
    numbers = ", ".join(f"{m.upper()} {_ci(r)}" for m, r in found)
    head = f"Over all placements, LL_model − LL_veridical (mean per placement, 95% CI): {numbers}"
    participants = int(found[0][1]["participants"])
    if participants < MIN_PARTICIPANTS:
        return f"{head}; {participants} participant(s), too few (< {MIN_PARTICIPANTS}) to judge."
    words = {1: "fits credibly better than", -1: "fits credibly worse than", 0: "is not credibly different from"}
    verdicts = [(m, side(r)) for m, r in found]
    name = {"ipe": "the IPE", "cnn": "the CNN"}
    if len(verdicts) == 2 and all(s == 1 for _, s in verdicts):
        return f"{head}. Both approximate models fit credibly better than the veridical baseline, as in the paper."
    said = "; ".join(f"{name[m]} {words[s]} the veridical baseline" for m, s in verdicts)
    same = all(s == 1 for _, s in verdicts)
    return f"{head}. {said[0].upper() + said[1:]}: {'as in' if same else 'unlike'} the paper ({PAPER_BASELINE})."


def figure(stage: pd.DataFrame, order: Sequence[str], names: Sequence[str], epsilon: float, n_boot: int,
           physics: str = ""):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from matplotlib.ticker import MaxNLocator

    has_adv = (stage["measure"] == "ipe_minus_cnn").any()
    groups = [g for g in order if (stage["group"] == g).any()]
    fig, axes = plt.subplots(len(groups), 2 if has_adv else 1, figsize=(11 if has_adv else 5.5, 3.4 * len(groups)),
                             squeeze=False)
    pcol = {"veridical": "#555555", "ipe": "#2f6db5", "cnn": "#d0452f", "hybrid": "#3a9a5b"}
    extra = iter(["#8e5bb5", "#b5875b", "#2aa3a3", "#c2559a"])
    for name in names:
        pcol.setdefault(name, next(extra, "#000000"))
    for r, g in enumerate(groups):
        ax = axes[r][0]
        for name in names:
            d = stage[(stage["group"] == g) & (stage["measure"] == name)].sort_values("n_blocks")
            ax.plot(d["n_blocks"], d["mean"], "o-", color=pcol[name], label=LABELS.get(name, name))
            ax.fill_between(d["n_blocks"], d["ci_low"], d["ci_high"], color=pcol[name], alpha=0.2)
        ax.set_ylabel(f"{g}\nmean log-likelihood")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_xlabel("blocks in the scene (after the placement)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        if r == 0:
            ax.set_title(f"log-likelihood of executed placements (ε = {epsilon:g}; 95% CI)"
                         + (f"\n{physics}" if physics else ""), fontsize=9)
        if has_adv:
            ax = axes[r][1]
            d = stage[(stage["group"] == g) & (stage["measure"] == "ipe_minus_cnn")].sort_values("n_blocks")
            ax.axhline(0, color="black", lw=0.8)
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            ax.plot(d["n_blocks"], d["mean"], "-", color=colour(g, order))
            ax.fill_between(d["n_blocks"], d["ci_low"], d["ci_high"], color=colour(g, order), alpha=0.2)
            for _, row in d.iterrows():
                s = side(row)
                face = {1: pcol["ipe"], -1: pcol["cnn"], 0: "white"}[s]
                ax.plot(row["n_blocks"], row["mean"], "o", ms=7, mfc=face, mec=face if s else "dimgrey")
            c = crossover(stage, g)
            said = {"matches": "matches the paper", "reverse": "reverse of the paper"}.get(c.verdict,
                                                                                          "no paper crossover")
            ahead = [f"IPE ahead: {stages_text(c.ipe_ahead)}"] if c.ipe_ahead else []
            ahead += [f"CNN ahead: {stages_text(c.cnn_ahead)}"] if c.cnn_ahead else []
            ax.text(0.02, 0.04, f"{'; '.join(ahead) or 'no stage credible'} ({said})", transform=ax.transAxes,
                    fontsize=8, color="dimgrey")
            ax.set_xlabel("blocks in the scene (after the placement)")
            ax.set_ylabel("IPE − CNN\nLL_ipe − LL_cnn per placement")
            ax.grid(alpha=0.3)
            if r == 0:
                ax.set_title(f"> 0: IPE fits better; < 0: CNN fits better; filled: 95% CI excludes 0\n"
                             f"({n_boot} bootstrap resamples of participants; paper: IPE ahead early, CNN later)",
                             fontsize=9)
    fig.align_ylabels()
    fig.tight_layout(w_pad=2.5)
    return fig


def section(df: pd.DataFrame, out: Path, order, compare, settings, world) -> Section:
    done = placements(df)
    skipped = int(df["timed_out"].sum())
    names = list(settings.predictors)
    predictors = build_predictors(names, world, settings.world_overrides)
    probs = probabilities(done, predictors, settings.seed)
    values = {n: log_likelihoods(p, settings.epsilon) for n, p in probs.items()}
    values.update(differences(values))
    stage = by_stage(done, values, order, settings.bootstrap, settings.seed)
    total = overall(done, values, order, settings.bootstrap, settings.seed)
    per = done[["participant", "group", "task_id", "trial", "step", "n_blocks", "x", "layer", "stable"]].copy()
    for n, p in probs.items():
        per[f"p_{n}"] = p
        per[f"ll_{n}"] = values[n]
    write_csv(per, out / "fig4_placements.csv")
    write_csv(stage, out / "fig4_loglik.csv")
    write_csv(total, out / "fig4_overall.csv")
    files = ["fig4_loglik.csv", "fig4_overall.csv", "fig4_placements.csv"]
    groups = [g for g in order if (per["group"] == g).any()]
    has_adv = "ipe_minus_cnn" in values
    crossovers = {g: crossover(stage, g) for g in groups} if has_adv else {}
    if has_adv:
        write_csv(pd.DataFrame([{"group": g, "ipe_ahead": " ".join(map(str, c.ipe_ahead)),
                                 "cnn_ahead": " ".join(map(str, c.cnn_ahead)),
                                 "not_credible": " ".join(map(str, c.unclear)),
                                 "too_few_participants": " ".join(map(str, c.too_few)),
                                 "verdict": c.verdict, "matches_paper": c.matches_paper}
                                for g, c in crossovers.items()]), out / "fig4_crossover.csv")
        files.insert(1, "fig4_crossover.csv")
    rows = []
    for g in groups:
        at = per[per["group"] == g]
        rows.append([g, len(at), at["participant"].nunique()] + [f"{at[f'll_{n}'].mean():.3f}" for n in names])
    text = markdown_table(["group", "placements", "participants"] + [f"mean LL {n}" for n in names], rows)
    findings = []
    for g in groups:
        said = [crossover_sentence(crossovers[g], stage)] if has_adv else []
        base = baseline_sentence(g, total)
        said += [base] if base else []
        if said:
            findings.append(f"- **{g}.** " + " ".join(said))
    if findings:
        text += ("\n\nFindings (95% CIs by bootstrap over participants; a difference is credible where its CI "
                 f"excludes 0 and at least {MIN_PARTICIPANTS} participants have placements there; stages are "
                 "judged one by one, without correction for their number):\n\n" + "\n".join(findings))
    if has_adv:
        adv = stage[stage["measure"] == "ipe_minus_cnn"]
        side_word = {1: "IPE", -1: "CNN", 0: "neither"}
        text += "\n\n" + markdown_table(
            ["group", "blocks", "placements", "participants", "LL_ipe − LL_cnn [95% CI]", "credibly ahead"],
            [[r["group"], int(r["n_blocks"]), int(r["placements"]), int(r["participants"]), _ci(r),
              side_word[side(r)] if int(r["participants"]) >= MIN_PARTICIPANTS else "too few participants"]
             for _, r in adv.iterrows()])
        text += ("\n\nLL_ipe − LL_cnn is also the paper's \"residual with respect to the veridical simulator\": "
                 "(LL_ipe − LL_vrd) − (LL_cnn − LL_vrd) is the same number, the veridical term cancelling.")
    else:
        text += "\n\nThe IPE − CNN comparison by stage needs the predictors ipe and cnn."
    described = [describe(n, predictors[n], world) for n in names]
    text += "\n\nPredictors: " + "; ".join(described) + "."
    phys = {n: physics_of(predictors[n], world) for n in names}
    if phys.get("ipe") and phys.get("veridical") and phys["ipe"] != phys["veridical"]:
        text += (f" The IPE simulates with the `{phys['ipe']}` physics and the veridical baseline is the "
                 f"`{phys['veridical']}` physics: the IPE's difference from the baseline is its noise and the "
                 "difference between the two physics together (`--world predictor.backend=world` makes the IPE "
                 "simulate with the world's physics).")
    text += (f"\n\nRules: every executed placement is a positive sample; LL = log(clip(p, ε, 1 − ε)) with ε = "
             f"{settings.epsilon:g}; predictors asked with the logged continuous x, one batch per distinct state, "
             f"each state's generator seeded from seed {settings.seed} and its canonical key; stage = blocks in the "
             f"tower after the placement; 95% CIs by bootstrap over participants ({settings.bootstrap} resamples, "
             f"percentile). Timed-out records skipped: {skipped}. Distinct states asked: "
             f"{len(set(zip(done['participant'], done['trial'], done['step'])))} placements in "
             f"{_distinct_states(done)} states.")
    if len(stage):
        short = [f"{n}: {_brief(predictors[n], phys[n])}" for n in names if phys.get(n)]
        save_figure(figure(stage, order, names, settings.epsilon, settings.bootstrap, "; ".join(short)),
                    out / "fig4_loglik.png")
        files.insert(1, "fig4_loglik.png")
    else:
        text += "\n\nNo executed placement: no figure."
    return Section("Physical prediction by construction stage (Fig. 4)", text, files)


def _distinct_states(done: pd.DataFrame) -> int:
    return len({(tuple(map(tuple, b)), tuple(s[k:])) for b, s, k in
                zip(done["tower_before"], done["sequence"], done["step"])})
