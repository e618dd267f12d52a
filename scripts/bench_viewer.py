"""Frame-update rate of the viewer (offscreen, software rendering): set_frame + render per frame.

Usage::

    nice .venv/bin/python scripts/bench_viewer.py [OUT_DIR] [--frames 60] [--sizes 512x512,1200x800]

Without OUT_DIR a synthetic case (tests/viewer_fixture.py) is written to a temporary folder.
Prints medians (ms) of: the in-place update (``set_frame``: wire points, texture, overlays),
the render, and both together, with the resulting frames per second.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def bench(out_dir, size, n_frames: int) -> dict:
    from guidewire3d.viewer.app import open_viewer

    ctl, h = open_viewer(out_dir, size_px=size, off_screen=True, persist=False)
    pl = h.plotter
    pl.screenshot(None, return_img=True)  # first render (pyvista renders only after it)
    for _ in range(3):
        ctl.next_frame()
        pl.render()
    upd, ren, tot, cpu = [], [], [], []
    for _ in range(n_frames):
        c0 = time.process_time()
        t0 = time.perf_counter()
        ctl.next_frame()
        t1 = time.perf_counter()
        pl.render()
        t2 = time.perf_counter()
        cpu.append(time.process_time() - c0)
        upd.append(t1 - t0)
        ren.append(t2 - t1)
        tot.append(t2 - t0)
    pl.close()
    med = statistics.median
    return {"update_ms": 1e3 * med(upd), "render_ms": 1e3 * med(ren), "frame_ms": 1e3 * med(tot),
            "fps": 1.0 / med(tot), "cpu_ms": 1e3 * med(cpu), "n_frames_case": ctl.n_frames}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir", nargs="?")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--sizes", default="512x512,800x500,1200x800")
    args = ap.parse_args(argv)
    if args.out_dir:
        out = Path(args.out_dir)
    else:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
        from viewer_fixture import write_synthetic_outdir

        out = write_synthetic_outdir(tempfile.mkdtemp(prefix="bench-viewer-"), n_frames=8).out_dir
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"case: {out}   frames timed per size: {args.frames}   (medians; load average {load:.1f} on "
          f"{os.cpu_count()} CPUs; CPU = process CPU time over all threads)")
    print("| window | update (ms) | render (ms) | frame (ms) | fps | CPU per frame (ms) |")
    print("|---|---|---|---|---|---|")
    for size in sizes:
        r = bench(out, size, args.frames)
        print(f"| {size[0]}x{size[1]} | {r['update_ms']:.1f} | {r['render_ms']:.1f} | {r['frame_ms']:.1f} "
              f"| {r['fps']:.1f} | {r['cpu_ms']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
