"""Benchmark the guidewire presence test (issue #20 item 2: "a wire where there is none").

Prints one table: on frames WITHOUT a wire (the 40 shared real coronary angiograms), how many
times ``guidewire3d segment`` would still report a wire (a false wire), before the test
(``ordered_wire(..., check_presence=False)``) and with it; on simulated frames WITH a wire, how
many traced wires the test keeps (and that their points are unchanged); and what the test costs
per frame (median ms of :func:`guidewire3d.xray.wirepresence.presence_of_curve` inside
``ordered_wire``, 512x512 frames, next to ``ordered_wire`` itself).

Simulated frames: training-range seeds 1300.. (``--train-seeds``, where the thresholds were
looked at) and, with ``--bench``, the held-out frames of ``scripts/bench_segmentation.py`` (seeds
0-11, 20 frames each, the same options and cache). Run::

    nice .venv/bin/python scripts/bench_wire_presence.py --train-seeds 24 --bench
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
REAL_DIR = Path("/work/shared/data/coronary-angiograms")
TRAIN_SEED0 = 1300


def _segment(frame, method):
    from guidewire3d.xray.segmentation import guidewire_mask

    return guidewire_mask(frame, method=method)


def real_negatives(method):
    """(n images, false wires before, false wires after, reasons) on the real angiograms."""
    from skimage.io import imread

    from guidewire3d.xray.orderedwire import ordered_wire

    files = sorted(REAL_DIR.glob("*.png"), key=lambda p: p.stem)
    files = [f for f in files if not f.stem.endswith("_gt")]
    before = after = 0
    reasons = {}
    for f in files:
        image = imread(f)
        mask = _segment(image, method)
        before += bool(ordered_wire(mask, image=image, check_presence=False))
        ow = ordered_wire(mask, image=image)
        after += bool(ow)
        if ow.presence is not None and not ow.presence:
            key = ("edge" if "edge" in ow.message else "tree" if "tree" in ow.message and "wide" not in ow.message
                   else "wide + tree" if "tree" in ow.message else "wide")
            reasons[key] = reasons.get(key, 0) + 1
    return len(files), before, after, reasons


def simulated_positives(cases, method):
    """(frames, traced without the test, kept with it, kept with the same points, presence ms, ordered_wire ms)."""
    from guidewire3d.xray.orderedwire import ordered_wire
    from guidewire3d.xray.wirepresence import presence_of_curve

    n = traced = kept = same = 0
    t_presence, t_ow = [], []
    for frames in cases:
        for frame in frames:
            mask = _segment(frame, method)
            n += 1
            t0 = time.perf_counter()
            ref = ordered_wire(mask, image=frame, check_presence=False)
            t1 = time.perf_counter()
            ow = ordered_wire(mask, image=frame)
            if not ref:
                continue
            traced += 1
            kept += bool(ow)
            same += bool(ow) and np.array_equal(ow.points_uv_px, ref.points_uv_px)
            # the test alone, as ordered_wire runs it (the skeleton of the whole mask; ordered_wire
            # has the skeleton of its region at hand)
            from skimage.morphology import skeletonize

            rr, cc = np.nonzero(skeletonize(mask))
            skel = np.column_stack([cc, rr])
            t2 = time.perf_counter()
            presence_of_curve(frame, ref.points_uv_px, skel)
            t_presence.append(time.perf_counter() - t2)
            t_ow.append(t1 - t0)
    return n, traced, kept, same, np.median(t_presence) * 1e3, np.median(t_ow) * 1e3


def train_cases(n_seeds, n_frames):
    from guidewire3d.phantom import PhantomOptions, simulate

    sys.path.insert(0, str(ROOT / "scripts"))
    from bench_segmentation import case_options

    for seed in range(TRAIN_SEED0, TRAIN_SEED0 + n_seeds):
        yield simulate(PhantomOptions(seed=seed, n_frames=n_frames, **case_options(seed)), make_ct=False).frames


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--train-seeds", type=int, default=24, help="training-range seeds 1300.. (10 frames each)")
    ap.add_argument("--bench", action="store_true", help="also the 240 held-out frames of bench_segmentation")
    ap.add_argument("--ridge", action="store_true", help="also the ridge segmenter")
    ap.add_argument("--cache-dir", default="/tmp")
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "2")
    methods = ["unet"] + (["ridge"] if args.ridge else [])
    rows = []
    for method in methods:
        if REAL_DIR.is_dir():
            n, b, a, reasons = real_negatives(method)
            why = ", ".join(f"{k} {v}" for k, v in sorted(reasons.items()))
            rows.append((method, "real angiograms, no wire", n, f"false wires {b} -> {a}", f"rejected as: {why}", ""))
        sets = [(f"simulated, seeds {TRAIN_SEED0}-{TRAIN_SEED0 + args.train_seeds - 1} x 10",
                 train_cases(args.train_seeds, 10))]
        if args.bench:
            sys.path.insert(0, str(ROOT / "scripts"))
            from bench_segmentation import load_cases

            sets.append(("simulated, bench seeds 0-11 x 20", (c["frames"] for c in load_cases(12, 20, args.cache_dir))))
        for label, cases in sets:
            n, traced, kept, same, ms_p, ms_ow = simulated_positives(cases, method)
            rows.append((method, label, n, f"wires kept {kept}/{traced}", f"points unchanged {same}/{kept}",
                         f"{ms_p:.2f} ms (ordered_wire {ms_ow:.1f} ms)"))
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"\nGuidewire presence test (host load average {load} on {os.cpu_count()} cores)")
    print(f"{'segmenter':<9} {'frames':<36} {'n':>4}  {'outcome':<22} {'detail':<34} presence test per frame (median)")
    for r in rows:
        print(f"{r[0]:<9} {r[1]:<36} {r[2]:>4}  {r[3]:<22} {r[4]:<34} {r[5]}")


if __name__ == "__main__":
    main()
