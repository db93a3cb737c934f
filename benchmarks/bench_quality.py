"""Picture quality of a call against its input: face, head and frame SSIM and PSNR.

Usage:
  PYOPENGL_PLATFORM=egl python benchmarks/bench_quality.py --input CLIP [--output OUT.mp4]
      [--fast] [--code CHECKOUT] [--json RESULT.json]
  python benchmarks/bench_quality.py --input CLIP --evaluate OUT.mp4 [--stats S.json]

Runs ``facewire demo --input CLIP --output OUT.mp4 --stats S.json`` as a child process (a real
loopback call), then scores OUT.mp4 against CLIP with facewire.quality: frame i against frame
i, regions from the input's own landmarks (this checkout's tracker), means over frames. Prints
those and the call's geometry kbit/s from its stats.

``--code CHECKOUT`` runs the call from another checkout (for example a git worktree of an
older commit) with this interpreter: PYTHONPATH and the working folder are set to it, and the
script checks that facewire, sender, receiver, protocol and models are imported from there.
The scoring always uses this checkout's metric and tracker, so versions are scored alike.

The call is paced at the clip's frame rate unless ``--fast`` is given. With ``--fast`` a
version-2 receiver that falls behind renders only the newest frame and writes the skipped
ones as held copies of the previous picture, so the recording (and its score) depends on the
machine's load; paced, every frame is rendered (``--every-frame``: a busy machine's sender
would otherwise leave frames out as a camera does, and the score would measure the load).

``--evaluate OUT.mp4`` scores an existing output without running a call (``--stats`` names
its stats file for the bit rate).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from facewire.quality import REGIONS, QualityReport, score_videos  # noqa: E402
from facewire.sender.capture import demo_clip_path  # noqa: E402

#: The call's parts: inside facewire since issue 27, top-level packages in older checkouts.
PARTS = ("sender", "receiver", "protocol", "models")


def _env(code: Path | None) -> dict[str, str]:
    env = dict(os.environ)
    if code is not None:
        env["PYTHONPATH"] = str(code)
    return env


def check_imports(code: Path) -> None:
    """Fail unless the call's packages come from ``code`` (not this checkout)."""
    probe = (
        "import importlib, facewire\n"
        "print(facewire.__file__)\n"
        f"for part in {PARTS!r}:\n"
        "    try:\n"
        "        m = importlib.import_module('facewire.' + part)\n"
        "    except ImportError:\n"
        "        m = importlib.import_module(part)\n"
        "    print(m.__file__)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe],
        cwd=code,
        env=_env(code),
        check=False,
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["?"])[-1]
        raise SystemExit(f"--code {code}: cannot import the call's packages: {last}")
    files = done.stdout.split()
    root = code.resolve()
    stray = [f for f in files if root not in Path(f).resolve().parents]
    if stray or len(files) != 1 + len(PARTS):
        raise SystemExit(f"--code {code}: packages imported from elsewhere: {stray or files}")


def _demo_help(code: Path | None) -> str:
    """``facewire demo --help`` of the checkout that runs the call (older ones lack flags)."""
    cmd = [sys.executable, "-m", "facewire", "demo", "--help"]
    done = subprocess.run(cmd, cwd=code, env=_env(code), capture_output=True, text=True)
    return done.stdout


def run_call(
    clip: Path, output: Path, stats: Path, fast: bool, frames: int | None, code: Path | None
) -> None:
    cmd = [sys.executable, "-m", "facewire", "demo", "--input", str(clip)]
    cmd += ["--output", str(output), "--compare", "", "--stats", str(stats)]
    if fast:
        cmd.append("--fast")
    elif "--every-frame" in _demo_help(code):  # the picture is scored, not the machine's load
        cmd.append("--every-frame")
    if frames is not None:
        cmd += ["--frames", str(frames)]
    done = subprocess.run(
        cmd, cwd=code, env=_env(code), capture_output=True, text=True, check=False
    )
    if done.returncode != 0:
        raise SystemExit(f"facewire demo failed ({done.returncode}): {done.stderr.strip()}")
    print(done.stdout.strip().splitlines()[0])  # the call's summary line


def summary(report: QualityReport, stats: dict[str, Any] | None) -> dict[str, Any]:
    out: dict[str, Any] = report.as_dict()
    if stats is not None:
        out["geometry_kbps"] = stats["kbps"]["geometry"]
        out["edge_kbps"] = stats.get("edge_kbps", 0.0)  # a part of the geometry's packets
        out["call"] = {k: stats.get(k) for k in ("frames_in", "frames_out", "frames_held")}
    return out


def print_table(result: dict[str, Any]) -> None:
    print(
        f"scored {result['frames']} frames ({result['held']} missing from the output and held, "
        f"{result['untracked']} input frames without a face)"
    )
    print("region  SSIM    PSNR dB")
    for r in REGIONS:
        print(f"{r:<7} {result['ssim'][r]:.4f}  {result['psnr_db'][r]:.2f}")
    if "geometry_kbps" in result:
        call = result["call"]
        print(
            f"geometry {result['geometry_kbps']:.2f} kbit/s (of which the edge "
            f"{result.get('edge_kbps', 0.0):.2f}); call: {call['frames_in']} frames in, "
            f"{call['frames_out']} out, {call['frames_held']} held by the receiver"
        )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--input", type=Path, default=None, help="clip (default: the bundled one)")
    parser.add_argument("--output", type=Path, help="where the call's output goes (default: temp)")
    parser.add_argument("--evaluate", type=Path, metavar="OUT.mp4", help="score this, no call")
    parser.add_argument("--stats", type=Path, metavar="S.json", help="the call's stats file")
    parser.add_argument("--fast", action="store_true", help="send as fast as possible")
    parser.add_argument("--frames", type=int, help="send at most N frames")
    parser.add_argument("--code", type=Path, metavar="CHECKOUT", help="run the call from here")
    parser.add_argument("--json", type=Path, metavar="RESULT.json", help="write the figures")
    args = parser.parse_args()
    clip = (args.input or demo_clip_path()).resolve()
    code = args.code.resolve() if args.code else None
    with tempfile.TemporaryDirectory() as tmp:
        if args.evaluate:
            output, stats_path = args.evaluate, args.stats
        else:
            if code is not None:
                check_imports(code)
            output = (args.output or Path(tmp) / "out.mp4").resolve()
            stats_path = (args.stats or output.with_suffix(".json")).resolve()
            run_call(clip, output, stats_path, args.fast, args.frames, code)
        stats = json.loads(stats_path.read_text()) if stats_path else None
        result = summary(score_videos(clip, output, limit=args.frames), stats)
    result.update(input=str(clip), output=str(output), code=str(code) if code else None)
    print_table(result)
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
