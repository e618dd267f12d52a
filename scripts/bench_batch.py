"""Batch throughput: studies per hour with 1 and 2 local Dask workers, and the peak memory per worker.

    .venv/bin/python scripts/bench_batch.py [--studies 4] [--frames 4] [--workers 1 2] [--repeats 1]

Simulates ``--studies`` phantom studies (seeds 200.., ``--frames`` live frames each), then runs
``guidewire3d batch``'s library call (``batch.run_batch``, images included as ``reconstruct`` writes
them) over them once per worker count, into a fresh folder each time. The wall time includes
starting the local cluster (worker processes importing numpy, torch, VTK), as a user sees it.
Per study: its task's wall seconds and the peak resident memory of its worker process while it
ran (VmHWM, reset at the start of the study). A worker's first study also pays the process's
one-off costs (imports, numba compiling skan's graph code), so it is shown apart from the later
ones, and "studies per hour (later studies)" is workers x 3600 / the later studies' median.
Prints a table of medians over ``--repeats``; the work is bounded by ``--studies`` x
``len(--workers)`` x ``--repeats`` reconstructions.
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--studies", type=int, default=4, help="phantom studies (default 4)")
    ap.add_argument("--frames", type=int, default=4, help="live frames per study (default 4)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts (default 1 2)")
    ap.add_argument("--repeats", type=int, default=1, help="runs per worker count (default 1; medians)")
    ap.add_argument("--no-images", action="store_true", help="skip the PNGs, as `batch --no-images`")
    ap.add_argument("--keep", metavar="DIR", help="keep the studies and outputs in DIR")
    args = ap.parse_args(argv)
    if not 1 <= args.studies <= 64 or not 1 <= args.frames <= 50 or min(args.workers) < 1 or args.repeats < 1:
        ap.error("expected 1..64 studies, 1..50 frames, workers >= 1, repeats >= 1")

    from guidewire3d.app import batch
    from guidewire3d.app import bench
    from guidewire3d.phantom import PhantomOptions, simulate, write_case

    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_batch-"))
    root.mkdir(parents=True, exist_ok=True)
    print(f"machine: {bench.machine_line()}; load average at start {_load()}", flush=True)
    t0 = time.perf_counter()
    specs = []
    for i in range(args.studies):
        d = root / "studies" / f"s{200 + i}"
        if not (d / "truth.json").is_file():
            shutil.rmtree(d, ignore_errors=True)
            write_case(simulate(PhantomOptions(seed=200 + i, n_frames=args.frames)), d)
        specs.append(batch.StudySpec(d.name, str(d / "ct"), str(d / "roadmap.dcm"), str(d / "frames.dcm")))
    print(f"{args.studies} phantom studies ({args.frames} live frames each) in {time.perf_counter() - t0:.0f} s",
          flush=True)

    results = {}
    try:
        for n in args.workers:
            walls, firsts, laters, peaks, statuses = [], [], [], [], []
            for r in range(args.repeats):
                out = root / f"out-w{n}-r{r}"
                shutil.rmtree(out, ignore_errors=True)
                t = time.perf_counter()
                rows = batch.run_batch(specs, out, workers=n, images=not args.no_images, progress=False)
                walls.append(time.perf_counter() - t)
                by_worker = {}
                for x in rows:
                    statuses.append(x["status"])
                    if x["status"] in (batch.DONE, batch.NOT_RECONSTRUCTED):
                        by_worker.setdefault(x["worker"], []).append(x)
                for xs in by_worker.values():
                    xs.sort(key=lambda x: x["started"])
                    firsts.append(float(xs[0]["seconds"]))
                    laters += [float(x["seconds"]) for x in xs[1:]]
                    peaks.append(max(float(x["peak_rss_mb"]) for x in xs))
                print(f"  {n} worker(s), run {r + 1}: {walls[-1]:.0f} s; load {_load()}", flush=True)
            results[n] = (walls, firsts, laters, peaks, statuses)
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)

    def med(v):
        return f"{statistics.median(v):.1f}" if v else "-"

    print()
    print("| workers | studies | wall s | studies per hour (wall) | s per study: a worker's first / later (median) | "
          "studies per hour (later studies) | peak RSS per worker MB (median / max) | not done |")
    print("|---|---|---|---|---|---|---|---|")
    for n, (walls, firsts, laters, peaks, statuses) in results.items():
        wall = statistics.median(walls)
        bad = sum(s != batch.DONE for s in statuses)
        steady = f"{n * 3600 / statistics.median(laters):.0f}" if laters else "-"
        print(f"| {n} | {args.studies} | {wall:.1f} | {args.studies / wall * 3600:.0f} | {med(firsts)} / {med(laters)} "
              f"| {steady} | {statistics.median(peaks):.0f} / {max(peaks):.0f} | {bad} |")
    print(f"\nload average at end {_load()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
