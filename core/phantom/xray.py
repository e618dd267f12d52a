"""The simulator's X-ray: the true patient pose, the C-arm views, and the images seen through them.

Projection with :class:`guidewire3d.geometry.CArm` and the true patient
:class:`~guidewire3d.geometry.Pose`. Attenuation line integrals are exact chord lengths of rays
through mitred cylinder segments (no drawn lines): the roadmap integrates the contrast lumen,
the live frames the wire (and an optional guiding catheter), blurred by focal spot and detector,
with Poisson quantum noise at a relative dose, gain flicker and an optional faint anatomy-like
background. MONOCHROME2: background bright, vessels and wire darker.

The true pose ``T_iso_from_lps`` relates to the registration's start
``nominal_pose(tree.centroid_lps_mm)`` by ``pose @ nominal.inverse() = Pose(R, delta)``: a
rotation about the isocentre of at most 5 degrees and an isocentre offset ``|delta| <= 20 mm``.
The second view (held out, or plane B of a biplane: :func:`biplane_plane_b`) sees the patient
with the same pose.
"""
from __future__ import annotations

import numpy as np
from guidewire3d.geometry import CArm, Pose, so3_exp
from guidewire3d.phantom.anatomy import _every_other, _unit
from guidewire3d.phantom.ct import _smooth_field
from guidewire3d.vesseltree import VesselTree
from scipy import ndimage

__all__ = ["render_tube_line_integral", "biplane_plane_b", "BIPLANE_DEFAULT_SEPARATION_DEG"]


# ======================================================================================
# pose and views
# ======================================================================================
def _sample_pose(rng, centroid) -> Pose:
    rot = _unit(rng.normal(size=3)) * np.radians(rng.uniform(0.5, 5.0))
    delta = _unit(rng.normal(size=3)) * rng.uniform(3.0, 20.0)
    # pose @ nominal^-1 = Pose(R, delta): rotation about the isocentre, then an offset
    R = so3_exp(rot)
    return Pose(R, -R @ np.asarray(centroid) + delta)


def _sample_angles(rng) -> tuple[float, float]:
    return round(float(rng.uniform(-40, 40)), 2), round(float(rng.uniform(-25, 25)), 2)


def _beam(primary, secondary):
    a, b = np.radians(primary), np.radians(secondary)
    return np.array([np.sin(a) * np.cos(b), -np.cos(a) * np.cos(b), np.sin(b)])


def _sample_views(rng, tree: VesselTree, pose: Pose, detector_px: int) -> tuple[CArm, CArm]:
    pa, sa = _sample_angles(rng)
    sid = round(float(rng.uniform(950, 1200)), 1)
    sod = round(float(rng.uniform(650, 800)), 1)
    shape = (detector_px, detector_px)
    probe = CArm(pa, sa, sid, sod, 1.0, shape)
    uv = probe.project(tree.points_lps_mm, pose)
    extent_det_mm = float(np.max(np.ptp(uv, axis=0)))
    fill = rng.uniform(0.85, 1.3)
    pixel = round(float(np.clip(extent_det_mm / (detector_px * fill), 0.15, 0.4)), 4)
    main = CArm(pa, sa, sid, sod, pixel, shape)
    d0 = _beam(pa, sa)
    for _ in range(1000):
        pb, sb = _sample_angles(rng)
        if np.degrees(np.arccos(np.clip(d0 @ _beam(pb, sb), -1, 1))) >= 30.0:
            break
    sid2 = round(float(rng.uniform(950, 1200)), 1)
    sod2 = round(float(rng.uniform(650, 800)), 1)
    held = CArm(pb, sb, sid2, sod2, pixel, shape)
    return main, held


#: default separation of a biplane's plane B from plane A (LAO/RAO), deg
BIPLANE_DEFAULT_SEPARATION_DEG = 90.0


