"""Per-frame diagnosis of the live engine on ``bench_real_anatomy.py``'s frames (issue 17), in the true pose.

The benchmark's poses and live frames (the same ``--seed``, ``make_pose`` and ``render`` calls: four frames per
pose, the tip 90, 60, 30 and 0 mm before the end of the wire's path) are rendered once and cached under
``--cache`` with ``diagnose_real_anatomy.py``'s roadmaps (about 1 min per pose); the automatic tree is the
benchmark's cached one. Each pose's frames go
through ``live.Session`` at the **true** pose (the registration taken out), and are scored against the true
wire's in-image part: the verdicts, the reasons of the ``uncertain`` ones, the ``ok`` frames whose wire is more
than ``WIRE_OFF_MM`` or whose tip is more than ``TIP_OFF_MM`` off (silently wrong), and per 3D wire point its
distance from the true wire (and the part of it along the beam) against its own uncertainty, by the tree's
radius at the point.

``--root entry`` roots the tree at its point nearest the true wire's entry (its first point, the lowest
aorta point: a transfemoral wire) instead of the tree's own root (since stop 47 the lower end of its aorta,
``vesseltree.rooted_at_caudal_end``; before, its widest end), as the product's ``--access-lps`` does
with the access point a clinician gives (``vesseltree.rooted_at_access``).

    nice .venv/bin/python scripts/diagnose_real_frames.py --poses 20 [--root entry] [--biplane]
"""
from __future__ import annotations

import argparse
import collections
import os
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import bench_real_anatomy as b  # noqa: E402
import real_anatomy as ra  # noqa: E402

RADIUS_BINS_MM = ((0, 2), (2, 4), (4, 7), (7, 10), (10, 20))


def cached_frames(n: int, seed: int, cache: Path, log) -> list[dict]:
    """Poses ``0..n-1`` of ``seed`` as the benchmark draws them: ``carm``, ``pose``, ``frames`` and the true wire of
    each frame (``true_wires``), rendered once and cached with the roadmaps of ``diagnose_real_anatomy.py``."""
    from diagnose_real_anatomy import prepared_cases

    return prepared_cases(n, seed, cache, log)


def entry_rooted(tree, true_wire_lps_mm):
    """``tree`` rooted at its point nearest the true wire's first point, where the wire enters: what the product's
    ``--access-lps`` does (``vesseltree.rooted_at_access``) with the access a clinician gives."""
    from guidewire3d.vesseltree import rooted_at_access

    return rooted_at_access(tree, np.asarray(true_wire_lps_mm)[0])


def plane_b(P, seed: int, wires, iodine, mu_ct, vol):
    """Plane B of pose ``P`` (``cached_frames``): a view 90 deg from plane A's primary angle (towards the
    patient's midline: LAO 90 - a, or RAO), no angulation, the same SID, SOD and detector, about the same isocentre
    (the same patient pose), and its live frames of the same wire (``bench_real_anatomy.render``, its own noise)."""
    carm_b = b.plane_b_carm(P["carm"])
    rng = np.random.default_rng([seed, int(P["k"]), 2])
    _, frames, _, _ = b.render(rng, carm_b, P["pose"], wires[P["target"]], iodine, mu_ct, vol)
    return carm_b, frames


def point_errors(carm, pose, wire3d, true_lps_mm, tree) -> dict:
    """Per 3D wire point: distance to the true wire (mm), its part along the beam, the tree's radius at the
    point's nearest tree point, and the point's own uncertainty (1 sigma, mm)."""
    from guidewire3d.metrics import resample_polyline
    from scipy.spatial import cKDTree

    X = np.asarray(wire3d.points_lps_mm, float)
    T = resample_polyline(np.asarray(true_lps_mm, float), 0.2)
    dist, idx = cKDTree(T).query(X)
    beam_lps = pose.R.T @ carm.beam_direction
    rad = tree.radius_mm[cKDTree(tree.points_lps_mm).query(X)[1]]
    return dict(err=dist, along=np.abs((X - T[idx]) @ beam_lps), rad=rad, unc=np.asarray(wire3d.uncertainty_mm, float))


