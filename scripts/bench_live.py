"""Live-path speed: marginal time per frame after the one-off CTA and registration work.

Per frame: guidewire segmentation, ordered 2D wire, 3D reconstruction (tracking) and the
report entry. Measured over a long simulated sequence, per segmenter mode, and printed as a
table of medians.

    nice .venv/bin/python scripts/bench_live.py --frames 120 --seed 2024
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()

    from guidewire3d import bench, export, image2d, live, phantom, registration, vessels3d
    from guidewire3d.segmentation import GuidewireSegmenter, guidewire_mask

    case = phantom.simulate(phantom.PhantomOptions(seed=args.seed, n_frames=args.frames))
    t0 = time.perf_counter()
    ves = vessels3d.extract_vessels(case.volume)
    t_cta = time.perf_counter() - t0
    t0 = time.perf_counter()
    cl = image2d.roadmap_centerline(case.roadmap, max_radius_px=float(ves.tree.radius_mm.max()) / case.carm.pixel_at_iso_mm * 1.5)
    reg = registration.register(ves.tree, cl.points_uv_px, case.carm, centerline_radius_px=cl.radius_px)
    t_reg = time.perf_counter() - t0

    rows = []
    modes = (("UNet, ROI tracking (default)", "unet", True),
             ("UNet, full frame", "unet", False),
             ("Ridge, ROI tracking", "ridge", True))
    for name, method, tracking in modes:
        seg = GuidewireSegmenter(method=method, num_threads=args.threads)
        if not tracking:
            seg.segment = lambda frame, _m=method: guidewire_mask(frame, method=_m)  # noqa: E731
        session = live.Session(ves.tree, case.carm, reg.pose, registration_covariance=reg.covariance_6x6,
                               segmenter=seg)
        session.warm_up(case.frames[0])  # session creation, first-call compilation
        lat, ok = [], 0
        t_all = time.perf_counter()
        for fr in session.run(case.frames):
            export.frame_record(fr.index, fr.wire2d, fr.wire3d, fr.seconds, fr)  # the report entry is part of the live path
            lat.append(fr.seconds)
            ok += bool(fr)
        marginal = (time.perf_counter() - t_all) / len(case.frames)
        rows.append([name, f"{1000 * marginal:.1f}", f"{1.0 / marginal:.1f}", f"{1000 * float(np.median(lat)):.1f}",
                     f"{ok}/{len(case.frames)}"])
    print(f"live path, {args.frames} frames 512x512, seed {args.seed}; one-off: CTA vessels {t_cta:.1f} s, "
          f"roadmap + registration {t_reg * 1000:.0f} ms; machine: {bench.machine_line()}, "
          f"load average {os.getloadavg()[0]:.1f}")
    print(bench._table(["mode", "marginal ms/frame", "FPS", "median latency ms", "frames ok"], rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
