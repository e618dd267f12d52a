"""Centerline of wide vessels on thick-slice volumes (issue 17): a curved 8-12 mm radius tube with a
4 mm side branch, sampled on 0.7 x 0.7 x 2.5 mm voxels, against its known axes."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from guidewire3d.cta.centerline import CenterlineOptions, _isotropic_mask, centerline_from_mask

SPACING_XYZ = (0.7, 0.7, 2.5)
ISO = CenterlineOptions(isotropic_ratio=1.5)


def _phantom():
    """Mask (z, y, x) of a trunk along an arc (radius of curvature 70 mm, in the x-z plane, so it
    crosses the slices obliquely) whose radius grows from 8 to 12 mm, with a 4 mm branch leaving it
    at 60 degrees; and the dense true axes (LPS mm, origin 0, identity direction)."""
    t = np.linspace(-0.9, 0.9, 1200)
    R = 70.0
    trunk = np.column_stack([60 + R * np.sin(t), np.full_like(t, 35.0), 40 + R * (1 - np.cos(t)) * 0.8 + 30 * (t + 0.9)])
    r_trunk = 8.0 + 4.0 * (t - t[0]) / (t[-1] - t[0])
    j = trunk[600]
    d = np.array([0.0, np.sin(np.radians(60)), 0.0]) + np.array([0.0, 0.0, 0.5])
    d /= np.linalg.norm(d)
    s = np.linspace(0.0, 40.0, 400)
    branch = j + s[:, None] * d
    r_branch = np.full(len(s), 4.0)
    sp = np.array(SPACING_XYZ)
    shape_xyz = np.ceil(np.array([125.0, 85.0, 150.0]) / sp).astype(int)
    grid = np.stack(np.meshgrid(*[np.arange(n) * s_ for n, s_ in zip(shape_xyz, sp)], indexing="ij"), -1).reshape(-1, 3)
    inside = np.zeros(len(grid), bool)
    for axis, rad in ((trunk, r_trunk), (branch, r_branch)):
        dist, k = cKDTree(axis).query(grid)
        inside |= dist <= rad[k]
    mask_xyz = inside.reshape(*shape_xyz)
    return np.ascontiguousarray(mask_xyz.transpose(2, 1, 0)), trunk, branch, r_trunk


def _axis_errors(tree, trunk, branch, r_trunk):
    """Distance (mm) of each tree point to the true axes, and of each true trunk point (away from
    the caps, which the centerline stops short of by design) to the tree."""
    axes = np.vstack([trunk, branch])
    d_est = cKDTree(axes).query(tree.points_lps_mm)[0]
    s = np.r_[0, np.cumsum(np.linalg.norm(np.diff(trunk, axis=0), axis=1))]
    mid = (s > r_trunk[0] + 2) & (s < s[-1] - r_trunk[-1] - 2)
    d_ref = cKDTree(tree.points_lps_mm).query(trunk[mid])[0]
    return d_est, d_ref


@pytest.fixture(scope="module")
def phantom():
    return _phantom()


def test_isotropic_mask_keeps_the_shape(phantom):
    mask = phantom[0]
    sp_zyx = np.array(SPACING_XYZ)[::-1]
    iso, sp_iso = _isotropic_mask(mask, sp_zyx)
    assert np.allclose(sp_iso, 0.7, atol=0.01)
    assert np.allclose((np.array(iso.shape) - 1) * sp_iso, (np.array(mask.shape) - 1) * sp_zyx)
    # the thick slices are interpolated, not replicated: the volume is kept within 3 %
    v0 = mask.sum() * np.prod(sp_zyx)
    v1 = iso.sum() * np.prod(sp_iso)
    assert abs(v1 - v0) < 0.03 * v0
    # on the original slices the interpolated mask is the original (its level is 0.2 mm outside
    # the half-way surface: the in-plane boundary voxels stay, no voxel is added there)
    k = np.rint(np.arange(mask.shape[0]) * sp_zyx[0] / sp_iso[0]).astype(int)
    on = np.abs(k * sp_iso[0] - np.arange(mask.shape[0]) * sp_zyx[0]) < 1e-6
    assert on.sum() >= 2
    assert (iso[k[on]] == mask[on]).mean() > 0.999


def test_thin_oblique_vessel_stays_connected_on_the_isotropic_copy():
    """A one-voxel vessel stepping one voxel in y and one in x per 2.5 mm slice touches its
    neighbours only at voxel corners; its isotropic copy must stay in one piece (else the skeleton
    keeps a piece). At the half-way level (0) it came apart in 5."""
    from scipy import ndimage as ndi

    m = np.zeros((12, 24, 24), bool)
    for k in range(2, 10):
        m[k, 2 + k, 3 + k] = True
    assert ndi.label(m, structure=np.ones((3, 3, 3)))[1] == 1
    iso, _ = _isotropic_mask(m, np.array([2.5, 0.7, 0.7]))
    assert ndi.label(iso, structure=np.ones((3, 3, 3)))[1] == 1


def test_wide_curved_tube_on_thick_slices_is_centred_without_extra_branches(phantom):
    mask, trunk, branch, r_trunk = phantom
    tree = centerline_from_mask(mask, spacing_mm=SPACING_XYZ, origin_lps_mm=(0, 0, 0), options=ISO)
    d_est, d_ref = _axis_errors(tree, trunk, branch, r_trunk)
    # one trunk, one branch: three branches from the junction (the root's run, the rest of the trunk,
    # the side branch), three ends
    ends = np.r_[tree.root, tree.leaves[tree.leaves != tree.root]]
    assert len(ends) == 3, f"{len(ends)} ends ({len(tree.branches)} branches): spurs or strands left"
    assert np.median(d_est) < 0.5, np.median(d_est)
    assert np.percentile(d_est, 95) < 1.5, np.percentile(d_est, 95)
    assert d_ref.max() < 1.5, d_ref.max()
    # the tree carries its own centerline error (0.4 x the 2.5 mm slices), which covers the actual one (rms per
    # axis across the vessel: the distance to the axis over sqrt(2)); a real CT's is larger than this clean tube's
    assert tree.centerline_sigma_mm == pytest.approx(1.0)
    assert np.sqrt(np.mean(d_est**2) / 2) < tree.centerline_sigma_mm
    # the radius of the trunk is measured, not the distance to the slices
    k = cKDTree(trunk).query(tree.points_lps_mm)[1]
    on_trunk = (d_est < 1.0) & (cKDTree(branch).query(tree.points_lps_mm)[0] > 15.0)
    assert np.median(np.abs(tree.radius_mm[on_trunk] - r_trunk[k[on_trunk]])) < 0.5


def test_isotropic_skeleton_is_closer_to_the_axis_than_the_thick_slice_one(phantom):
    """The default (``isotropic_ratio=0``) thins on the mask's own grid; on this phantom its points
    lie farther from the axis (p95 1.24 against 0.55 mm when written)."""
    mask, trunk, branch, r_trunk = phantom
    iso = centerline_from_mask(mask, spacing_mm=SPACING_XYZ, origin_lps_mm=(0, 0, 0), options=ISO)
    raw = centerline_from_mask(mask, spacing_mm=SPACING_XYZ, origin_lps_mm=(0, 0, 0))
    e_iso = _axis_errors(iso, trunk, branch, r_trunk)[0]
    e_raw = _axis_errors(raw, trunk, branch, r_trunk)[0]
    assert len(iso.branches) <= len(raw.branches)
    assert np.percentile(e_iso, 95) <= np.percentile(e_raw, 95)
