"""The inputs of a registration, checked and sampled once: the 3D and 2D models.

* 3D (:func:`_model_from_input`, cached per ``VesselTree``): the centerline resampled three times,
  for LM (~4 px at the isocentre, with tangents, point sigmas, branches and the neighbour graph of
  the visibility support), for scoring (~1 px) and for the global search (one search cell); a bare
  (N, 3) point cloud is accepted without topology.
* 2D (:func:`_model_2d`): the roadmap centerline moved onto a local quadratic fit of its
  neighbours (removes noise across the vessel without shrinking curved vessels, which would bias
  the depth), sampled every ~2 px, with a point sigma that grows with the vessel radius and with
  how badly the neighbourhood fits one smooth curve (junctions, crossings), and a nearest-index map
  (``scipy.ndimage.distance_transform_edt(return_indices=True)`` of the rasterised samples) for
  O(1) closest-point lookups.

How the point sigmas enter the energy: :mod:`guidewire3d.registration.problem`.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
from guidewire3d.errors import InputError
from guidewire3d.geometry import CArm
from guidewire3d.vesseltree import VesselTree
from scipy import ndimage as ndi
from scipy import sparse as sp
from scipy.spatial import cKDTree

SIGMA_2D_PX = 0.5  # 2D centerline point uncertainty (px), before radius growth
SIGMA_3D_MM = 0.05  # 3D centerline point uncertainty (mm), before radius growth
FIT_RMS_WEIGHT = 4.0  # weight of the local-fit RMS (px^2) in the 2D point variance
RADIUS_GROWTH = 0.1  # sigma grows by this fraction of the local vessel radius (in quadrature)
SEARCH_CELL_PX = 8.0  # global search: nominal coarse grid for a 512-px image (scaled with the image); the
#   3D model's coarse samples are one cell apart


@dataclass(frozen=True, eq=False)
class _Model3D:
    points: np.ndarray  # (N, 3) LPS, LM samples (~1 mm)
    tangents: np.ndarray  # (N, 3) unit
    sigma_mm: np.ndarray  # (N,)
    step_mm: float
    dense: np.ndarray  # (Nd, 3) for scoring, finer
    coarse: np.ndarray  # (Nc, 3) for the global search
    centroid: np.ndarray  # (3,) centroid of the input tree points
    r_g: float  # radius of gyration (mm)
    bif_ids: np.ndarray  # bifurcation point ids in the input tree
    has_topology: bool
    branch: np.ndarray  # (N,) branch index of each LM sample (all 0 without topology)
    branch_parent: np.ndarray  # (B,) parent branch of each branch (-1 at the root; [-1] without topology)
    neighbours: object  # (N, N) sparse 0/1: samples within ~1.6 steps (support dilation)


_MODEL_CACHE: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _resample_tree(tree: VesselTree, step_mm: float):
    """Points every <= step_mm along every edge; tangents of their edge; radii interpolated."""
    p, r = tree.points_lps_mm, tree.radius_mm
    e = tree.edges
    a, b = p[e[:, 0]], p[e[:, 1]]
    L = np.linalg.norm(b - a, axis=1)
    n = np.maximum(np.ceil(L / step_mm).astype(np.int64), 1)
    edge_of = np.repeat(np.arange(len(e)), n)
    k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n) + 1  # 1..n per edge
    f = (k / n[edge_of])[:, None]
    pts = a[edge_of] + f * (b - a)[edge_of]
    tang = ((b - a) / np.maximum(L, 1e-12)[:, None])[edge_of]
    rad = r[e[edge_of, 0]] + f[:, 0] * (r[e[edge_of, 1]] - r[e[edge_of, 0]])
    branch = tree.point_branch[e[edge_of, 1]]
    # the root point, with the tangent of its first edge
    root = tree.root
    first = np.flatnonzero(e[:, 0] == root)
    t_root = tang[np.flatnonzero(edge_of == first[0])[0]] if len(first) else np.array([1.0, 0, 0])
    pts = np.vstack([p[root][None], pts])
    tang = np.vstack([t_root[None], tang])
    rad = np.r_[r[root], rad]
    branch = np.r_[tree.point_branch[root], branch]
    return pts, tang, rad, branch


def _pca_lines(points: np.ndarray, k: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Unit tangents of an unordered point cloud sampling curves (principal axis of the k-NN)."""
    n, dim = points.shape
    k = int(min(k, n))
    if k < 3:
        t = np.zeros_like(points)
        t[:, 0] = 1.0
        return t, points.copy()
    _, idx = cKDTree(points).query(points, k=k)
    nb = points[idx] - points[idx].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    _, vec = np.linalg.eigh(cov)
    return vec[:, :, -1], points.copy()