def main(argv=None):
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ra.add_pose_arguments(ap)
    ap.add_argument("--root", choices=("auto", "entry"), default="auto",
                    help="auto: the automatic tree as it is (rooted at its aorta's lower end); entry: rooted where the "
                         "true wire enters, as --access-lps roots it")
    ap.add_argument("--biplane", action="store_true",
                    help="a second plane at the same pose (plane_b: 90 deg from plane A, no angulation), both through "
                         "app.biplane.BiplaneSession")
    ap.add_argument("--sigma-centerline-mm", type=float, default=None,
                    help="the reconstruction's CTA centerline error (ReconOptions.sigma_centerline_mm; default: the "
                         "engine's)")
    a = ap.parse_args(argv)
    from guidewire3d import metrics
    from guidewire3d.app.biplane import BiplaneSession
    from guidewire3d.reconstruction import ReconOptions
    from guidewire3d.live import Session

    cache = Path(a.cache).expanduser()

    def log(m):
        print(m, file=sys.stderr, flush=True)

    tree0 = b.automatic_tree(cache, log)
    poses = cached_frames(a.poses, a.seed, cache, log)
    if a.biplane:
        vol, labels, _, _ = ra.load_case(cache)
        wires, mu_ct = b.cached_wires(vol, labels, cache), ra.anatomy_mu(vol, labels)
        iodine = ra.iodine_fraction(vol, labels)
    rows, pts = [], []
    for P in poses:
        carm, pose = P["carm"], P["pose"]
        tree = entry_rooted(tree0, P["true_wires"][0]) if a.root == "entry" else tree0
        options = None if a.sigma_centerline_mm is None else ReconOptions(sigma_centerline_mm=a.sigma_centerline_mm)
        if a.biplane:
            carm_b, frames_b = plane_b(P, a.seed, wires, iodine, mu_ct, vol)
            session = BiplaneSession(tree, (carm, carm_b), pose, options=options, threads=1)
            session.warm_up(P["frames"][0], frames_b[0])
            results = [session.process(fa, fb).result for fa, fb in zip(P["frames"], frames_b)]
        else:
            session = Session(tree, carm, pose, options=options)
            session.warm_up(P["frames"][0])
            results = session.run(P["frames"])
        for t, (fr, tw) in enumerate(zip(results, P["true_wires"])):
            tru = b.visible_part(carm, pose, tw)
            row = dict(k=P["k"], t=t, verdict=fr.verdict.value, msg=fr.message, err=np.nan, tip=np.nan,
                       sig=np.nan, tip_sig=np.nan)
            if fr.wire3d and len(tru) >= 2:
                e = metrics.wire_errors_mm(fr.wire3d.points_lps_mm, tru)
                u = np.asarray(fr.wire3d.uncertainty_mm, float)
                row.update(err=e["mean_error_mm"], tip=e["tip_error_mm"], sig=float(np.median(u)) if len(u) else np.nan,
                           tip_sig=float(u[-1]) if len(u) else np.nan)
                pe = point_errors(carm, pose, fr.wire3d, tru, tree)
                pe["ok"] = np.full(len(pe["err"]), fr.verdict.value == "ok")
                pts.append(pe)
            rows.append(row)
    n = collections.Counter(r["verdict"] for r in rows)
    E, T = np.array([r["err"] for r in rows]), np.array([r["tip"] for r in rows])
    ok = np.array([r["verdict"] == "ok" for r in rows])
    wrong = ok & ((E > b.WIRE_OFF_MM) | (T > b.TIP_OFF_MM))
    print(f"{len(poses)} poses, {len(rows)} frames, true pose, tree root: {a.root}"
          + (", biplane (plane B 90 deg from plane A)" if a.biplane else "") + f"; load {os.getloadavg()[0]:.1f}")
    print(f"verdicts: ok {n['ok']}, uncertain {n['uncertain']}, failed {n['failed']}; ok with the wire > "
          f"{b.WIRE_OFF_MM:g} mm or the tip > {b.TIP_OFF_MM:g} mm off (silently wrong): {int(wrong.sum())}")
    for r in rows:
        if r["verdict"] == "ok":
            print(f"  ok: pose {r['k']} frame {r['t']}: wire {r['err']:.2f} mm, tip {r['tip']:.2f} mm; its points' "
                  f"median 1 sigma {r['sig']:.1f} mm, the tip's {r['tip_sig']:.1f} mm"
                  + ("  SILENTLY WRONG" if r["err"] > b.WIRE_OFF_MM or r["tip"] > b.TIP_OFF_MM else ""))
    for r in rows:
        if r["verdict"] == "failed":
            print(f"  failed: pose {r['k']} frame {r['t']}: {r['msg']}")
    from bench_stress import REASONS

    reasons = collections.Counter(name for r in rows if r["verdict"] == "uncertain"
                                  for name, words in REASONS.items() if words in r["msg"])
    print("reasons of the uncertain frames (bench_stress.REASONS; a frame may have several): "
          + ", ".join(f"{name} {c}" for name, c in reasons.most_common()))
    if pts:
        cat = {key: np.concatenate([p[key] for p in pts]) for key in ("err", "along", "rad", "unc", "ok")}
        print("\n| tree radius mm | points | mean error mm | of it along the beam | mean uncertainty (1 sigma) mm "
              "| error <= 2 sigma |")
        print("|---|---|---|---|---|---|")
        for lo, hi in RADIUS_BINS_MM:
            m = (cat["rad"] >= lo) & (cat["rad"] < hi)
            if m.any():
                print(f"| {lo}-{hi} | {int(m.sum())} | {cat['err'][m].mean():.1f} | {cat['along'][m].mean():.1f} | "
                      f"{cat['unc'][m].mean():.1f} | {np.mean(cat['err'][m] <= 2 * cat['unc'][m]):.2f} |")
        m = cat["ok"].astype(bool)
        if m.any():
            print(f"ok frames' points: mean error {cat['err'][m].mean():.2f} mm, "
                  f"{np.mean(cat['err'][m] <= 2 * cat['unc'][m]):.2f} within 2 sigma")


if __name__ == "__main__":
    main()
