"""Cut the branches of a vessel tree whose wide axis is dim: they are not contrast-filled lumens.

A contrast-filled vessel at least a few millimetres wide has the lumen's intensity on its axis
(partial volume dims only thinner ones). A wide branch whose axis is much dimmer is something
else that the threshold took in: an unenhanced or late vein (the portal and splenic veins of an
arterial-phase MR angiogram), bone marrow, or an enhancing organ. When such branches are a
minority of a tree, the rest of it can be the arterial tree the user asked for; this module
removes them, with everything that hangs beyond them (seen from the root), from the tree and
from the mask, and says what it removed. The caller judges the result again
(:func:`guidewire3d.cta.vesselmodel.check_plausibility`).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from guidewire3d import io
from guidewire3d.cta.centerline import _rooted_at_widest_end
from guidewire3d.cta.surface import surface_from_mask
from guidewire3d.cta.vessels3d import CTAVessels

__all__ = ["DimWidePruning", "dim_wide_points", "without_dim_wide_branches"]

#: mask voxels are given to the centerline point with the smallest ``distance - radius`` among
#: this many nearest points (a voxel of a wide trunk beside a thin branch's point goes to the trunk)
ASSIGN_NEIGHBOURS = 12


@dataclass(frozen=True)
class DimWidePruning:
    """What :func:`without_dim_wide_branches` removed, and the vessels that remain."""

    vessels: CTAVessels
    removed_branches: int
    removed_length_mm: float
    removed_cm3: float

    def explain(self) -> str:
        return (f"{self.removed_branches} wide branch(es) with a dim axis removed ({self.removed_length_mm:.0f} mm of "
                f"centerline, {self.removed_cm3:.1f} cm3; unenhanced veins, marrow or organ, not a contrast-filled "
                f"lumen), with what lies beyond them")


def dim_wide_points(volume: io.Volume, tree, background: float, lumen: float, *, wide_radius_mm: float,
                    dim_fraction: float) -> np.ndarray:
    """``(n_points,)`` bool: the points of the branches whose median radius is at least
    ``wide_radius_mm`` and whose median axis intensity (trilinear) is below ``background +
    dim_fraction (lumen - background)``; each point counted in the branch ``tree.point_branch``
    gives it (after its start node, the root in branch 0)."""
    pts = np.asarray(tree.points_lps_mm, dtype=float)
    out = np.zeros(len(pts), bool)
    if len(pts) < 2 or not lumen > background:
        return out
    val = ndi.map_coordinates(np.asarray(volume.array_zyx, dtype=np.float32), volume.lps_to_index_zyx(pts).T,
                              order=1, mode="nearest")
    frac = (val - background) / (lumen - background)
    for b in tree.branches:
        ids = b.point_ids if b.index == 0 else b.point_ids[1:]
        if len(ids) and np.median(tree.radius_mm[ids]) >= wide_radius_mm and np.median(frac[ids]) < dim_fraction:
            out[ids] = True
    return out


def _beyond(tree, cut: np.ndarray) -> np.ndarray:
    """``cut`` and every point whose path to the root passes through a cut point."""
    bad = np.asarray(cut, bool).copy()
    par = tree.parent
    for i in tree.order:                     # parents before children
        if par[i] >= 0 and bad[par[i]]:
            bad[i] = True
    return bad


def _mask_of_points(mask_zyx: np.ndarray, volume: io.Volume, tree, keep_points: np.ndarray) -> np.ndarray:
    """The mask's voxels whose centerline point (smallest distance minus radius among the
    ``ASSIGN_NEIGHBOURS`` nearest) is kept."""
    idx = np.argwhere(mask_zyx)
    if not len(idx):
        return mask_zyx.copy()
    xyz = volume.index_zyx_to_lps(idx.astype(float))
    k = min(ASSIGN_NEIGHBOURS, tree.n_points)
    d, j = cKDTree(tree.points_lps_mm).query(xyz, k=k)
    d, j = d.reshape(len(idx), k), j.reshape(len(idx), k)
    best = j[np.arange(len(idx)), np.argmin(d - tree.radius_mm[j], axis=1)]
    out = np.zeros_like(mask_zyx, dtype=bool)
    sel = keep_points[best]
    out[tuple(idx[sel].T)] = True
    return out


def without_dim_wide_branches(volume: io.Volume, vessels: CTAVessels, *, background: float, lumen: float,
                              wide_radius_mm: float, dim_fraction: float, max_fraction: float,
                              seeds_lps_mm=None, seed_radius_mm: float = 3.0) -> DimWidePruning | None:
    """The vessels without their wide branches with a dim axis (:func:`dim_wide_points`) and what
    lies beyond them, or None when that cannot give a tree: no such branch, more than
    ``max_fraction`` of the length in them (then the tree is not mostly vessels), the root in one,
    or a seed (farther than ``seed_radius_mm`` from every remaining point) cut off.
    """
    tree = vessels.tree
    dim = dim_wide_points(volume, tree, background, lumen, wide_radius_mm=wide_radius_mm, dim_fraction=dim_fraction)
    if not dim.any():
        return None
    if dim[tree.root]:                       # rooted at a dim vessel's end: the widest end of the others instead
        tree = _rooted_at_widest_end(tree, allowed=~dim)
        if dim[tree.root]:
            return None
    seg = tree.length_at_point_mm
    total = float(seg.sum())
    if total <= 0 or float(seg[dim].sum()) > max_fraction * total:
        return None
    cut = _beyond(tree, dim)
    keep = ~cut
    if keep.sum() < 2:
        return None
    if seeds_lps_mm is not None:
        seeds = np.atleast_2d(np.asarray(seeds_lps_mm, dtype=float))
        d, j = cKDTree(tree.points_lps_mm[keep]).query(seeds)
        if np.any(d - tree.radius_mm[keep][j] > seed_radius_mm):     # a seed in a removed lumen
            return None
    mask = _mask_of_points(vessels.mask_zyx, volume, tree, keep)
    mask.setflags(write=False)
    surf = surface_from_mask(mask, spacing_mm=volume.spacing_mm, origin_lps_mm=volume.origin_lps_mm,
                             direction=volume.direction)
    removed_branches = sum(1 for b in tree.branches if cut[b.point_ids[-1]])
    vox_cm3 = float(np.prod(volume.spacing_mm)) / 1000.0
    removed_cm3 = float(np.count_nonzero(vessels.mask_zyx) - np.count_nonzero(mask)) * vox_cm3
    out = replace(vessels, mask_zyx=mask, surface=surf, tree=tree.subtree(keep), seconds=dict(vessels.seconds))
    return DimWidePruning(out, removed_branches, float(seg[cut].sum()), removed_cm3)
