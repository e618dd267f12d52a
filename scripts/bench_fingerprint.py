"""What recording and comparing a study's input files costs (``report.json``'s ``inputs.files``).

    .venv/bin/python scripts/bench_fingerprint.py CASE [CASE ...] [--repeats 5]

``CASE`` is a folder as ``guidewire3d phantom --out CASE`` writes it (``ct/``, ``roadmap.dcm``,
``frames.dcm``). Per case, medians over ``--repeats`` runs of: finding the series's files
(``io.volume_files``: the GDCM scan ``read_volume`` also does), the SHA-256 of the CT files in 1 and
in 4 threads (``io.file_fingerprints``), every input's record (``pipeline.input_files``: what
``run_to_outdir`` adds to a run), a rerun's comparison of one study (``batch.input_changes``), and,
for scale, reading the CTA (``io.read_volume``). The files are in the page cache after the first
run (the figures are warm; a cold read adds the disk's time to read the bytes once).
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path


def _median_s(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cases", nargs="+", type=Path, metavar="CASE", help="phantom case folders")
    ap.add_argument("--repeats", type=int, default=5, help="runs per measure (default 5; medians)")
    args = ap.parse_args(argv)
    if not 1 <= args.repeats <= 50:
        ap.error("expected 1..50 repeats")

    from guidewire3d import io
    from guidewire3d.app import batch, bench, pipeline

    print(f"machine: {bench.machine_line()}; load average at start "
          f"{' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print("| CT files | CT MB | series scan s | SHA-256, 1 thread: s (MB/s) | SHA-256, 4 threads: s (MB/s) "
          "| record of the 3 inputs s | a rerun's comparison s | read_volume s |")
    print("|---|---|---|---|---|---|---|---|")
    for case in args.cases:
        ct, road, frames = case / "ct", case / "roadmap.dcm", case / "frames.dcm"
        _, files = io.volume_files(ct)
        mb = sum(p.stat().st_size for p in files) / 1e6
        spec = batch.StudySpec(case.name, str(ct), str(road), str(frames))
        report = {"inputs": {"series_uid": io.volume_files(ct)[0],
                             "files": pipeline.input_files(ct, road, frames)}}
        assert batch.input_changes(spec, report) == []
        scan = _median_s(lambda: io.volume_files(ct), args.repeats)
        one = _median_s(lambda: io.file_fingerprints(files, root=ct, threads=1), args.repeats)
        four = _median_s(lambda: io.file_fingerprints(files, root=ct, threads=4), args.repeats)
        record = _median_s(lambda: pipeline.input_files(ct, road, frames), args.repeats)
        compare = _median_s(lambda: batch.input_changes(spec, report), args.repeats)
        read = _median_s(lambda: io.read_volume(ct), max(1, min(args.repeats, 3)))
        print(f"| {len(files)} | {mb:.0f} | {scan:.3f} | {one:.3f} ({mb / one:.0f}) | {four:.3f} ({mb / four:.0f}) "
              f"| {record:.3f} | {compare:.3f} | {read:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
