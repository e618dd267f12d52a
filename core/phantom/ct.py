"""The simulator's CTA on the anatomy's grid.

Soft tissue about 40 HU, contrast 250-500 HU with a partial-volume edge, mild blur, correlated
noise; optional spine/ribs (700-1200 HU) and contrast-filled blobs (a heart chamber).
"""
from __future__ import annotations

import numpy as np
from guidewire3d.phantom.anatomy import VolumeSize, _every_other, _Grid
from guidewire3d.vesseltree import VesselTree
from scipy import ndimage

__all__: list[str] = []


# ======================================================================================
# lumen on the CT grid
# ======================================================================================
def _lumen_depth_grid(tree: VesselTree, grid: _Grid, *, pad_mm: float) -> np.ndarray:
    """Depth of every voxel centre (mm), exact within ``pad_mm`` of the wall, ``-pad_mm`` beyond."""
    nz, ny, nx = grid.shape_zyx
    sx, sy, sz = grid.spacing_xyz
    ox, oy, oz = grid.origin_xyz
    depth = np.full(grid.shape_zyx, -pad_mm, dtype=np.float32)
    xs = ox + sx * np.arange(nx)
    ys = oy + sy * np.arange(ny)
    zs = oz + sz * np.arange(nz)
    # coarser segments (every second edge along each branch) are exact enough for the CT
    for br in tree.branches:
        ids = _every_other(br.point_ids)
        P = tree.points_lps_mm[ids]
        R = tree.radius_mm[ids]
        for a, b, ra, rb in zip(P[:-1], P[1:], R[:-1], R[1:]):
            reach = max(ra, rb) + pad_mm
            blo = np.minimum(a, b) - reach
            bhi = np.maximum(a, b) + reach
            i0, i1 = np.searchsorted(xs, blo[0]), np.searchsorted(xs, bhi[0], side="right")
            j0, j1 = np.searchsorted(ys, blo[1]), np.searchsorted(ys, bhi[1], side="right")
            k0, k1 = np.searchsorted(zs, blo[2]), np.searchsorted(zs, bhi[2], side="right")
            if i0 >= i1 or j0 >= j1 or k0 >= k1:
                continue
            ab = b - a
            L2 = max(float(ab @ ab), 1e-12)
            dx = (xs[i0:i1] - a[0])[None, None, :]
            dy = (ys[j0:j1] - a[1])[None, :, None]
            dz = (zs[k0:k1] - a[2])[:, None, None]
            t = np.clip((dx * ab[0] + dy * ab[1] + dz * ab[2]) / L2, 0.0, 1.0)
            ex, ey, ez = dx - t * ab[0], dy - t * ab[1], dz - t * ab[2]
            d = (ra + (rb - ra) * t) - np.sqrt(ex * ex + ey * ey + ez * ez)
            sub = depth[k0:k1, j0:j1, i0:i1]
            np.maximum(sub, d.astype(np.float32), out=sub)
    return depth


# ======================================================================================
# CT synthesis
# ======================================================================================
def _interp_matrix(n_fine: int, n_coarse: int) -> np.ndarray:
    """``(n_fine, n_coarse)`` smooth (Gaussian-bump) interpolation weights, rows sum to 1."""
    x = np.linspace(0.0, n_coarse - 1.0, n_fine)[:, None]
    w = np.exp(-0.5 * ((x - np.arange(n_coarse)[None, :]) / 0.6) ** 2)
    return (w / w.sum(axis=1, keepdims=True)).astype(np.float32)


def _smooth_field(rng, shape, coarse, amplitude) -> np.ndarray:
    """A smooth random field of about ``amplitude`` std (separable interpolation of a coarse grid)."""
    c = rng.normal(size=tuple(coarse)).astype(np.float32)
    mats = [_interp_matrix(s, cs) for s, cs in zip(shape, coarse)]
    if len(shape) == 2:
        f = mats[0] @ c @ mats[1].T
    else:
        f = np.einsum("ai,ijk->ajk", mats[0], c)
        f = np.einsum("bj,ajk->abk", mats[1], f)
        f = np.einsum("ck,abk->abc", mats[2], f, optimize=True)
    f = f - f.mean()
    return (f * (amplitude / max(float(f.std()), 1e-6))).astype(np.float32)