def biplane_plane_b(plane_a: CArm, drawn: CArm, angles_deg=None) -> CArm:
    """Plane B of a biplane case: the drawn second view's SID and SOD, plane A's pixel size, at
    ``angles_deg`` (primary, secondary) or, by default, 90 deg from plane A in LAO/RAO (towards the
    lateral side nearer to it) at 0 deg CRA/CAU, as a frontal + lateral biplane is used."""
    if angles_deg is None:
        pa = float(plane_a.primary_deg)
        pb = pa - BIPLANE_DEFAULT_SEPARATION_DEG if pa >= 0 else pa + BIPLANE_DEFAULT_SEPARATION_DEG
        angles_deg = (pb, 0.0)
    return CArm(float(angles_deg[0]), float(angles_deg[1]), drawn.sid_mm, drawn.sod_mm, plane_a.pixel_mm, plane_a.shape)


# ======================================================================================
# X-ray rendering
# ======================================================================================
def _mitre_chains(chains):
    """Segments (a, b, r, n_a, n_b) of polylines with mitred joints (no overlap, no gap)."""
    A, B, Rr, NA, NB = [], [], [], [], []
    for pts, rad in chains:
        if len(pts) < 2:
            continue
        t = _unit(np.diff(pts, axis=0))
        nj = np.empty((len(pts), 3))
        nj[0], nj[-1] = t[0], t[-1]
        if len(pts) > 2:
            nj[1:-1] = _unit(t[:-1] + t[1:])
        A.append(pts[:-1]), B.append(pts[1:])
        Rr.append(0.5 * (rad[:-1] + rad[1:]))
        NA.append(nj[:-1]), NB.append(nj[1:])
    if not A:
        z = np.zeros((0, 3))
        return z, z, np.zeros(0), z, z
    return np.vstack(A), np.vstack(B), np.concatenate(Rr), np.vstack(NA), np.vstack(NB)


def render_tube_line_integral(carm: CArm, pose: Pose, chains, *, supersample: int = 2,
                              return_fine: bool = False) -> np.ndarray:
    """Line integrals (mm of path length) of the X-rays through tubes, per detector pixel.

    Parameters
    ----------
    carm, pose : the view and the true patient pose.
    chains : list of ``(points_lps_mm (n, 3), radius_mm (n,))`` polylines; each is a tube made of
        cylinders with mitred joints, so consecutive pieces neither overlap nor leave gaps.
    supersample : sub-pixel samples per axis (the result is their mean).
    return_fine : also return the ``(H*s, W*s)`` sub-sample image.

    Returns
    -------
    (rows, cols) float32 array of chord lengths (mm) (and the sub-sample image if asked).
    """
    ss = int(supersample)
    H, W = carm.shape
    fine = np.zeros((H * ss, W * ss), np.float32)
    _accumulate_segments(carm, pose, *_mitre_chains(chains), ss=ss, out=fine)
    coarse = _block_mean(fine, ss)
    return (coarse, fine) if return_fine else coarse


def _block_mean(fine, ss):
    if ss == 1:
        return fine.copy()
    import cv2

    H, W = fine.shape[0] // ss, fine.shape[1] // ss
    return cv2.resize(np.ascontiguousarray(fine, np.float32), (W, H), interpolation=cv2.INTER_AREA)


