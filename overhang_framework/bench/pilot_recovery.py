"""Depth recovery through the server against offline: ``python -m overhang_framework.bench.pilot_recovery``.

    python -m overhang_framework.bench.pilot_recovery --out DIR [--time-scale 1] [--fit WORD ...]
        [PARTICIPANTS OVERRIDES...]

Runs, with the commands a lab types: the pilot (``python -m overhang_framework.experiment pilot``, its own
server, ``run_dir`` ``DIR/pilot``), the export of what the server stored, the offline simulation of the
same cohort with the same seed (``python -m overhang_framework.participants``, ``DIR/offline``), and the
fit of each log (``python -m overhang_framework.fit``, with ``--fit`` words such as ``'~models.cnn'``).
Then it counts the exported placements equal to the offline simulation's in the server's orders
(:func:`overhang_framework.experiment.pilot.offline_twin`), sets each participant's planted depth beside
the depth of its best model (by BIC), for the exported and the offline log, and writes ``DIR/recovery.json`` and ``DIR/recovery.md``: the
confusion of planted and fitted depths, the share recovered, and each step's wall time.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional, Sequence


def depth_recovery(fits_csv: Path, truth_csv: Path, id_column: str = "id") -> dict:
    """Planted against fitted depth (the best model by BIC) of every participant fitted in ``fits_csv``."""
    import pandas as pd

    from overhang_framework.fit.compare import winners

    best = winners(pd.read_csv(fits_csv)).set_index("participant")
    truth = pd.read_csv(truth_csv)
    pairs = [(int(r["depth"]), int(best.loc[str(r[id_column]), "depth"])) for _, r in truth.iterrows()
             if str(r[id_column]) in best.index]
    depths = sorted({d for pair in pairs for d in pair})
    confusion = {f"planted {a}": {f"fitted {b}": sum(1 for p in pairs if p == (a, b)) for b in depths}
                 for a in depths}
    right = sum(a == b for a, b in pairs)
    return {"participants": len(pairs), "recovered": right, "accuracy": right / len(pairs) if pairs else None,
            "confusion": confusion}


def _timed(args: Sequence[str]) -> float:
    started = time.monotonic()
    done = subprocess.run([sys.executable, *args], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if done.returncode != 0:
        raise SystemExit(f"error: {' '.join(args[:3])} failed: {done.stderr.strip().splitlines()[-1:]}")
    return round(time.monotonic() - started, 1)


def _table(name: str, r: dict) -> list[str]:
    cols = list(next(iter(r["confusion"].values())))
    lines = [f"**{name}**: {r['recovered']} of {r['participants']} depths recovered", "",
             "| | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    lines += [f"| {row} | " + " | ".join(str(v) for v in cells.values()) + " |"
              for row, cells in r["confusion"].items()]
    return lines + [""]


def parser() -> argparse.ArgumentParser:
    """The command's argument parser."""
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.pilot_recovery",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("overrides", nargs="*", help="the participants command's overrides (cohort=small seed=0)")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--time-scale", default="1")
    ap.add_argument("--serve", action="append", default=[], help="passed to the pilot's --serve")
    ap.add_argument("--fit", action="append", default=[], help="a word for the fit command (repeatable)")
    return ap


def main(argv: Optional[Sequence[str]] = None) -> int:
    from overhang_framework.results import atomic_write_json, atomic_write_text

    args = parser().parse_args(argv)
    out = args.out
    seconds = {}
    seconds["pilot"] = _timed(["-m", "overhang_framework.experiment", "pilot", "--out", str(out / "pilot"),
                               "--no-progress", "--time-scale", args.time_scale,
                               *[w for s in args.serve for w in ("--serve", s)], *args.overrides])
    seconds["export"] = _timed(["-m", "overhang_framework.experiment", "export", f"run_dir={out / 'pilot'}",
                                "--out", str(out / "pilot" / "log.jsonl")])
    seconds["offline"] = _timed(["-m", "overhang_framework.participants", *args.overrides, "progress=false",
                                 f"hydra.run.dir={out / 'offline'}"])
    result = {"overrides": args.overrides, "time_scale": float(args.time_scale), "fit": args.fit}
    import csv
    import json

    from overhang_framework.experiment.pilot import offline_twin, placements_alike

    records = [json.loads(line) for line in (out / "pilot" / "log.jsonl").read_text().splitlines()]
    with open(out / "pilot" / "participants.csv") as f:
        table = {r["id"]: r for r in csv.DictReader(f)}
    alike, total = placements_alike(records, offline_twin(args.overrides, records, table))
    result["alike"] = {"placements": total, "equal_offline_in_server_order": alike}
    for name, log in (("exported", out / "pilot" / "log.jsonl"), ("offline", out / "offline" / "log.jsonl")):
        seconds[f"fit {name}"] = _timed(["-m", "overhang_framework.fit", str(log), "--out", str(out / f"fit_{name}"),
                                         *args.fit, "progress=false"])
        result[name] = depth_recovery(out / f"fit_{name}" / "fits.csv", log.parent / "participants.csv")
    result["seconds"] = seconds
    atomic_write_json(out / "recovery.json", result)
    md = ["# Depth recovery: through the server and offline", "",
          f"`python -m overhang_framework.bench.pilot_recovery --out {out} --time-scale {args.time_scale} "
          + " ".join([*(f"--serve {s}" for s in args.serve), *(f"--fit '{w}'" for w in args.fit), *args.overrides])
          + "`", ""]
    md += [f"{alike} of {total} exported placements equal the offline simulation's in the server's orders", ""]
    md += _table("exported (the pilot through the server)", result["exported"])
    md += _table("offline (the participants command, same seed)", result["offline"])
    md += ["wall time: " + ", ".join(f"{k} {v:g} s" for k, v in seconds.items()), ""]
    atomic_write_text(out / "recovery.md", "\n".join(md))
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
