"""The Hydra callback that writes ``results.csv`` at the end of every multirun.

It is listed in the project's ``config.yaml`` (``hydra.callbacks``), so every
sweep gets it; it runs where the sweep was launched, after every job returned,
whichever launcher ran the jobs. A sweep with failed jobs names them, each
with the first line of its error, and ends with exit status 1 after writing
``results.csv``.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig


class SweepResults(Callback):
    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        from overhang_framework.report.aggregate import describe, write_results

        sweep_dir = Path(config.hydra.sweep.dir)
        if not sweep_dir.is_dir():
            return
        path, rows = write_results(sweep_dir)
        print(f"{path}: {describe(rows)}")
        if any(r["status"] == "failed" for r in rows):
            sys.exit(1)
