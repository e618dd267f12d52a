"""Which end is the tip: frame verdicts against the truth when the CTA misses the proximal vessels.

The simulated tree is cut ``--cut`` mm below its root along the wire's path (the wire's proximal
part then runs beyond the segmented tree and projects over other branches); each frame goes
through ``live.Session`` at the true pose. A tip at the wrong end must never be ``ok``.

    nice .venv/bin/python scripts/bench_orientation.py --seeds 20 --cut 0 25 40
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
    args = ap.parse_args()

    from guidewire3d.app import bench
    from guidewire3d.live import session as live
    from guidewire3d.phantom import PhantomOptions, simulate

    cases = [simulate(PhantomOptions(seed=s, n_frames=args.frames), make_ct=False) for s in range(args.seeds)]
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
        rows.append(["whole tree" if cut <= 0 else f"cut {cut:g} mm below the root", n["n"], n[("ok", False)],
                     n[("uncertain", False)], n[("uncertain", True)], n[("ok", True)]])
    print(f"seeds 0-{args.seeds - 1}, {args.frames} frames each, true pose; machine: {bench.machine_line()}, "
          f"load average {os.getloadavg()[0]:.1f}")
    print(bench._table(["tree", "frames reconstructed", "ok, right end", "uncertain, right end", "uncertain, wrong end",
                        "ok, WRONG end"], rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
