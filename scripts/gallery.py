"""Montage of simulated cases: roadmap, a live frame with the truth wire, held-out frame, CTA MIP.

Usage::

    .venv/bin/python scripts/gallery.py --out gallery.png [--seeds 0 1 2 3 4 5] [--frame -1]
        [--distractors] [--dose 1.0] [--no-background] [--no-catheter]

One row per seed. Columns: the roadmap (subtracted contrast) with the projected truth tree; the
live frame with the truth wire (red, ends marked: proximal green, tip yellow); the live frame
alone; the held-out view's frame with its truth wire; the CTA maximum-intensity projection along
the main view's dominant axis with the truth wire (LPS) on it.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def _mip(case):
    vol = case.volume
    a = np.asarray(vol.array_zyx)
    # project along y (anterior-posterior): a coronal MIP, rows = z (superior at the top)
    mip = a.max(axis=1)[::-1]
    sx, sy, sz = vol.spacing_mm
    ox, oy, oz = vol.origin_lps_mm
    nz = a.shape[0]
    extent = (ox - sx / 2, ox + (a.shape[2] - 0.5) * sx, oz - sz / 2, oz + (nz - 0.5) * sz)
    return mip, extent


def main(argv=None) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from guidewire3d.phantom import PhantomOptions, simulate

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="gallery.png")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    p.add_argument("--frames", type=int, default=6)
    p.add_argument("--frame", type=int, default=-1, help="live frame to show (default the last)")
    p.add_argument("--distractors", action="store_true")
    p.add_argument("--no-background", action="store_true")
    p.add_argument("--no-catheter", action="store_true")
    p.add_argument("--dose", type=float, default=1.0)
    p.add_argument("--motion", type=float, default=0.0)
    p.add_argument("--wire-diameter", type=float, default=None)
    args = p.parse_args(argv)

    n = len(args.seeds)
    fig, axes = plt.subplots(n, 5, figsize=(20, 4.1 * n), squeeze=False)
    for row, seed in enumerate(args.seeds):
        t0 = time.perf_counter()
        opts = PhantomOptions(seed=seed, n_frames=args.frames, distractors=args.distractors or seed % 2 == 1,
                              background=not args.no_background, catheter=not args.no_catheter, dose=args.dose,
                              motion_mm=args.motion, wire_diameter_mm=args.wire_diameter)
        case = simulate(opts)
        dt = time.perf_counter() - t0
        k = args.frame % len(case.frames)
        c, h = case.carm, case.heldout_carm
        ax = axes[row]
        ax[0].imshow(case.roadmap, cmap="gray")
        uvt = c.project(case.tree.points_lps_mm, case.pose)
        ax[0].plot(uvt[:, 0], uvt[:, 1], ",", color="cyan", alpha=0.25)
        ax[0].set_title(f"seed {seed}: roadmap  LAO {c.primary_deg:+.0f} CRA {c.secondary_deg:+.0f}  "
                        f"px {c.pixel_mm:.3f}", fontsize=9)
        fr = case.frames[k]
        lo, hi = np.percentile(fr, [0.5, 99.5])
        uv = case.wire_uv_px[k]
        ax[1].imshow(fr, cmap="gray", vmin=lo, vmax=hi)
        ax[1].plot(uv[:, 0], uv[:, 1], "-", color="red", lw=0.6, alpha=0.7)
        ax[1].plot(*uv[0], "o", color="lime", ms=4)
        ax[1].plot(*uv[-1], "o", color="yellow", ms=4)
        ax[1].set_title(f"frame {k} + truth; wire {case.wire_diameter_mm:.2f} mm, {dt:.1f} s", fontsize=9)
        ax[2].imshow(fr, cmap="gray", vmin=lo, vmax=hi)
        ax[2].set_title(f"frame {k} (dose {opts.dose:g}, bg {opts.background}, cath {opts.catheter})", fontsize=9)
        hf = case.heldout_frames[k]
        lo2, hi2 = np.percentile(hf, [0.5, 99.5])
        ax[3].imshow(hf, cmap="gray", vmin=lo2, vmax=hi2)
        huv = case.heldout_wire_uv_px[k]
        ax[3].plot(huv[:, 0], huv[:, 1], "-", color="red", lw=0.6, alpha=0.5)
        ax[3].set_title(f"held-out LAO {h.primary_deg:+.0f} CRA {h.secondary_deg:+.0f}", fontsize=9)
        mip, extent = _mip(case)
        ax[4].imshow(mip, cmap="gray", vmin=-100, vmax=900, extent=extent, aspect="equal")
        w = case.wire_lps_mm[k]
        ax[4].plot(w[:, 0], w[:, 2], "-", color="red", lw=0.8)
        ax[4].set_title(f"CTA coronal MIP {case.volume.shape_zyx[::-1]}"
                        f"{' + distractors' if opts.distractors else ''}", fontsize=9)
        for a in ax[:4]:
            a.set_xlim(-0.5, c.cols - 0.5)
            a.set_ylim(c.rows - 0.5, -0.5)
        for a in ax:
            a.set_xticks([])
            a.set_yticks([])
        print(f"seed {seed}: {dt:.1f} s", flush=True)
    fig.tight_layout()
    out = Path(args.out)
    fig.savefig(out, dpi=60)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