def _synth_ct(rng, grid: _Grid, depth, stamps, volume: VolumeSize, tree):
    """HU volume: soft tissue, contrast lumen with partial volume, distractor stamps, blur, noise."""
    shape = grid.shape_zyx
    sp = np.asarray(grid.spacing_xyz)
    hu = _smooth_field(rng, shape, (6, 6, 6), rng.uniform(4.0, 9.0))
    hu += np.float32(40.0)
    if volume is VolumeSize.LARGE:  # a body outline with air outside
        nz, ny, nx = shape
        yy, xx = np.mgrid[0:ny, 0:nx].astype(np.float32)
        cx, cy = (nx - 1) / 2, (ny - 1) / 2 + rng.uniform(-10, 10)
        ax, ay = nx * rng.uniform(0.42, 0.48), ny * rng.uniform(0.32, 0.4)
        body = ((xx - cx) / ax) ** 2 + ((yy - cy) / ay) ** 2 <= 1.0
        hu[:, ~body] = np.float32(-1000.0)
    # contrast, fading slightly along the tree, with a partial-volume edge
    c0 = rng.uniform(250.0, 500.0)
    vox = float(np.cbrt(np.prod(sp)))
    zi, yi, xi = np.nonzero(depth > -0.5 * vox)
    if len(zi):
        frac = np.clip(0.5 + depth[zi, yi, xi] / vox, 0.0, 1.0)
        pts = grid.lo + np.column_stack([xi, yi, zi]) * sp
        _, nn = tree.kdtree.query(pts)
        s = tree.arclength_from_root_mm[nn]
        c = c0 * (1.0 - 0.15 * s / max(float(tree.arclength_from_root_mm.max()), 1.0))
        hu[zi, yi, xi] = hu[zi, yi, xi] * (1 - frac) + c * frac
    for sl, m, v in stamps:
        sub = hu[sl]
        sub[m] = np.broadcast_to(v, m.shape)[m]
    # mild blur (scanner PSF), then correlated noise
    sig_mm = rng.uniform(0.35, 0.6)
    hu = ndimage.gaussian_filter(hu, sigma=(sig_mm / sp[2], sig_mm / sp[1], sig_mm / sp[0]), mode="nearest")
    noise = rng.standard_normal(size=shape, dtype=np.float32)
    noise = ndimage.gaussian_filter(noise, sigma=0.7, mode="wrap")
    noise *= np.float32(rng.uniform(8.0, 20.0) / max(float(noise[::4, ::4, ::4].std()), 1e-6))
    hu += noise
    del noise
    np.clip(hu, -1024, 3071, out=hu)
    return hu


