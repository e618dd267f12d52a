"""Loops of the skeleton where two vessels cross (``centerline._recut_loops``, ``_crossings``).

Ground truth: a synthetic mask whose vessels are known. A trunk gives off a branch whose origin the
partial volume narrows to a waist, and a second branch that crosses the first one 20 mm beyond it.
The skeleton then has a loop (trunk, branch, crossing, second branch), and its thinnest edge is
the first branch's waist. ``bench_stress`` 10115 frame 2 was that case: the wire's branch, cut at its
origin, hung backwards from the crossing, and the tip was put in another vessel 14 mm off.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from skimage.morphology import skeletonize

from guidewire3d.cta.centerline import _crossings, centerline_from_mask
from guidewire3d.cta.grid import edt_mm

SP_MM = 0.5


def _tube(shape, a_mm, b_mm, ra_mm, rb_mm):
    """A mask of the tube from ``a_mm`` to ``b_mm`` (x, y, z) whose radius runs linearly from ``ra_mm`` to ``rb_mm``."""
    z, y, x = np.indices(shape, dtype=float) * SP_MM
    p = np.stack([x, y, z], axis=-1)
    a, b = np.asarray(a_mm, float), np.asarray(b_mm, float)
    t = np.clip(((p - a) @ (b - a)) / float((b - a) @ (b - a)), 0.0, 1.0)
    d = np.linalg.norm(p - (a + t[..., None] * (b - a)), axis=-1)
    return d <= ra_mm + t * (rb_mm - ra_mm)


def _crossing_mask(waist_mm: float):
    shape = (40, 130, 140)                                  # z, y, x at 0.5 mm: 20 x 65 x 70 mm
    m = _tube(shape, (2, 15, 10), (68, 15, 10), 2.4, 2.0)   # the trunk along x, widest at x = 2 (the root)
    o = np.array([18.0, 15.0, 10.0])                        # the first branch's origin on the trunk's axis
    u = np.array([0.6, 0.8, 0.0])
    m |= _tube(shape, o, o + 2.5 * u, 1.3, 1.3)             # (inside the trunk)
    m |= _tube(shape, o + 2.5 * u, o + 6.5 * u, waist_mm, waist_mm)  # its origin, narrowed
    m |= _tube(shape, o + 6.5 * u, o + 55 * u, 1.3, 1.1)    # then the branch
    c = np.array([58.0, 15.0, 10.0])                        # the second branch leaves at x = 58 ...
    m |= _tube(shape, c, (20.0, 60.0, 10.0), 1.2, 1.0)     # ... and crosses the first one
    return m


def _first_branch_route_mm(tree):
    """The tree's route from its root to a point 10 mm along the first branch, against the way along the vessels."""
    o = np.array([18.0, 15.0, 10.0])
    q = o + 10.0 * np.array([0.6, 0.8, 0.0])
    P = tree.points_lps_mm                                  # identity direction, origin 0: LPS = (x, y, z) mm
    k = int(np.argmin(np.linalg.norm(P - q, axis=1)))
    assert np.linalg.norm(P[k] - q) < 1.5                   # the branch is in the tree
    return float(tree.arclength_from_root_mm[k]), 16.0 + 10.0


def test_a_crossing_is_found_and_a_bifurcation_is_not():
    m = _crossing_mask(0.75)
    vox = np.column_stack(np.nonzero(skeletonize(m)))
    pairs = cKDTree(vox).query_pairs(np.sqrt(3) + 1e-6, output_type="ndarray")
    r = edt_mm(m, np.full(3, SP_MM))[tuple(vox.T)]
    cross = _crossings(vox, pairs, r, np.full(3, SP_MM))
    at = vox[cross >= 0] * SP_MM                            # z, y, x mm
    assert len(at)
    # where the branches cross: the first branch's axis meets the second's at about (x 36.6, y 39.8)
    centre = at.mean(axis=0)
    assert abs(centre[2] - 36.6) < 3.0 and abs(centre[1] - 39.8) < 3.0
    # the trunk's two bifurcations (x 18 and 58, y 15) are not crossings
    assert not np.any((np.abs(at[:, 1] - 15.0) < 4.0))


def test_a_branch_narrowed_at_its_origin_keeps_its_origin_where_it_crosses_another():
    m = _crossing_mask(0.75)
    tree = centerline_from_mask(m, spacing_mm=(SP_MM,) * 3, origin_lps_mm=(0.0, 0.0, 0.0))
    assert np.linalg.norm(tree.points_lps_mm[tree.root] - (2.0, 15.0, 10.0)) < 4.0   # rooted at the trunk's wide end
    route, along = _first_branch_route_mm(tree)
    # from its origin on the trunk (16 mm from the root's end, 10 mm along the branch), not round through the
    # second branch and the crossing (about 90 mm)
    assert route < along + 8.0, route


def test_without_a_waist_the_tree_is_the_same():
    # the branch as wide at its origin as beyond: the thinnest edge of the loop lies elsewhere, and the first
    # branch's route is its own either way
    m = _crossing_mask(1.3)
    tree = centerline_from_mask(m, spacing_mm=(SP_MM,) * 3, origin_lps_mm=(0.0, 0.0, 0.0))
    route, along = _first_branch_route_mm(tree)
    assert route < along + 8.0, route