def _accumulate_segments(carm: CArm, pose: Pose, a_all, b_all, r_all, na_all, nb_all, *, ss: int, out):
    """Add the exact chord length of each pixel sub-sample's ray through each mitred cylinder.

    Segment ``k`` is the cylinder of radius ``r_all[k]`` around ``a_all[k] -> b_all[k]``, cut by the
    planes through ``a`` and ``b`` with normals ``na``/``nb``. ``out`` is the ``(H*ss, W*ss)`` image.
    """
    if len(a_all) == 0:
        return out
    H, W = carm.shape
    Pm = carm.projection_matrix(pose)
    Minv = np.linalg.inv(Pm[:, :3])
    C = -Minv @ Pm[:, 3]
    f = carm.focal_px
    ha = np.c_[a_all, np.ones(len(a_all))] @ Pm.T
    hb = np.c_[b_all, np.ones(len(b_all))] @ Pm.T
    uva, uvb = ha[:, :2] / ha[:, 2:], hb[:, :2] / hb[:, 2:]
    rpx = r_all * f / np.minimum(ha[:, 2], hb[:, 2])
    off = (ss - 1) / 2.0
    reach = rpx + 1.0
    ulo = np.minimum(uva[:, 0], uvb[:, 0]) - reach
    uhi = np.maximum(uva[:, 0], uvb[:, 0]) + reach
    vlo = np.minimum(uva[:, 1], uvb[:, 1]) - reach
    vhi = np.maximum(uva[:, 1], uvb[:, 1]) + reach
    I0 = np.maximum(np.floor(ulo * ss + off).astype(int), 0)
    I1 = np.minimum(np.ceil(uhi * ss + off).astype(int) + 1, W * ss)
    J0 = np.maximum(np.floor(vlo * ss + off).astype(int), 0)
    J1 = np.minimum(np.ceil(vhi * ss + off).astype(int) + 1, H * ss)
    T_all = _unit(b_all - a_all)
    W_all = C - a_all
    G1 = np.einsum("ij,ij->i", W_all, na_all)
    G2 = np.einsum("ij,ij->i", C - b_all, nb_all)
    for k in np.flatnonzero((I0 < I1) & (J0 < J1)):
        i0, i1, j0, j1 = I0[k], I1[k], J0[k], J1[k]
        u = (np.arange(i0, i1) - off) / ss
        v = (np.arange(j0, j1) - off) / ss
        # unit ray directions M^-1 (u, v, 1)
        dx = Minv[0, 0] * u[None, :] + (Minv[0, 1] * v + Minv[0, 2])[:, None]
        dy = Minv[1, 0] * u[None, :] + (Minv[1, 1] * v + Minv[1, 2])[:, None]
        dz = Minv[2, 0] * u[None, :] + (Minv[2, 1] * v + Minv[2, 2])[:, None]
        nrm = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
        dx *= nrm
        dy *= nrm
        dz *= nrm
        t, w, r = T_all[k], W_all[k], r_all[k]
        wt = w @ t
        wp = w - wt * t
        ot = dx * t[0] + dy * t[1] + dz * t[2]
        A = np.maximum(1.0 - ot * ot, 1e-12)
        Bq = dx * wp[0] + dy * wp[1] + dz * wp[2]
        disc = Bq * Bq - A * (wp @ wp - r * r)
        hit = disc > 0
        if not hit.any():
            continue
        sq = np.sqrt(np.where(hit, disc, 0.0))
        s_lo = (-Bq - sq) / A
        s_hi = (-Bq + sq) / A
        # start plane (X - a).na >= 0 ; end plane (X - b).nb <= 0, with X = C + s * ray
        na, nb = na_all[k], nb_all[k]
        h1 = dx * na[0] + dy * na[1] + dz * na[2]
        h2 = dx * nb[0] + dy * nb[1] + dz * nb[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            c1 = -G1[k] / h1
            c2 = -G2[k] / h2
        s_lo = np.where(h1 > 0, np.maximum(s_lo, c1), s_lo)
        s_hi = np.where(h1 < 0, np.minimum(s_hi, c1), s_hi)
        s_hi = np.where(h2 > 0, np.minimum(s_hi, c2), s_hi)
        s_lo = np.where(h2 < 0, np.maximum(s_lo, c2), s_lo)
        chord = np.where(hit, np.maximum(s_hi - s_lo, 0.0), 0.0)
        out[j0:j1, i0:i1] += chord.astype(np.float32)
    return out


def _tree_chains(tree: VesselTree):
    """Render chains of the tree: every branch, minus the start of children inside their parent."""
    chains = []
    P, R = tree.points_lps_mm, tree.radius_mm
    for br in tree.branches:
        ids = _every_other(br.point_ids)
        if br.parent >= 0:
            par_ids = tree.branches[br.parent].point_ids
            pp, pr = P[par_ids], R[par_ids]
            k0 = 0
            for k in range(1, len(ids)):
                q = P[ids[k]]
                d = np.linalg.norm(pp - q, axis=1)
                j = int(np.argmin(d))
                if d[j] + R[ids[k]] <= pr[j]:
                    k0 = k
                else:
                    break
            ids = ids[k0:]
        if len(ids) >= 2:
            chains.append((P[ids], R[ids]))
    return chains


def _psf_sigma_px(rng, carm: CArm) -> float:
    focal_spot = rng.uniform(0.3, 0.6)  # mm
    blur_det_mm = focal_spot * (carm.sid_mm - carm.sod_mm) / carm.sod_mm
    det = rng.uniform(0.45, 0.7)  # px
    return float(np.sqrt(det**2 + (blur_det_mm / 2.355 / carm.pixel_mm) ** 2))


def _background_att(rng, shape, amount) -> np.ndarray:
    """Faint anatomy-like residual attenuation: multi-scale smooth texture plus soft bands."""
    H, W = shape
    att = np.zeros(shape, np.float32)
    for coarse, amp in ((4, 0.5), (10, 0.3), (24, 0.15)):
        att += _smooth_field(rng, shape, (coarse, coarse), amp)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32) / max(H, W)
    for _ in range(int(rng.integers(1, 4))):  # rib/diaphragm-like soft bands
        ang = rng.uniform(0, np.pi)
        off = rng.uniform(0.2, 0.8)
        curv = rng.uniform(-0.6, 0.6)
        s = xx * np.cos(ang) + yy * np.sin(ang)
        q = -xx * np.sin(ang) + yy * np.cos(ang)
        dist = s - off - curv * (q - 0.5) ** 2
        att += np.float32(rng.uniform(0.5, 1.2)) * np.exp(-0.5 * (dist / rng.uniform(0.02, 0.05)) ** 2)
    att -= att.min()
    return att * np.float32(amount / max(float(att.max()), 1e-6))


