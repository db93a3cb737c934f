"""The rate-quality picture of ``facewire bandwidth``: face and head SSIM against kbit/s.

Two rows (rates amortised over the clip, and steady state after the start-up message), two
columns (face and head SSIM). Each codec is a line through its envelope over the resolution
ladder, its other points faint; our call is a star.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

COLOURS = {"h264": "#1f77b4", "vp9": "#2ca02c", "av1": "#d62728"}
OURS = "#000000"
ROWS = (
    ("amortised", "whole clip (our snapshot, their key frame)"),
    ("steady", "steady state (after them)"),
)


def plot(result: dict[str, Any], path: Path) -> None:
    """Draw ``result`` (as ``facewire bandwidth --json`` writes it) to a PNG at ``path``."""
    import matplotlib

    matplotlib.use("Agg")  # files only: no display here
    import matplotlib.pyplot as plt

    from facewire.rdreport import COMPARED, codec_curve

    ours = result["ours"]
    labels = {name: c["label"] for name, c in result["settings"]["codecs"].items()}
    fig, axes = plt.subplots(2, 2, figsize=(12, 9), squeeze=False)
    for row, (accounting, row_title) in enumerate(ROWS):
        for col, region in enumerate(COMPARED):
            ax = axes[row][col]
            for codec, label in labels.items():
                colour = COLOURS.get(codec)
                pts = [p for p in result["points"] if p["codec"] == codec]
                ax.scatter(
                    [p["kbps"]["payload"][accounting] for p in pts],
                    [p["ssim"][region] for p in pts],
                    s=14,
                    color=colour,
                    alpha=0.3,
                    linewidths=0,
                )
                curve = codec_curve(result["points"], codec, region, accounting)
                if curve:
                    ax.plot(*zip(*curve, strict=True), "o-", color=colour, label=label, ms=5)
            rate = ours["kbps"]["payload"][accounting]
            ssim = ours["quality"]["ssim"][region]
            ax.plot(rate, ssim, "*", color=OURS, ms=18, label="facewire (our call)")
            ax.annotate(
                f"facewire\n{ssim:.3f} at {rate:.1f} kbit/s",
                (rate, ssim),
                textcoords="offset points",
                xytext=(10, -22),
                fontsize=9,
            )
            ax.set_xscale("log")
            ax.margins(x=0.12, y=0.08)
            _rate_ticks(ax)
            ax.set_xlabel(f"kbit/s payload, {row_title}")
            ax.set_ylabel(f"{region} SSIM (luma)")
            ax.set_title(f"{region} region, {accounting}")
            ax.grid(True, which="both", alpha=0.3)
    # One legend for the four panels, above them: inside a panel it can hide our star.
    handles, names = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, names, loc="upper center", ncol=4, fontsize=9, bbox_to_anchor=(0.5, 0.955))
    name = Path(result["input"]).name
    fig.suptitle(
        f"{name}: {result['width']}x{result['height']}, {result['frames']} frames at "
        f"{result['fps']:.0f} fps; each codec's line is its best rung of the resolution "
        "ladder (faint: every rung)",
        fontsize=11,
    )
    fig.tight_layout(rect=(0, 0, 1, 0.92))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    logger.info("wrote %s", path)


def _rate_ticks(ax: Any) -> None:
    """Ticks at powers of two (and 1.5 times them over a short range), labelled as numbers."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter

    lo, hi = ax.get_xlim()
    steps = (1.0,) if hi / lo > 16 else (1.0, 1.5)
    ticks = [m * 2.0**k for k in range(-6, 16) for m in steps if lo <= m * 2.0**k <= hi]
    ax.xaxis.set_major_locator(FixedLocator(ticks))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
