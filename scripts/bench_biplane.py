"""Benchmark of biplane (issue 23): monoplane numbers beside biplane ones, in one table.

Cases: simulator seeds ``--seed0 .. --seed0 + --cases - 1`` with ``PhantomOptions(seed, n_frames,
biplane=True)`` (plane B 90 deg from plane A in LAO/RAO, its own SID/SOD; the planes share the
isocentre). Per case two roadmap variants, as ``scripts/bench_registration.py`` makes them:

* ``full``: the simulator's roadmaps (every vessel), plane A and plane B;
* ``path``: single-path roadmaps: only the catheterised root-to-leaf vessel path (a selective
  injection), rendered and exposed for both planes (``bench_registration._render_roadmap``).

The 3D tree is the simulator's true centerline tree (``--cta``: the one ``vessels3d`` extracts from
the simulated CT, as ``reconstruct`` sees it; ~15 s more per case), the 2D centerlines
``roadmap_centerline`` of the roadmaps (``max_radius_px`` as the pipeline), the start the
DICOM one. Registration success as in ``bench_registration.py``: the verdict is ``ok`` AND the
mTRE over the true centerline is below 2 mm. Monoplane: ``registration.register`` on plane A's
roadmap; biplane: ``biplane.register_biplane`` on both.

Wires: every live frame (pair) reconstructed at the method's own pose from the full roadmaps
(reconstructed whatever the verdict, i.e. as ``--force``), through the live engines (UNet or
ridge segmentation, ordered wire): monoplane ``live.Session`` on plane A's frames, biplane
``biplane.BiplaneSession`` on the pairs. Errors against the true wire's part visible in plane A
(``metrics.wire_errors_mm``): the median over frames of the mean 3D error and of the tip error.
Frames (pairs) per second: 1 / the median wall time of a frame (pair), after the first two of each
case (warm-up), on this machine (print the load with it).

    nice .venv/bin/python scripts/bench_biplane.py --cases 30 --frames 4 --results biplane.pkl
    .venv/bin/python scripts/bench_biplane.py --cases 30 --seed0 30 --no-wires   # registration columns alone
    .venv/bin/python scripts/bench_biplane.py --timing 100 --frames 12 [--segmenter ridge]   # speed alone
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_registration import SUCCESS_MM, _render_roadmap  # noqa: E402

from guidewire3d import metrics
from guidewire3d.app import biplane
from guidewire3d.xray.roadmap import roadmap_centerline
from guidewire3d.live import session as live
from guidewire3d import registration as reg
from guidewire3d.phantom import PhantomOptions, simulate  # noqa: E402


def _centerline(img, tree, carm):
    r_px = float(tree.radius_mm.max()) / carm.pixel_at_iso_mm * 1.5
    return roadmap_centerline(img, max_radius_px=r_px)


def _tree_of(case, use_cta: bool):
    if not use_cta:
        return case.tree
    from guidewire3d.cta import vessels3d

    return vessels3d.extract_vessels(case.volume).tree


#: the verdict lines: an ``ok`` frame whose tip is farther than this from the true one is wrong
TIP_OFF_MM = 5.0
#: the tip-end reasons of ``live.frame_verdict`` (``orderedwire.tip_end_check``), by their first words
TIP_END_REASONS = {"two layers at the tip": "tip uncertain: the wire's last", "no wire at the tip": "tip uncertain: the trace's last"}

_SEGMENTERS = {}


def _segmenters(method: str):
    """Three segmenters (monoplane, biplane plane A, plane B), made once."""
    if method not in _SEGMENTERS:
        from guidewire3d.xray.segmentation import GuidewireSegmenter

        _SEGMENTERS[method] = tuple(GuidewireSegmenter(method=method) for _ in range(3))
    return _SEGMENTERS[method]


def run_case(seed: int, args, log) -> dict:
    t0 = time.perf_counter()
    case = simulate(PhantomOptions(seed=seed, n_frames=args.frames, biplane=True), make_ct=bool(args.cta))
    tree = _tree_of(case, args.cta)
    true_tree = case.tree
    P_true = true_tree.points_lps_mm
    carms = (case.carm, case.heldout_carm)
    rng = np.random.default_rng(70_000 + seed)
    path_ids = np.asarray(case.wire_path_point_ids)
    path_chain = [(P_true[path_ids], true_tree.radius_mm[path_ids])]
    roadmaps = {"full": (np.asarray(case.roadmap), np.asarray(case.heldout_roadmap)),
                "path": tuple(_render_roadmap(c, case.pose, path_chain, rng) for c in carms)}
    out = {"seed": seed, "reg": {}, "wires": {}}
    poses = {}
    for variant, imgs in roadmaps.items():
        cls = [_centerline(img, tree, c) for img, c in zip(imgs, carms)]
        done = []
        if args.only != "bi":
            done.append(("mono", reg.register(tree, cls[0].points_uv_px, carms[0], centerline_radius_px=cls[0].radius_px)))
        if args.only != "mono":
            done.append(("bi", biplane.register_biplane(tree, [c.points_uv_px for c in cls], carms,
                                                        centerline_radius_px=[c.radius_px for c in cls]).result))
        for name, r in done:
            e = metrics.mtre_mm(r.pose, case.pose, P_true)
            out["reg"][(name, variant)] = dict(mtre=e, ok=bool(r.success), success=bool(r.success and e < SUCCESS_MM),
                                               seconds=r.seconds, verdict=r.verdict.value)
            if variant == "full":
                poses[name] = r
    if args.no_wires:
        out["wires"] = {"mono": [], "bi": []}
        log(_case_line(seed, out, t0))
        return out
    # wires at each method's own pose from the full roadmaps
    truth = []
    for t in range(args.frames):
        vis = np.asarray(case.wire_visible[t], bool)
        truth.append(np.asarray(case.wire_lps_mm[t])[vis])
    segs = _segmenters(args.segmenter)  # loaded once for all cases (a new one exports the network again)
    for sg in segs:
        sg.reset()
    mono = live.Session(tree, carms[0], poses["mono"].pose, registration_covariance=poses["mono"].covariance_6x6,
                        segmenter=segs[0])
    mono.warm_up(case.frames[0])
    bi = biplane.BiplaneSession(tree, carms, poses["bi"].pose, registration_covariance=poses["bi"].covariance_6x6,
                                segmenter=segs[1:], threads=args.threads)
    bi.warm_up(case.frames[0], case.heldout_frames[0])
    recs = {"mono": [], "bi": []}
    for t in range(args.frames):
        t1 = time.perf_counter()
        fr = mono.process(case.frames[t], index=t)
        dt_m = time.perf_counter() - t1
        t1 = time.perf_counter()
        bp = bi.process(case.frames[t], case.heldout_frames[t], index=t)
        dt_b = time.perf_counter() - t1
        for name, res, dt, views in (("mono", fr, dt_m, "A" if fr else ""),
                                     ("bi", bp.result, dt_b, bp.views)):
            w3 = res.wire3d
            rec = {"t": t, "seconds": dt, "ok": bool(w3), "views": views, "verdict": res.verdict.value,
                   "message": res.message}
            if w3 and len(truth[t]) >= 2:
                rec.update(metrics.wire_errors_mm(w3.points_lps_mm, truth[t]))
                if name == "bi":  # calibration of uncertainty_mm: per point distance to the true wire
                    from scipy.spatial import cKDTree

                    dense = metrics.resample_polyline(truth[t], 0.05)
                    rec["e_pts"] = cKDTree(dense).query(w3.points_lps_mm)[0]
                    rec["sig_pts"] = np.asarray(w3.uncertainty_mm)
            recs[name].append(rec)
    bi.close()
    out["wires"] = recs
    log(_case_line(seed, out, t0))
    return out


def _case_line(seed: int, out: dict, t0: float) -> str:
    r = out["reg"]
    if len(r) < 4:  # one method only (--only)
        return f"  seed {seed}: " + ", ".join(f"{k[0]} {k[1]} {x['mtre']:.2f} mm ({x['verdict']})" for k, x in r.items())
    return (f"  seed {seed}: mono {r[('mono', 'full')]['mtre']:.2f}/{r[('mono', 'path')]['mtre']:.2f} mm "
            f"({r[('mono', 'full')]['verdict']}/{r[('mono', 'path')]['verdict']}), "
            f"bi {r[('bi', 'full')]['mtre']:.2f}/{r[('bi', 'path')]['mtre']:.2f} mm "
            f"({r[('bi', 'full')]['verdict']}/{r[('bi', 'path')]['verdict']}); "
            f"{time.perf_counter() - t0:.1f} s")


def table(results, args, out=print) -> None:
    import os
    import platform

    rows = []
    for name, label in (("mono", "monoplane (plane A)"), ("bi", "biplane (A + B)")):
        if (name, "full") not in results[0]["reg"]:
            continue
        regs = {v: [r["reg"][(name, v)] for r in results] for v in ("full", "path")}
        allr = regs["full"] + regs["path"]
        succ = sum(x["success"] for x in allr)
        s_full = sum(x["success"] for x in regs["full"])
        s_path = sum(x["success"] for x in regs["path"])
        wrong_ok = sum(x["ok"] and x["mtre"] >= SUCCESS_MM for x in allr)
        mtre = np.median([x["mtre"] for x in allr])
        rt = np.median([x["seconds"] for x in allr])
        frames = [f for r in results for f in r["wires"][name]]
        good = [f for f in frames if "mean_error_mm" in f]
        mean_e = np.median([f["mean_error_mm"] for f in good]) if good else np.nan
        tip_e = np.median([f["tip_error_mm"] for f in good]) if good else np.nan
        tip90 = np.percentile([f["tip_error_mm"] for f in good], 90) if good else np.nan
        steady = [f["seconds"] for f in frames if f["t"] >= 2]
        rate = 1.0 / np.median(steady) if steady else np.nan
        two = sum(1 for f in frames if f["views"] == "AB")
        rows.append((label, f"{succ}/{len(allr)} ({100 * succ / len(allr):.1f} %)", f"{s_full}/{len(regs['full'])}",
                     f"{s_path}/{len(regs['path'])}", str(wrong_ok), f"{mtre:.2f}", f"{1e3 * rt:.0f}",
                     f"{mean_e:.3f}", f"{tip_e:.3f}", f"{tip90:.2f}", f"{len(good)}/{len(frames)}",
                     f"{two}" if name == "bi" else "-", f"{rate:.1f}"))
    out(f"\nBiplane benchmark: seeds {args.seed0}..{args.seed0 + args.cases - 1}, {args.frames} frames each, "
        f"tree: {'CTA-extracted' if args.cta else 'simulator truth'}, segmenter {args.segmenter}, "
        f"biplane 2D analysis in {args.threads} thread(s)")
    out(f"host: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
        f"{', '.join(f'{x:.2f}' for x in os.getloadavg())} (at the end)\n")
    head = ("| method | registration success (ok and mTRE < 2 mm) | full roadmaps | single-path roadmaps | "
            "ok but wrong | median mTRE mm | median registration ms | 3D wire mean mm (median) | tip mm (median) | "
            "tip mm p90 | frames reconstructed | from both planes | frames (pairs) / s |")
    out(head)
    out("|" + "---|" * (head.count("|") - 1))
    for r in rows:
        out("| " + " | ".join(r) + " |")
    for name in [n for n in ("mono", "bi") if (n, "full") in results[0]["reg"]]:
        bad = [f"{r['seed']} {v} {x['mtre']:.2f} mm {x['verdict']}" for r in results for v in ("full", "path")
               for x in [r["reg"][(name, v)]] if not x["success"]]
        if name == "bi" or len(bad) <= 20:
            out(f"\n{name} registrations not successful (seed, roadmap, mTRE, verdict): " + ("; ".join(bad) or "none"))
    for name in ("mono", "bi"):      # the frame verdicts against the truth (a frame is wrong: its tip > TIP_OFF_MM)
        frames = [f for r in results for f in r["wires"].get(name, []) if "verdict" in f and "tip_error_mm" in f]
        if not frames:
            continue
        n = {v: sum(f["verdict"] == v for f in frames) for v in ("ok", "uncertain")}
        off = sum(f["verdict"] == "ok" and f["tip_error_mm"] > TIP_OFF_MM for f in frames)
        refused = sum(f["verdict"] == "uncertain" and f["tip_error_mm"] <= TIP_OFF_MM for f in frames)
        why = {k: sum(words in f["message"] for f in frames) for k, words in TIP_END_REASONS.items()}
        out(f"\n{name} frame verdicts ({len(frames)} frames with a 3D wire): ok {n['ok']}, uncertain {n['uncertain']}; "
            f"ok with the tip > {TIP_OFF_MM:g} mm off {off}; uncertain with the tip within {TIP_OFF_MM:g} mm {refused}; "
            + ", ".join(f"{k} {v}" for k, v in why.items()))
    bi = [f for r in results for f in r["wires"]["bi"] if "e_pts" in f]
    if bi:
        e = np.concatenate([f["e_pts"] for f in bi])
        s = np.concatenate([f["sig_pts"] for f in bi])
        out(f"\nbiplane uncertainty_mm calibration (pooled points): RMS(error) / RMS(sigma) = "
            f"{np.sqrt(np.mean(e ** 2)) / np.sqrt(np.mean(s ** 2)):.2f}, within 1 sigma {100 * np.mean(e <= s):.0f} %, "
            f"within 2 sigma {100 * np.mean(e <= 2 * s):.0f} %")


def timing(seed: int, n_frames: int, segmenter: str, out=print) -> None:
    """Steady-state speed alone (no registration): the true pose, one process; wall and CPU time
    (``time.process_time``, both threads) per monoplane frame and per biplane pair, medians after
    the first two."""
    import os

    case = simulate(PhantomOptions(seed=seed, n_frames=n_frames, biplane=True), make_ct=False)
    carms = (case.carm, case.heldout_carm)
    segs = _segmenters(segmenter)
    rows = []
    mono = live.Session(case.tree, carms[0], case.pose, segmenter=segs[0])
    mono.warm_up(case.frames[0])
    w, c = [], []
    for t in range(n_frames):
        w0, c0 = time.perf_counter(), time.process_time()
        mono.process(case.frames[t])
        w.append(time.perf_counter() - w0)
        c.append(time.process_time() - c0)
    rows.append(("monoplane frame", w, c))
    for threads in (2, 1):
        for sg in segs:
            sg.reset()
        bi = biplane.BiplaneSession(case.tree, carms, case.pose, segmenter=segs[1:], threads=threads)
        bi.warm_up(case.frames[0], case.heldout_frames[0])
        w, c = [], []
        for t in range(n_frames):
            w0, c0 = time.perf_counter(), time.process_time()
            bi.process(case.frames[t], case.heldout_frames[t])
            w.append(time.perf_counter() - w0)
            c.append(time.process_time() - c0)
        bi.close()
        rows.append((f"biplane pair, {threads} thread(s)", w, c))
    out(f"\nspeed: seed {seed}, {n_frames} frames, segmenter {segmenter}; load average "
        f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    out("| path | wall ms (median) | CPU ms (median) | per second (wall) |")
    out("|---|---|---|---|")
    for name, w, c in rows:
        mw, mc = 1e3 * np.median(w[2:]), 1e3 * np.median(c[2:])
        out(f"| {name} | {mw:.1f} | {mc:.1f} | {1e3 / mw:.1f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=30)
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--segmenter", default="unet", choices=("unet", "ridge"))
    ap.add_argument("--threads", type=int, default=2, choices=(1, 2),
                    help="biplane: the two planes' 2D analyses in 1 or 2 threads")
    ap.add_argument("--no-wires", action="store_true",
                    help="the registration columns only (no live frames reconstructed; the wire columns are empty)")
    ap.add_argument("--only", choices=("mono", "bi"), default=None,
                    help="one method's registration only (needs --no-wires)")
    ap.add_argument("--cta", action="store_true", help="register to the CTA-extracted tree (slower)")
    ap.add_argument("--results", type=Path, default=None, metavar="FILE",
                    help="keep each case's results in FILE (pickle) as it completes; a rerun with the same "
                         "options takes the cases already there and runs the others")
    ap.add_argument("--timing", type=int, default=None, metavar="SEED",
                    help="only the speed table: one case, --frames frames, the true pose")
    args = ap.parse_args(argv)
    if args.only and not args.no_wires:
        ap.error("--only needs --no-wires (the wire columns compare both methods)")
    if args.timing is not None:
        timing(args.timing, max(args.frames, 4), args.segmenter)
        return 0

    def log(m):
        print(m, file=sys.stderr, flush=True)

    import pickle

    key = (args.frames, args.segmenter, args.threads, bool(args.cta), bool(args.no_wires), args.only)
    done = {}
    if args.results is not None and args.results.is_file():
        saved_key, done = pickle.loads(args.results.read_bytes())
        if saved_key != key:
            log(f"{args.results}: made with other options {saved_key}, not reused")
            done = {}
    results = []
    for seed in range(args.seed0, args.seed0 + args.cases):
        if seed not in done:
            done[seed] = run_case(seed, args, log)
            if args.results is not None:
                tmp = args.results.with_suffix(".tmp")
                tmp.write_bytes(pickle.dumps((key, done)))
                tmp.replace(args.results)
        results.append(done[seed])
    table(results, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