def _gain_field(shape) -> np.ndarray:
    H, W = shape
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    r2 = ((xx - (W - 1) / 2) ** 2 + (yy - (H - 1) / 2) ** 2) / (0.5 * max(H, W)) ** 2
    return (1.0 - 0.12 * r2).astype(np.float32)


def _expose(rng, att, *, b0, n0, psf_px, gain_field, gain):
    """Detector counts for an attenuation image: blur, Poisson quanta, correlation, gain."""
    signal = np.exp(-att) * gain_field * np.float32(gain)
    signal = ndimage.gaussian_filter(signal, psf_px, mode="nearest")
    quanta = rng.poisson(np.maximum(signal, 0) * n0).astype(np.float32)
    img = quanta * np.float32(b0 / n0)
    img = ndimage.gaussian_filter(img, 0.45, mode="nearest")
    img += rng.normal(0.0, 0.002 * b0, size=img.shape).astype(np.float32)
    return np.clip(img, 0, 65535).astype(np.float32)


def _wire_mask(fine_chord, ss, uv_list, shape):
    H, W = shape
    cover = _block_mean((fine_chord > 0).astype(np.float32), ss)
    mask = cover >= 0.34
    for uv in uv_list:
        if len(uv) < 2:
            continue
        # dense 2D samples of the projected centreline (<= 0.25 px apart)
        seg = np.linalg.norm(np.diff(uv, axis=0), axis=1)
        sub = np.maximum(np.ceil(seg / 0.25).astype(int), 1)
        t = np.concatenate([np.arange(k) / k for k in sub])
        i = np.repeat(np.arange(len(seg)), sub)
        dense = np.vstack([uv[i] + (uv[i + 1] - uv[i]) * t[:, None], uv[-1:]])
        ij = np.rint(dense).astype(int)
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < W) & (ij[:, 1] >= 0) & (ij[:, 1] < H)
        mask[ij[ok, 1], ij[ok, 0]] = True
    return mask
