"""The figure the analyses share: measures against the number of blocks, one line per model."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from overhang_framework.results import atomic_output


def plot_by_blocks(summary: Sequence[dict], path: Path, title: str, series: str,
                   panels: Sequence[tuple[str, str]], label: Callable[[object], str] = str,
                   colormap: Optional[str] = None) -> None:
    """One panel per ``(key, y label)`` of ``panels``, saved as a PNG atomically.

    ``summary`` rows have ``n_blocks``, the ``series`` key (one line per value,
    in order of first appearance, named by ``label``), and for each panel's
    ``key`` its value and ``key_sem`` (drawn as error bars). ``colormap``
    colours the lines along a matplotlib colour map (default: the colour cycle).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    values = list(dict.fromkeys(r[series] for r in summary))
    colors = (plt.get_cmap(colormap)(np.linspace(0, 0.9, len(values))) if colormap
              else [None] * len(values))
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.6), constrained_layout=True)
    axes = np.atleast_1d(axes)
    for value, color in zip(values, colors):
        sel = sorted((r for r in summary if r[series] == value), key=lambda r: r["n_blocks"])
        n = [r["n_blocks"] for r in sel]
        for ax, (key, _) in zip(axes, panels):
            ax.errorbar(n, [r[key] for r in sel], yerr=[r[f"{key}_sem"] for r in sel], marker="o", ms=4,
                        capsize=2, color=color, label=label(value))
    for ax, (_, ylabel) in zip(axes, panels):
        ax.set_ylabel(ylabel)
        ax.set_xlabel("blocks in the tower after the action")
        ax.set_xticks(sorted({r["n_blocks"] for r in summary}))
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    try:
        with atomic_output(path) as tmp:
            fig.savefig(tmp, dpi=150, format="png")
    finally:
        plt.close(fig)