def _smooth_curve_2d(points: np.ndarray, k: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Denoise 2D centerline points with a local quadratic fit (unbiased on curved vessels).

    For each point, its k nearest neighbours are expressed in their principal frame ``(s, n)``
    and ``n = a + b s + c s^2`` is fitted by least squares; the point is moved onto the fitted
    curve at its own ``s`` and its tangent is the curve's. A plain local-line fit would pull
    points toward the centre of curvature, i.e. shrink the projected tree, which biases the
    (weakly observed) depth.

    Returns
    -------
    tangents, points : (M, 2) ndarray
    fit_rms : (M,) ndarray
        RMS residual (px) of the local fit: large at junctions, crossings and noisy stretches.
    """
    n = len(points)
    k = int(min(k, n))
    if k < 4:
        return (*_pca_lines(points), np.zeros(n))
    _, idx = cKDTree(points).query(points, k=k)
    nbp = points[idx]
    c = nbp.mean(axis=1)
    d = nbp - c[:, None, :]
    dx, dy = d[..., 0], d[..., 1]
    cov = np.empty((n, 2, 2))
    cov[:, 0, 0] = np.sum(dx * dx, axis=1)
    cov[:, 0, 1] = cov[:, 1, 0] = np.sum(dx * dy, axis=1)
    cov[:, 1, 1] = np.sum(dy * dy, axis=1)
    _, vec = np.linalg.eigh(cov)
    t = vec[:, :, -1]
    nn = np.column_stack([-t[:, 1], t[:, 0]])
    sk = dx * t[:, 0:1] + dy * t[:, 1:2]
    nk = dx * nn[:, 0:1] + dy * nn[:, 1:2]
    V = np.stack([np.ones_like(sk), sk, sk * sk], axis=2)  # (n, k, 3)
    A = V.transpose(0, 2, 1) @ V + 1e-6 * np.eye(3)
    rhs = V.transpose(0, 2, 1) @ nk[..., None]
    coef = np.linalg.solve(A, rhs)[..., 0]
    s0 = np.sum((points - c) * t, axis=1)
    n0 = coef[:, 0] + coef[:, 1] * s0 + coef[:, 2] * s0 * s0
    fit_rms = np.sqrt(np.mean(((V @ coef[..., None])[..., 0] - nk) ** 2, axis=1))
    smooth = c + s0[:, None] * t + n0[:, None] * nn
    tang = t + (coef[:, 1] + 2.0 * coef[:, 2] * s0)[:, None] * nn
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    # where the neighbourhood is not one curve (bifurcations, crossings), keep the raw point
    bad = fit_rms > 1.0
    smooth[bad] = points[bad]
    tang[bad] = t[bad]
    return tang, smooth, fit_rms


def _grid_subsample(points: np.ndarray, step: float) -> np.ndarray:
    """Indices of one point per ``step``-sized grid cell (first occurrence, original order)."""
    keys = np.floor(points / step).astype(np.int64)
    keys -= keys.min(axis=0)
    lin = keys[:, 0]
    for d in range(1, keys.shape[1]):  # one integer key per cell (injective)
        lin = lin * (int(keys[:, d].max()) + 1) + keys[:, d]
    _, first = np.unique(lin, return_index=True)
    return np.sort(first)


def _model_from_input(tree, carm: CArm) -> _Model3D:
    px_iso = carm.pixel_at_iso_mm
    step = float(np.clip(4.0 * px_iso, 0.5, 1.5))  # LM samples: ~4 px at the isocentre
    dense_step = float(np.clip(px_iso, 0.05, 0.5))
    coarse_step = float(max(_search_cell_px(carm) * px_iso, 0.5))
    if isinstance(tree, VesselTree):
        key = (round(step, 6), round(dense_step, 6), round(coarse_step, 6))
        cached = _MODEL_CACHE.get(tree)
        if cached is not None and key in cached:
            return cached[key]
        pts, tang, rad, branch = _resample_tree(tree, step)
        dense = _resample_tree(tree, dense_step)[0]
        coarse = _resample_tree(tree, coarse_step)[0]
        src = tree.points_lps_mm
        bif = tree.bifurcations
        branch_parent = np.array([b.parent for b in tree.branches], dtype=np.int64)
        has_topology = True
    else:
        src = np.asarray(tree, dtype=float)
        if src.ndim != 2 or src.shape[1] != 3 or len(src) < 2:
            raise InputError(f"tree must be a VesselTree or (N>=2, 3) points in LPS mm, got shape {src.shape}")
        if not np.all(np.isfinite(src)):
            raise InputError("tree points_lps_mm contain non-finite values")
        keep = _grid_subsample(src, step * 0.7)
        pts = src[keep]
        tang = _pca_lines(src)[0][keep]
        rad = np.ones(len(pts))
        dense = src
        coarse = src[_grid_subsample(src, coarse_step)]
        bif = np.zeros(0, dtype=np.int64)
        branch = np.zeros(len(pts), dtype=np.int64)
        branch_parent = np.array([-1], dtype=np.int64)
        has_topology = False
    centroid = src.mean(axis=0)
    r_g = float(np.sqrt(np.mean(np.sum((pts - pts.mean(axis=0)) ** 2, axis=1))))
    r_g = max(r_g, 5.0)
    sigma = np.sqrt(SIGMA_3D_MM**2 + (RADIUS_GROWTH * rad) ** 2)
    neighbours = cKDTree(pts).sparse_distance_matrix(cKDTree(pts), 1.6 * step, output_type="coo_matrix").tocsr()
    neighbours.data[:] = 1.0
    neighbours = neighbours + sp.identity(len(pts), format="csr")
    model = _Model3D(
        points=pts, tangents=tang, sigma_mm=sigma, step_mm=step, dense=dense, coarse=coarse,
        centroid=centroid, r_g=r_g, bif_ids=bif, has_topology=has_topology, branch=branch,
        branch_parent=branch_parent, neighbours=neighbours,
    )
    for a in (pts, tang, sigma, dense, coarse, centroid, branch, branch_parent):
        a.setflags(write=False)
    if isinstance(tree, VesselTree):
        _MODEL_CACHE.setdefault(tree, {})[key] = model
    return model


def _search_cell_px(carm: CArm) -> float:
    """The global search's grid cell (px): ``SEARCH_CELL_PX`` for a 512-px image, scaled with ``carm``'s."""
    return float(max(2.0, round(SEARCH_CELL_PX * max(carm.shape) / 512.0)))


@dataclass(frozen=True, eq=False)
class _Model2D:
    uv: np.ndarray  # (M, 2) LM samples (px)
    tangents: np.ndarray  # (M, 2) unit
    sigma_px: np.ndarray  # (M,)
    all_uv: np.ndarray  # (Ma, 2) every input point (quality, score)
    cell: float  # nearest-index raster cell (px)
    origin: np.ndarray  # (2,) uv of raster cell (0, 0)
    nn_map: np.ndarray  # (Hr, Wr) int: index into uv of the nearest sample


def _check_2d(centerline_uv_px, name="centerline_uv_px") -> np.ndarray:
    q = np.asarray(centerline_uv_px, dtype=float)
    if q.ndim != 2 or q.shape[1] != 2:
        raise InputError(f"{name} must be (M, 2) pixel (u, v) points, got shape {q.shape}")
    if not np.all(np.isfinite(q)):
        raise InputError(f"{name} contains non-finite values")
    return q


def _model_2d(q: np.ndarray, radius_px, carm: CArm) -> _Model2D:
    if radius_px is None:
        rad = np.zeros(len(q))
    else:
        rad = np.asarray(radius_px, dtype=float).reshape(-1)
        if rad.shape != (len(q),) or not np.all(np.isfinite(rad)):
            raise InputError(f"centerline_radius_px must be finite with one value per point ({len(q)}), got {rad.shape}")
    keep = _grid_subsample(q, 2.0)
    tang_all, smooth, fit_rms = _smooth_curve_2d(q)
    uv, tang = smooth[keep], tang_all[keep]
    # point uncertainty: extraction noise, growing with the vessel radius and with how badly
    # the neighbourhood fits one smooth curve (junctions, crossings, spurs)
    sigma = np.sqrt(SIGMA_2D_PX**2 + (RADIUS_GROWTH * rad[keep]) ** 2 + FIT_RMS_WEIGHT * fit_rms[keep] ** 2)
    # nearest-index raster (<= ~256 cells on the long side)
    cell = float(max(1.0, np.ceil(max(carm.shape) / 256.0)))
    lo = np.minimum(uv.min(axis=0), [-0.5, -0.5]) - cell
    hi = np.maximum(uv.max(axis=0), [carm.cols - 0.5, carm.rows - 0.5]) + cell
    origin = lo
    shape = (int(np.ceil((hi[1] - lo[1]) / cell)) + 1, int(np.ceil((hi[0] - lo[0]) / cell)) + 1)
    occ_idx = -np.ones(shape, dtype=np.int64)
    ij = np.rint((uv - origin) / cell).astype(np.int64)
    occ_idx[ij[:, 1], ij[:, 0]] = np.arange(len(uv))
    _, (ii, jj) = ndi.distance_transform_edt(occ_idx < 0, return_indices=True)
    nn_map = occ_idx[ii, jj]
    for a in (uv, tang, sigma, q, nn_map):
        a.setflags(write=False)
    return _Model2D(uv=uv, tangents=tang, sigma_px=sigma, all_uv=q, cell=cell, origin=origin, nn_map=nn_map)

