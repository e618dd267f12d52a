"""Benchmarks of the classical 2D image analysis (guidewire3d.xray.roadmap, guidewire3d.xray.orderedwire).

Three measurements, each a function other benches can import:

- :func:`real_vessel_dice`: vessel Dice of :func:`guidewire3d.xray.roadmap.vessel_mask` on the real
  non-subtracted coronary angiograms of ``/work/shared/data/coronary-angiograms`` (``N.png`` with
  manual masks ``N_gt.png``), no per-image tuning, for the classical and the learned method side by
  side. The learned model was TRAINED on these 40 images, so its column is a training-set score;
  the honest estimate for unseen images is the k-fold cross-validated Dice recorded in the weights'
  metadata by ``scripts/train_vessels2d.py`` (printed below the table).
- :func:`simulated_roadmap_dice`: vessel Dice of both methods on simulated subtracted roadmaps
  (``guidewire3d.phantom.simulate(...).roadmap`` vs ``vessel_mask_2d``), with and without the
  CTA-derived ``max_radius_px`` the pipeline passes; the basis of ``VesselMethod.AUTO``.
- :func:`simulated_wire_accuracy`: :func:`guidewire3d.xray.orderedwire.ordered_wire` on simulated live frames
  (``guidewire3d.phantom.simulate``) from a given mask source (the TRUE wire mask by default, or any
  callable ``(frame, case, t) -> mask``): mean symmetric centerline distance to the true projected
  wire, tip error, failures and time.

Usage::

    python scripts/bench_vessels2d_real.py                 # both tables
    python scripts/bench_vessels2d_real.py --only real     # real-angiogram Dice only
    python scripts/bench_vessels2d_real.py --only sim --cases 10   # simulated-roadmap Dice, both methods
    python scripts/bench_vessels2d_real.py --only wire --cases 10 --frames 20
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from guidewire3d.xray.orderedwire import ordered_wire
from guidewire3d.xray.roadmap import vessel_mask
from guidewire3d.metrics import dice, precision_recall, symmetric_polyline_distance

REAL_DIR = Path("/work/shared/data/coronary-angiograms")


def real_vessel_dice(data_dir=REAL_DIR, ids=None, method="classical") -> list[dict]:
    """Per-image Dice / precision / recall / seconds of ``vessel_mask(image, method=method)`` on the
    real angiograms."""
    from skimage.io import imread

    data_dir = Path(data_dir)
    if ids is None:
        ids = sorted(int(p.stem) for p in data_dir.glob("*.png") if p.stem.isdigit())
    rows = []
    for i in ids:
        img = imread(data_dir / f"{i}.png")
        gt = imread(data_dir / f"{i}_gt.png") > 0
        t0 = time.perf_counter()
        m = vessel_mask(img, method=method)
        dt = time.perf_counter() - t0
        p, r = precision_recall(m, gt)
        rows.append(dict(image=i, dice=dice(m, gt), precision=p, recall=r, seconds=dt))
    return rows


def simulated_roadmap_dice(*, n_cases: int = 10, seed0: int = 0) -> list[dict]:
    """Dice of ``vessel_mask`` vs the true ``vessel_mask_2d`` on simulated roadmaps, per method,
    without (``roadmap_centerline``'s default) and with the pipeline's CTA-derived ``max_radius_px``.

    Returns
    -------
    list of dict
        One row per case: ``case``, and ``dice_<method>`` / ``s_<method>`` for ``classical``,
        ``learned``, ``auto``, plus ``dice_classical_r`` / ``dice_auto_r`` (with ``max_radius_px``).
    """
    from guidewire3d.phantom import PhantomOptions, simulate

    rows = []
    for c in range(n_cases):
        case = simulate(PhantomOptions(seed=seed0 + c, n_frames=1), make_ct=False)
        road, gt = case.roadmap, case.vessel_mask_2d
        r_px = float(case.tree.radius_mm.max()) / case.carm.pixel_at_iso_mm * 1.5
        row = dict(case=seed0 + c)
        for name, kw in (("classical", {}), ("learned", {}), ("auto", {}), ("classical_r", {"max_radius_px": r_px}),
                         ("auto_r", {"max_radius_px": r_px})):
            t0 = time.perf_counter()
            m = vessel_mask(road, method=name.removesuffix("_r"), **kw)
            row[f"s_{name}"] = time.perf_counter() - t0
            row[f"dice_{name}"] = dice(m, gt)
        rows.append(row)
    return rows


def simulated_wire_accuracy(*, n_cases: int = 10, n_frames: int = 20, seed0: int = 0, mask_fn=None,
                            max_gap_px: float = 15.0) -> list[dict]:
    """Ordered-wire accuracy on simulated frames.

    Parameters
    ----------
    n_cases, n_frames : int
        Phantom cases (seeds ``seed0 .. seed0 + n_cases - 1``) and live frames per case.
    mask_fn : callable ``(frame, case, t) -> (H, W) bool``, optional
        Mask source; default the true wire mask ``case.wire_mask[t]``.

    Returns
    -------
    list of dict
        One row per frame: ``case, t, success, message, dist_px`` (mean symmetric distance between the
        extracted and the true visible wire, 0.25 px resampling), ``tip_px`` (distance between the
        extracted distal end and the true tip; NaN if the true tip is outside the image),
        ``reversed`` (ordering wrong), ``ms``.
    """
    from guidewire3d.phantom import PhantomOptions, simulate

    rows = []
    for c in range(n_cases):
        case = simulate(PhantomOptions(seed=seed0 + c, n_frames=n_frames), make_ct=False)
        hint = _root_uv(case)
        for t in range(len(case.frames)):
            mask = case.wire_mask[t] if mask_fn is None else mask_fn(case.frames[t], case, t)
            truth = np.asarray(case.wire_uv_px[t], float)
            vis = np.asarray(case.wire_visible[t], bool)
            t0 = time.perf_counter()
            ow = ordered_wire(mask, image=case.frames[t], proximal_hint_uv=hint, max_gap_px=max_gap_px)
            ms = 1e3 * (time.perf_counter() - t0)
            row = dict(case=c, t=t, success=ow.success, message=ow.message, ms=ms, dist_px=np.nan,
                       tip_px=np.nan, reversed=False, n_gaps=ow.n_gaps_bridged)
            tv = truth[vis]
            if ow.success and len(tv) >= 2:
                row["dist_px"] = symmetric_polyline_distance(ow.points_uv_px, tv, step=0.25)
                if vis[-1]:
                    row["tip_px"] = float(np.linalg.norm(ow.points_uv_px[-1] - truth[-1]))
                row["reversed"] = bool(np.linalg.norm(ow.points_uv_px[0] - tv[0])
                                       > np.linalg.norm(ow.points_uv_px[-1] - tv[0]))
            rows.append(row)
    return rows


def _root_uv(case):
    """Projection of the vessel tree's root (the proximal hint)."""
    root = case.tree.points_lps_mm[case.tree.root]
    return np.asarray(case.carm.project(root, case.pose), float)


def _print_real(rows, rows_learned=None):
    lrn = {r["image"]: r for r in rows_learned or []}
    print("| image | Dice classical | precision | recall | s | Dice learned (train set) | precision | recall | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        q = lrn.get(r["image"])
        extra = (f" {q['dice']:.3f} | {q['precision']:.3f} | {q['recall']:.3f} | {q['seconds']:.2f} |" if q
                 else " - | - | - | - |")
        print(f"| {r['image']} | {r['dice']:.3f} | {r['precision']:.3f} | {r['recall']:.3f} | {r['seconds']:.2f} |"
              + extra)
    for name, rr in (("classical", rows), ("learned (training set!)", rows_learned or [])):
        if not rr:
            continue
        d = np.array([r["dice"] for r in rr])
        print(f"\nvessel_mask {name} on {len(rr)} real angiograms: Dice mean {d.mean():.3f}, "
              f"median {np.median(d):.3f}, min {d.min():.3f}, max {d.max():.3f}; "
              f"median time {np.median([r['seconds'] for r in rr]):.3f} s")
    _print_cv()


def _print_cv():
    """The learned model's cross-validated Dice, from its weights' metadata."""
    import json

    from guidewire3d.xray.vessels2d_learned import DEFAULT_WEIGHTS_PATH, load_vessel_unet

    if not DEFAULT_WEIGHTS_PATH.is_file():
        return
    meta = load_vessel_unet().metadata
    if "cv_dice_mean" not in meta:
        return
    folds = json.loads(meta["cv_fold_means"])
    print(f"\nlearned, {meta['cv_folds']}-fold cross-validation (held-out images only, "
          f"scripts/train_vessels2d.py): Dice mean {float(meta['cv_dice_mean']):.3f}, "
          f"median {float(meta['cv_dice_median']):.3f}; fold means " + ", ".join(f"{x:.3f}" for x in folds))
    if "cv_thresholds" in meta:
        print(f"  test-time flips {meta.get('cv_tta')}; thresholds picked on each fold's training images "
              f"{json.loads(meta['cv_thresholds'])} (fixed 0.5: Dice mean "
              f"{float(meta['cv_dice_mean_fixed_threshold']):.3f}); "
              f"shipped model threshold {meta.get('threshold')}, recipe {meta.get('recipe')}")


def _print_sim(rows):
    names = ("classical", "learned", "auto", "classical_r", "auto_r")
    print("\nvessel_mask on simulated roadmaps (Dice vs vessel_mask_2d; _r: with the pipeline's max_radius_px):")
    print("| case | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for r in rows:
        print(f"| {r['case']} | " + " | ".join(f"{r['dice_' + n]:.3f}" for n in names) + " |")
    print("| median | " + " | ".join(f"{np.median([r['dice_' + n] for r in rows]):.3f}" for n in names) + " |")
    print("| mean | " + " | ".join(f"{np.mean([r['dice_' + n] for r in rows]):.3f}" for n in names) + " |")
    print("| median s | " + " | ".join(f"{np.median([r['s_' + n] for r in rows]):.2f}" for n in names) + " |")


def _print_wire(rows, label="true wire mask"):
    ok = [r for r in rows if r["success"]]
    dist = np.array([r["dist_px"] for r in ok if np.isfinite(r["dist_px"])])
    tip = np.array([r["tip_px"] for r in ok if np.isfinite(r["tip_px"])])
    ms = np.array([r["ms"] for r in rows])
    print(f"\nordered_wire on {len(rows)} simulated frames ({label}):")
    print("| frames | success | centerline dist mean (px) | dist median | dist p95 | tip median (px) | tip p90 "
          "| reversed | gaps bridged | time median (ms) | time p95 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print(f"| {len(rows)} | {len(ok)} | {dist.mean():.3f} | {np.median(dist):.3f} | {np.percentile(dist, 95):.3f} | "
          f"{np.median(tip):.2f} | {np.percentile(tip, 90):.2f} | {sum(r['reversed'] for r in ok)} | "
          f"{sum(r['n_gaps'] for r in ok)} | {np.median(ms):.2f} | {np.percentile(ms, 95):.2f} |")
    fails = {}
    for r in rows:
        if not r["success"]:
            fails[r["message"]] = fails.get(r["message"], 0) + 1
    for msg, n in fails.items():
        print(f"  failed x{n}: {msg}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=["real", "sim", "wire"], default=None)
    ap.add_argument("--data", default=str(REAL_DIR))
    ap.add_argument("--cases", type=int, default=10)
    ap.add_argument("--frames", type=int, default=20)
    args = ap.parse_args(argv)
    if args.only in (None, "real"):
        from guidewire3d.xray.vessels2d_learned import DEFAULT_WEIGHTS_PATH

        learned = real_vessel_dice(args.data, method="learned") if DEFAULT_WEIGHTS_PATH.is_file() else None
        _print_real(real_vessel_dice(args.data, method="classical"), learned)
    if args.only in (None, "sim"):
        _print_sim(simulated_roadmap_dice(n_cases=args.cases))
    if args.only in (None, "wire"):
        _print_wire(simulated_wire_accuracy(n_cases=args.cases, n_frames=args.frames))


if __name__ == "__main__":
    main()
