"""Smoothing of the wire: the banded P-spline both reconstructions fit, and polyline measures.

:func:`fit_pspline` is step 5 of the single-view reconstruction (``single_view``) and the weighted
smoothing of the two-view one (``triangulation``); :func:`smooth_wire` is step 5 itself (lambda
halved until the smoothed wire projects onto the 2D wire again).
"""
from __future__ import annotations

import numpy as np
from guidewire3d import kernels
from scipy.interpolate import BSpline
from scipy.linalg import solveh_banded
from scipy.sparse import csr_array

__all__ = ["fit_pspline", "pspline_system", "smooth_wire", "arclength", "tangents", "curvature"]


def _penalised_banded(ab_data: np.ndarray, lam: float) -> np.ndarray:
    """The P-spline's banded matrix: ``B^T W B`` (upper banded form, (4, nb)) plus ``lam / (nb - 2)``
    times ``D^T D`` of the second-difference operator (and 1e-12 on the diagonal)."""
    ab = ab_data.copy()
    nb = ab.shape[1]
    w = lam / max(nb - 2, 1)
    # D^T D of the second-difference operator, by diagonals
    p0 = np.full(nb, 6.0)
    p0[[0, -1]] = 1.0
    if nb > 2:
        p0[[1, -2]] = 5.0
    p1 = np.full(nb - 1, -4.0)
    p1[[0, -1]] = -2.0
    if nb >= 3:
        ab[3] += w * p0
        ab[2, 1:] += w * p1
        ab[1, 2:] += w * 1.0
    ab[3] += 1e-12
    return ab


def _knots(x, knot: float) -> np.ndarray:
    """The clamped cubic knot vector of the P-spline over ``x``: ``nint = round(range / knot)``
    (at least 1) equal intervals, the end knots repeated 3 more times."""
    x0, x1 = float(x[0]), float(x[-1])
    nint = max(round((x1 - x0) / knot), 1)
    t = np.empty(nint + 7)
    t[:3], t[3:-3], t[-3:] = x0, np.linspace(x0, x1, nint + 1), x1
    return t


def pspline_system(x, Y, *, knot: float, weights=None):
    """The lambda-free part of :func:`fit_pspline`: knots, the design matrix's rows
    (values (M, 4) and first column (M,)), ``B^T W B`` in upper banded form (4, nb) and ``B^T W Y``
    (nb, D), from ``kernels.pspline_system``."""
    t = _knots(x, knot)
    M = len(x)
    # the data weights, summing to 1 (uniform 1/M without weights)
    wn = np.full(M, 1.0 / M) if weights is None else np.asarray(weights, float) / float(np.sum(weights))
    # B^T W B straight into the banded form (each row of B holds 4 consecutive basis functions)
    D, first, ab, BtY = kernels.pspline_system(np.clip(x, t[0], t[-1]), t, wn, Y)
    return t, D, first, ab, BtY


def fit_pspline(x, Y, *, lam: float, knot: float, weights=None):
    """Penalised cubic B-spline fit of ``Y`` over ``x``: ``(BSpline, design matrix)``.

    Objective: ``mean_m |Y_m - f(x_m)|^2 + lam * mean_k |second difference of coefficients_k|^2``
    (Eilers & Marx P-spline), solved as a banded (bandwidth 3) symmetric system.

    Parameters
    ----------
    x : (M,) ndarray of float, increasing
        Where the values are (the arclength along the 2D wire, px, in both reconstructions).
    Y : (M, D) ndarray of float
    lam : float
        Smoothness weight (the paper's lambda).
    knot : float
        Knot spacing, in the units of ``x``.
    weights : (M,) ndarray of float, optional
        Data weights: the mean over m is the weighted one.

    Returns
    -------
    spline : scipy.interpolate.BSpline
    design : (M, n_basis) sparse matrix
        The basis at ``x``: ``design @ spline.c`` are the fitted values at ``x``.
    """
    t, D, first, ab, BtY = pspline_system(x, Y, knot=knot, weights=weights)
    coef = solveh_banded(_penalised_banded(ab, lam), BtY)
    M, nb = len(x), ab.shape[1]
    design = csr_array((D.ravel(), (first[:, None] + np.arange(4)).ravel(), np.arange(0, 4 * M + 1, 4)),
                       shape=(M, nb))
    return BSpline(t, coef, 3, extrapolate=True), design


def smooth_wire(ctx, X, uv, *, lam: float, opt):
    """Smooth 3D points ``X`` (M, 3) keeping their projection near ``uv`` (M, 2): ``(points, lambda)``.

    The P-spline over the 2D arclength with ``lam`` (:func:`fit_pspline`), halved (at most 8 times)
    until the projection (``ctx.project``) stays within ``opt.max_projection_px`` of ``uv`` (mean)
    and 2.5x that (max); the lambda used is returned with the points. The design matrix and the
    data part of the normal equations do not depend on lambda: they are built once; each fit is
    one compiled call (``kernels.penalised_fit``: the system of ``fit_pspline``, solved by a
    banded Cholesky factorisation instead of its LAPACK call, the same to rounding).
    """
    x = arclength(uv)
    if len(X) < 5 or x[-1] < 2 * opt.knot_px:
        return X.copy(), lam
    _, D, first, ab, BtY = pspline_system(x, X, knot=opt.knot_px)
    for _ in range(8):
        Xs, mean_px, max_px = kernels.penalised_fit(D, first, ab, BtY, lam=lam, uv_px=uv, Rc=ctx.Rc, tc=ctx.tc,
                                                    focal_px=ctx.focal, principal_point_px=ctx.carm.principal_point_px)
        if mean_px <= opt.max_projection_px and max_px <= 2.5 * opt.max_projection_px:
            return Xs, lam
        lam *= 0.5
    return Xs, lam


def arclength(p) -> np.ndarray:
    """(N,) cumulative length along the polyline ``p`` (N, D), from 0 at its first point."""
    out = np.zeros(max(len(p), 1))
    if len(p) > 1:
        np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1), out=out[1:])
    return out


def tangents(X) -> np.ndarray:
    """(N, 3) unit tangents of a polyline (central differences)."""
    if len(X) < 2:
        return np.tile([1.0, 0.0, 0.0], (len(X), 1))
    return kernels.polyline_measures(X)[0]


def curvature(X) -> np.ndarray:
    """(N,) curvature of a polyline ``X`` (N, 3) (central differences; 0 for fewer than 3 points)."""
    if len(X) < 3:
        return np.zeros(len(X))
    return kernels.polyline_measures(X)[1]
