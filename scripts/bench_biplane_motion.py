"""Biplane with and without motion tracking, the whole chain (``reconstruct`` with two planes, ``--track-motion``).

Cases: the simulator's biplane cases (``PhantomOptions(seed, n_frames, breathing_mm, cardiac_mm, biplane=True)``:
plane B 90 deg from plane A, both roadmaps at the roadmap's breathing phase, the live frame pairs at 15 fps with
breathing, ``--breathing`` mm peak-to-peak over 4 s, and a cardiac contraction, ``--cardiac`` mm), seeds ``--seed0 ..
--seed0 + --cases - 1``. Each case goes through ``app.biplane.run`` as ``guidewire3d reconstruct --roadmap A
--roadmap B --frames A --frames B`` does (the vessel tree extracted from the simulated CT, both roadmaps' centerlines,
the joint registration, then every pair through ``BiplaneSession``; not forced: a registration not ``ok`` leaves
its pairs unreconstructed, counted as failed), once with the joint roadmap pose for every pair and once with
``track_motion=True`` (``motion.BiplaneMotionTracker``, the registration its prior).

Per pair, against the truth: the 3D wire's mean distance to the true wire's part in view and the tip error
(``metrics.wire_errors_mm``), the pose error (mTRE over the true tree of the pose the pair was reconstructed in
against the frame's true breathing pose; the cardiac contraction is not a pose and stays in the wire error), the
verdicts, and ``ok`` pairs that should not be: the wire more than ``WIRE_OFF_MM`` or the tip more than
``TIP_OFF_MM`` off (silently wrong).

    nice .venv/bin/python scripts/bench_biplane_motion.py --cases 8 --frames 30
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

WIRE_OFF_MM = 2.0
TIP_OFF_MM = 5.0


def _runs(case):
    from guidewire3d import io

    road = [io.XARun(case.roadmap, case.carm, source="roadmap A"),
            io.XARun(case.heldout_roadmap, case.heldout_carm, source="roadmap B")]
    live = [io.XARun(case.frames, case.carm, source="frames A"),
            io.XARun(case.heldout_frames, case.heldout_carm, source="frames B")]
    return road, live


def _acc() -> dict:
    return dict(err=[], tip=[], pose=[], verdicts={"ok": 0, "uncertain": 0, "failed": 0}, n=0, ok_wire_off=0,
                ok_tip_off=0, ab=0, motion={"ok": 0, "uncertain": 0, "failed": 0}, motion_ab=0, ms=[], std=[],
                pose_t=[], reg_not_ok=0, seconds=0.0, wrong=[])


def _score(a: dict, case, res) -> None:
    from guidewire3d import metrics
    from guidewire3d.app.biplane import motion_planes

    P = case.tree.points_lps_mm
    n = len(case.frames)
    a["n"] += n
    if not res.pairs:
        a["reg_not_ok"] += 1
        a["verdicts"]["failed"] += n
        a["pose"] += [metrics.mtre_mm(res.registration.pose, case.frame_pose(t), P) for t in range(n)]
        return
    for p in res.pairs:
        fr, t = p.result, p.result.index
        a["verdicts"][fr.verdict.value] += 1
        a["ab"] += p.views == "AB"
        pose = fr.pose if fr.pose is not None else res.registration.pose
        a["pose"].append(metrics.mtre_mm(pose, case.frame_pose(t), P))
        if fr.motion is not None:
            a["motion"][fr.motion.verdict.value] += 1
            a["motion_ab"] += motion_planes(fr.motion) == "AB"
            a["ms"].append(fr.motion.seconds * 1000)
            if np.isfinite(fr.motion.pose_std_mm):
                a["std"].append(fr.motion.pose_std_mm)
                a["pose_t"].append(a["pose"][-1])
        if fr:
            vis = np.asarray(case.wire_visible[t], bool)
            true = np.asarray(case.wire_lps_mm[t])[vis]
            e = metrics.wire_errors_mm(fr.wire3d.points_lps_mm, true)
            a["err"].append(e["mean_error_mm"])
            a["tip"].append(e["tip_error_mm"])
            ok = fr.verdict.value == "ok"
            a["ok_wire_off"] += ok and e["mean_error_mm"] > WIRE_OFF_MM
            a["ok_tip_off"] += ok and e["tip_error_mm"] > TIP_OFF_MM
            if ok and (e["mean_error_mm"] > WIRE_OFF_MM or e["tip_error_mm"] > TIP_OFF_MM):
                a["wrong"].append(f"seed {case.options.seed} pair {t}: wire {e['mean_error_mm']:.2f} mm, tip "
                                  f"{e['tip_error_mm']:.1f} mm, pose {a['pose'][-1]:.2f} mm, views {p.views or '-'}: "
                                  f"{fr.message[:160]}")


def _row(name: str, a: dict) -> list[str]:
    def med(x, fmt="{:.2f}"):
        return fmt.format(np.median(x)) if len(x) else "-"

    v, m = a["verdicts"], a["motion"]
    calib = (f"{np.sqrt(np.mean(np.square(a['pose_t'])) / np.mean(np.square(a['std']))):.2f}" if a["std"] else "-")
    return [name, med(a["err"]), f"{np.mean(a['err']):.2f}" if a["err"] else "-",
            f"{np.percentile(a['err'], 90):.2f}" if a["err"] else "-", med(a["tip"]),
            f"{np.percentile(a['tip'], 90):.1f}" if a["tip"] else "-", med(a["pose"]), f"{np.mean(a['pose']):.2f}",
            f"{np.percentile(a['pose'], 90):.2f}", f"{v['ok']} / {v['uncertain']} / {v['failed']}",
            a["ok_wire_off"], a["ok_tip_off"], f"{a['ab']}/{a['n']}",
            f"{m['ok']} / {m['uncertain']} / {m['failed']} ({a['motion_ab']} AB)" if a["ms"] else "-", calib,
            med(a["ms"], "{:.1f}"), a["reg_not_ok"]]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=8)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--breathing", type=float, default=15.0, help="mm peak-to-peak (default 15)")
    ap.add_argument("--cardiac", type=float, default=2.0, help="mm (default 2)")
    ap.add_argument("--segmenter", default="unet", choices=("unet", "ridge"))
    args = ap.parse_args(argv)

    from guidewire3d.app import bench, biplane
    from guidewire3d.phantom import PhantomOptions, simulate

    print(f"machine: {bench.machine_line()}, load average {os.getloadavg()[0]:.1f}")
    acc = {track: _acc() for track in (False, True)}
    t_all = time.perf_counter()
    for k in range(args.cases):
        seed = args.seed0 + k
        t0 = time.perf_counter()
        case = simulate(PhantomOptions(seed=seed, n_frames=args.frames, breathing_mm=args.breathing,
                                       cardiac_mm=args.cardiac, biplane=True))
        road, live = _runs(case)
        line = []
        for track in (False, True):
            t1 = time.perf_counter()
            res = biplane.run(case.volume, road, live, segmenter=args.segmenter, track_motion=track)
            acc[track]["seconds"] += time.perf_counter() - t1
            _score(acc[track], case, res)
            vs = [p.result.verdict.value for p in res.pairs]
            line.append(f"{'tracked' if track else 'static'}: reg {res.registration.result.verdict.value}, "
                        f"ok {vs.count('ok')}/{len(case.frames)}")
        print(f"  case {k + 1}/{args.cases} (seed {seed}, {time.perf_counter() - t0:.0f} s): {'; '.join(line)}",
              file=sys.stderr, flush=True)
    print(f"\nsimulator, biplane, the whole chain (biplane.run: vessels from the CT, joint registration, pairs; segmenter "
          f"{args.segmenter}): {args.cases} sequences x {args.frames} frame pairs at 15 fps, breathing {args.breathing:g} "
          f"mm, cardiac {args.cardiac:g} mm (seeds {args.seed0}-{args.seed0 + args.cases - 1}); "
          f"{time.perf_counter() - t_all:.0f} s; load average now {os.getloadavg()[0]:.1f}")
    rows = [_row("joint roadmap pose (static)", acc[False]), _row("track_motion (both planes)", acc[True])]
    print(bench._table(["pose", "3D wire median mm", "mean mm", "p90 mm", "tip median mm", "tip p90 mm",
                        "pose mTRE median mm", "mean mm", "p90 mm", "pairs ok / uncertain / failed",
                        f"ok, wire > {WIRE_OFF_MM:g} mm off", f"ok, tip > {TIP_OFF_MM:g} mm off",
                        "pairs from both planes", "tracker ok / uncertain / failed", "pose err / reported 1 sigma",
                        "tracking ms/pair (median)", "registrations not ok"], rows))
    for track, name in ((False, "static"), (True, "tracked")):
        if acc[track]["wrong"]:
            print(f"\n{name}: ok pairs whose wire is more than {WIRE_OFF_MM:g} mm or tip more than {TIP_OFF_MM:g} mm off")
            print("\n".join(f"  {w}" for w in acc[track]["wrong"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
