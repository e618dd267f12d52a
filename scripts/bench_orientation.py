"""Which end is the tip, and is it the tip: frame verdicts against the truth.

The simulated tree is cut ``--cut`` mm below its root along the wire's path (the wire's proximal
part then runs beyond the segmented tree and projects over other branches); each frame goes
through ``live.Session`` at the true pose. A tip at the wrong end must never be ``ok``; nor should
a tip far short of the true one (a stretch of the wire lost by the segmenter before its tip):
the last columns count the ``ok`` frames whose tip is more than ``--tip-mm`` from the true
(visible) tip, the frames made ``uncertain`` by a piece of the wire beyond the traced tip, and
those made ``uncertain`` by two layers of wire at the traced tip (the wire bends back over itself),
and those made ``uncertain`` because the tip's vessel runs along the beam (``live.TIP_STRETCH_MAX_MM``).

    nice .venv/bin/python scripts/bench_orientation.py --seeds 20 --cut 0 25 40
    nice .venv/bin/python scripts/bench_orientation.py --seeds 20 --frames 6 --cut 0 --wire-diameter 0.25
"""
from __future__ import annotations

import argparse
import collections
import os

import numpy as np


def cut_below(tree, path_ids, cut_mm: float):
    """The subtree below the wire path's point ``cut_mm`` from the root (the whole tree for 0)."""
    if cut_mm <= 0:
        return tree
    s = tree.arclength_from_root_mm
    node = path_ids[np.searchsorted(s[path_ids], cut_mm)]
    keep = np.zeros(tree.n_points, bool)
    for i in tree.order:  # root first
        keep[i] = i == node or (tree.parent[i] >= 0 and keep[tree.parent[i]])
    return tree.subtree(keep)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--cut", type=float, nargs="+", default=[0.0, 25.0, 40.0])
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--wire-diameter", type=float, default=None, help="mm (default: the simulator's, per seed)")
    ap.add_argument("--tip-mm", type=float, default=5.0, help="a right-end tip farther than this from the true one is off")
    args = ap.parse_args()

    from guidewire3d.app import bench
    from guidewire3d.live import session as live
    from guidewire3d.phantom import PhantomOptions, simulate

    seeds = range(args.seed0, args.seed0 + args.seeds)
    cases = [simulate(PhantomOptions(seed=s, n_frames=args.frames, wire_diameter_mm=args.wire_diameter), make_ct=False)
             for s in seeds]
    rows = []
    for cut in args.cut:
        n = collections.Counter()
        for case in cases:
            session = live.Session(cut_below(case.tree, case.wire_path_point_ids, cut), case.carm, case.pose)
            for t, frame in enumerate(case.frames):
                fr = session.process(frame)
                if not fr:
                    continue
                true_tip = case.wire_lps_mm[t][-1]
                wrong = (np.linalg.norm(fr.wire3d.points_lps_mm[0] - true_tip)
                         < np.linalg.norm(fr.wire3d.points_lps_mm[-1] - true_tip))
                n["n"] += 1
                n[(fr.verdict.value, wrong)] += 1
                visible_tip = case.wire_lps_mm[t][np.asarray(case.wire_visible[t], bool)][-1]
                tip_mm = float(np.linalg.norm(fr.tip_lps_mm - visible_tip))
                if fr.verdict.value == "ok" and not wrong:
                    n["ok_tip_off"] += tip_mm > args.tip_mm
                    n["ok_tip_max"] = max(n["ok_tip_max"], tip_mm)
                if fr.verdict.value == "uncertain" and not wrong:
                    n["unc_tip_off"] += tip_mm > args.tip_mm
                if getattr(fr.wire2d, "beyond_tip", None) is not None:
                    n["beyond"] += 1
                    n["beyond_off"] += tip_mm > args.tip_mm
                if "tip uncertain: the wire's last" in fr.message:
                    n["doubled"] += 1
                    n["doubled_off"] += tip_mm > args.tip_mm
                    # the only reason: ok without this check (the reasons of frame_verdict are independent)
                    if len(fr.message.split("; ")) == 1:
                        n["doubled_only_wrong_end" if wrong else "doubled_only"] += 1
                        n["doubled_only_off"] += (tip_mm > args.tip_mm) and not wrong
                if "tip uncertain: its vessel runs along the beam" in fr.message:
                    n["along"] += 1
                    n["along_off"] += tip_mm > args.tip_mm
                    if len(fr.message.split("; ")) == 1:      # the only reason: ok without this check
                        n["along_only"] += 1
                        n["along_only_off"] += (tip_mm > args.tip_mm) and not wrong
        rows.append(["whole tree" if cut <= 0 else f"cut {cut:g} mm below the root", n["n"], n[("ok", False)],
                     f"{n[('uncertain', False)]} ({n['unc_tip_off']})", n[("uncertain", True)], n[("ok", True)],
                     n["ok_tip_off"], f"{n['ok_tip_max']:.1f}", f"{n['beyond']} ({n['beyond_off']})",
                     f"{n['doubled']} ({n['doubled_off']})",
                     f"{n['doubled_only']} ({n['doubled_only_off']}), wrong end {n['doubled_only_wrong_end']}",
                     f"{n['along']} ({n['along_off']}); ok without it {n['along_only']} ({n['along_only_off']})"])
    wire = "simulator's" if args.wire_diameter is None else f"{args.wire_diameter:g} mm"
    print(f"seeds {seeds[0]}-{seeds[-1]}, {args.frames} frames each, true pose, {wire} wire; machine: "
          f"{bench.machine_line()}, load average {os.getloadavg()[0]:.1f}")
    print(bench._table(["tree", "frames reconstructed", "ok, right end", f"uncertain, right end (tip > {args.tip_mm:g} mm off)",
                        "uncertain, wrong end",
                        "ok, WRONG end", f"ok, right end, tip > {args.tip_mm:g} mm off", "largest ok tip error mm",
                        f"wire beyond the tip: uncertain (tip > {args.tip_mm:g} mm off)",
                        f"two layers at the tip: uncertain (tip > {args.tip_mm:g} mm off)",
                        f"of which ok without that check: right end (tip > {args.tip_mm:g} mm off)",
                        f"vessel along the beam at the tip: uncertain (tip > {args.tip_mm:g} mm off); ok without that "
                        "check"], rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