def _distractors(rng, grid: _Grid, depth, pad_mm):
    """Bone (spine or ribs) and contrast-filled blobs, kept >= 3 mm from the lumen.

    Each structure is tried at a few random places (scored on a coarse voxel subset) and the one
    that overlaps the vessels least is kept; voxels closer than 3 mm to the lumen are carved out.
    Returns ``(stamps, mask)``: ``stamps`` are ``(slices, submask, hu)`` to paint into the CT.
    """
    shape = grid.shape_zyx
    nz, ny, nx = shape
    sp = np.asarray(grid.spacing_xyz)
    axes = [np.float32(grid.origin_xyz[2]) + np.float32(sp[2]) * np.arange(nz, dtype=np.float32),
            np.float32(grid.origin_xyz[1]) + np.float32(sp[1]) * np.arange(ny, dtype=np.float32),
            np.float32(grid.origin_xyz[0]) + np.float32(sp[0]) * np.arange(nx, dtype=np.float32)]
    free = depth <= -min(3.0, pad_mm - 0.01)  # >= 3 mm outside the lumen
    lo, hi = grid.lo, grid.hi
    ext = hi - lo
    mask = np.zeros(shape, bool)

    def region(q, stride):
        """Slices (z, y, x) of the structure's bounding box and its voxel-centre coordinates."""
        blo, bhi = q["bbox"]
        sl = []
        for k, (a, l, h) in enumerate(zip(axes, blo[::-1], bhi[::-1])):
            i0, i1 = int(np.searchsorted(a, l)), int(np.searchsorted(a, h, side="right"))
            sl.append(slice(i0, max(i1, i0), stride))
        z, y, x = (a[s] for a, s in zip(axes, sl))
        return tuple(sl), (z[:, None, None], y[None, :, None], x[None, None, :])

    def spine_params():
        period = rng.uniform(24, 30)
        cx = rng.uniform(lo[0] + 0.2 * ext[0], hi[0] - 0.2 * ext[0])
        cy = rng.uniform(lo[1] + 0.55 * ext[1], hi[1] + 0.1 * ext[1])
        ax, ay = rng.uniform(14, 20), rng.uniform(11, 15)
        return dict(cx=cx, cy=cy, ax=ax, ay=ay, period=period, disc=rng.uniform(4, 6),
                    phase=rng.uniform(0, period), shell=rng.uniform(950, 1200), core=rng.uniform(700, 850),
                    bbox=(np.array([cx - ax, cy - ay, lo[2] - 5]), np.array([cx + ax, cy + ay, hi[2] + 5])))

    def spine(q, zz, yy, xx):
        rr = ((xx - q["cx"]) / q["ax"]) ** 2 + ((yy - q["cy"]) / q["ay"]) ** 2
        body = (np.mod(zz - q["phase"], q["period"]) > q["disc"]) & (rr <= 1.0)
        shell = rr > (1 - 2.0 / q["ax"]) ** 2
        return body, np.where(shell, np.float32(q["shell"]), np.float32(q["core"]))

    def ribs_params():
        n_ribs = int(rng.integers(2, 4))
        z0 = rng.uniform(lo[2] + 10, hi[2] - 10)
        gap = rng.uniform(18, 26)
        cx, cy = rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1])
        R = rng.uniform(0.45, 0.7) * ext[0]
        zc = [z0 + (j - n_ribs / 2) * gap for j in range(n_ribs)]
        tilt = rng.uniform(-0.3, 0.3)
        reach_z = 5.0 + abs(tilt) * (R + 5.0)
        return dict(cx=cx, cy=cy, R=R, zc=zc, rad=[rng.uniform(3.5, 5.0) for _ in range(n_ribs)], tilt=tilt,
                    value=rng.uniform(700, 1100),
                    bbox=(np.array([cx - R - 5, cy - R - 5, min(zc) - reach_z]),
                          np.array([cx + R + 5, cy + R + 5, max(zc) + reach_z])))

    def ribs(q, zz, yy, xx):
        rho = np.sqrt((xx - q["cx"]) ** 2 + (yy - q["cy"]) ** 2)
        m = False
        for zc, rad in zip(q["zc"], q["rad"]):
            m = m | ((rho - q["R"]) ** 2 + (zz - zc - q["tilt"] * (xx - q["cx"])) ** 2 <= rad * rad)
        return m, np.float32(q["value"])

    def blob_params():
        c = lo + rng.uniform(0.1, 0.9, 3) * ext
        rad = rng.uniform(9, 22, 3)
        return dict(c=c, rad=rad, value=rng.uniform(250, 450), bbox=(c - rad, c + rad))

    def blob(q, zz, yy, xx):
        c, r = q["c"], q["rad"]
        rr = ((xx - c[0]) / r[0]) ** 2 + ((yy - c[1]) / r[1]) ** 2 + ((zz - c[2]) / r[2]) ** 2
        return rr <= 1.0, np.float32(q["value"])

    kinds = [(spine_params, spine) if rng.random() < 0.6 else (ribs_params, ribs)]
    kinds += [(blob_params, blob)] * int(rng.integers(1, 3))
    stamps = []
    for make_params, fn in kinds:
        best, best_score = None, -np.inf
        for _ in range(8):
            q = make_params()
            sl, mesh = region(q, 3)
            fc = free[sl]
            if fc.size == 0:
                continue
            m, _ = fn(q, *mesh)
            m = np.broadcast_to(m, fc.shape)
            score = float((m & fc).sum() - 4 * (m & ~fc).sum())
            if m.any() and score > best_score:
                best, best_score = q, score
        if best is None:
            continue
        sl, mesh = region(best, 1)
        m, v = fn(best, *mesh)
        m = np.broadcast_to(m, free[sl].shape) & free[sl] & ~mask[sl]
        mask[sl] |= m
        stamps.append((sl, m, np.broadcast_to(v, m.shape)))
    return stamps, mask
