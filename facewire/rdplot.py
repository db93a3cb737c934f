"""The rate-quality picture of ``facewire bandwidth``: face and head SSIM against kbit/s.

On the left, the payload: two rows (rates amortised over the clip, and steady state after
the start-up message), two columns (face and head SSIM). On the right, one panel "on the
wire": face SSIM against kbit/s of IP packets in steady state, ours counted on a veth link
(sender to receiver, a star; both directions, a hollow star), the codecs' a model (over
SRTP, media only). Each codec is a line through its envelope over the resolution ladder, its
other points faint.
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

    from facewire.rdreport import COMPARED

    ours = result["ours"]
    labels = {name: c["label"] for name, c in result["settings"]["codecs"].items()}
    fig = plt.figure(figsize=(18, 9))
    grid = fig.add_gridspec(2, 3)
    axes = [[fig.add_subplot(grid[row, col]) for col in range(2)] for row in range(2)]
    for row, (accounting, row_title) in enumerate(ROWS):
        for col, region in enumerate(COMPARED):
            ax = axes[row][col]
            _codecs(ax, result["points"], labels, region, accounting, "payload")
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
            _axes(ax, f"kbit/s payload, {row_title}", region, f"{region} region, {accounting}")
    _wire_panel(fig.add_subplot(grid[:, 2]), result, labels)
    # One legend for the panels, above them: inside a panel it can hide our star.
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


def _codecs(
    ax: Any,
    points: list[dict[str, Any]],
    labels: dict[str, str],
    region: str,
    accounting: str,
    level: str,
) -> None:
    """Each codec's points (faint) and its envelope over the ladder (a line)."""
    from facewire.rdreport import codec_curve

    for codec, label in labels.items():
        colour = COLOURS.get(codec)
        pts = [p for p in points if p["codec"] == codec]
        ax.scatter(
            [p["kbps"][level][accounting] for p in pts],
            [p["ssim"][region] for p in pts],
            s=14,
            color=colour,
            alpha=0.3,
            linewidths=0,
        )
        curve = codec_curve(points, codec, region, accounting, level)
        if curve:
            ax.plot(*zip(*curve, strict=True), "o-", color=colour, label=label, ms=5)


def _axes(ax: Any, xlabel: str, region: str, title: str) -> None:
    ax.set_xscale("log")
    ax.margins(x=0.12, y=0.08)
    _rate_ticks(ax)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(f"{region} SSIM (luma)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)


def _wire_panel(ax: Any, result: dict[str, Any], labels: dict[str, str]) -> None:
    """Face SSIM against kbit/s of IP packets, steady: ours counted, the codecs' modelled."""
    region = "face"
    _codecs(ax, result["points"], labels, region, "steady", "wire")
    ours = result["ours"]
    wire = ours.get("wire", {})
    ssim = ours["quality"]["ssim"][region]
    if wire.get("source") == "measured":
        up, total = wire["kbps"]["up"], wire["kbps"]["total"]
        ax.plot([up, total], [ssim, ssim], "-", color=OURS, lw=0.8)
        stars = ax.plot(up, ssim, "*", color=OURS, ms=18, label="facewire, sender to receiver")
        stars += ax.plot(
            total, ssim, "*", color=OURS, ms=14, mfc="white", label="facewire, both ways"
        )
        ax.annotate(
            f"facewire, measured on a veth link\n{ssim:.3f} at {up:.1f} kbit/s "
            f"({total:.1f} both ways)",
            (up, ssim),
            textcoords="offset points",
            xytext=(10, -30),
            fontsize=9,
        )
        ax.legend(handles=stars, loc="best", fontsize=9)
    else:
        ax.text(
            0.03,
            0.97,
            "facewire: unknown (not counted on a link)",
            transform=ax.transAxes,
            va="top",
            fontsize=10,
        )
    _axes(
        ax,
        "kbit/s on the wire (IP packets), steady: ours counted on a link,\n"
        "the codecs' a model (over SRTP, media only, RTCP not counted)",
        region,
        "on the wire: face region, steady",
    )


def _rate_ticks(ax: Any) -> None:
    """Ticks at powers of two (and 1.5 times them over a short range), labelled as numbers."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter

    lo, hi = ax.get_xlim()
    steps = (1.0,) if hi / lo > 16 else (1.0, 1.5)
    ticks = [m * 2.0**k for k in range(-6, 16) for m in steps if lo <= m * 2.0**k <= hi]
    ax.xaxis.set_major_locator(FixedLocator(ticks))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
