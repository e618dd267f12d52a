"""Real data through the live engine: the 74 catheter centerlines of Ambrosini et al. (issue 20).

The shared liver catheterisation (``shared/data/ambrosini-dataset1``, loaded by ``ambrosini_data``)
has no images, but its 2D catheter centerlines say where the tip is (the source lists it first).
Each frame's curve goes through ``live.Session.process_wire`` (the 3D reconstruction and the frame
verdict that ``reconstruct`` and ``live`` give every frame) with the 3DRA tree:

* in the order a segmenter gives it (proximal -> distal) and reversed (tip first: the engine must
  find the tip itself, from the vessel tree);
* at the frame-0 manual fusion (static pose; the patient breathes, so later frames are off by 4-8
  px) and with per-frame pose tracking (``track_motion=True``, from the fusion).

There is no 3D truth. What is scored is what can be checked in 2D against the real data: the
projected 3D tip against the catheter's real tip (px; *wrong end*: more than ``--wrong-px`` from the
real tip while within that distance of the real proximal end), the 3D wire's projection error
against the catheter, and every verdict with its reason. A frame reported ``ok`` with its tip at
the wrong end is silently wrong.

    .venv/bin/python scripts/bench_real_catheter.py
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ambrosini_data import dataset1_root, load_dataset1  # noqa: E402


def run(d, *, reverse: bool, track: bool, wrong_px: float) -> dict:
    from guidewire3d.geometry import Pose
    from guidewire3d.live import session as live

    s = live.Session(d.tree, d.carm, Pose.identity(), track_motion=track)
    rows = []
    for k, uv in enumerate(d.curves_uv_px):
        given = uv[::-1] if reverse else uv
        fr = s.process_wire(given, index=k)
        tip_true, root_true = uv[-1], uv[0]
        row = {"k": k, "verdict": fr.verdict.value, "message": fr.message, "tip_px": np.nan, "wrong_end": False,
               "proj_px": np.nan}
        if fr.wire3d:
            pose = fr.pose if fr.pose is not None else Pose.identity()
            tip_uv = d.carm.project(fr.wire3d.points_lps_mm[-1:], pose)[0]
            row["tip_px"] = float(np.linalg.norm(tip_uv - tip_true))
            row["wrong_end"] = bool(row["tip_px"] > wrong_px and np.linalg.norm(tip_uv - root_true) < wrong_px)
            row["proj_px"] = float(fr.wire3d.projection_error_px)
        rows.append(row)
    return {"rows": rows}


def reason_of(message: str) -> str:
    """The first reason of a verdict message (``frame_verdict`` lists them, the first first)."""
    return message.split(":")[0].strip()[:40]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--wrong-px", type=float, default=20.0, help="a tip this far from the real tip, near its other end")
    args = ap.parse_args()
    if not (dataset1_root() / "dataset1_lps.npz").exists():
        print(f"shared real data not found at {dataset1_root()}", file=sys.stderr)
        return 2
    d = load_dataset1()
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name"))
    except (OSError, StopIteration):
        cpu = platform.processor()
    print(f"Ambrosini dataset1: {len(d.curves_uv_px)} real catheter frames; host {cpu}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f}")
    print("| pose | input order | ok | uncertain | failed | ok with the tip at the wrong end | ok: tip to real tip px, "
          "median / p90 / max | ok: projection error px, median | uncertain reasons |")
    print("|---|---|---|---|---|---|---|---|---|")
    for track in (False, True):
        for reverse in (False, True):
            rows = run(d, reverse=reverse, track=track, wrong_px=args.wrong_px)["rows"]
            v = Counter(r["verdict"] for r in rows)
            ok = [r for r in rows if r["verdict"] == "ok"]
            tips = np.array([r["tip_px"] for r in ok]) if ok else np.array([np.nan])
            proj = np.array([r["proj_px"] for r in ok]) if ok else np.array([np.nan])
            reasons = Counter(reason_of(r["message"]) for r in rows if r["verdict"] == "uncertain")
            print(f"| {'tracked' if track else 'fusion (frame 0)'} | {'tip first' if reverse else 'tip last'} | "
                  f"{v['ok']} | {v['uncertain']} | {v['failed']} | {sum(r['wrong_end'] for r in ok)} | "
                  f"{np.nanmedian(tips):.1f} / {np.nanpercentile(tips, 90):.1f} / {np.nanmax(tips):.1f} | "
                  f"{np.nanmedian(proj):.2f} | {', '.join(f'{k} {n}' for k, n in reasons.most_common())} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
