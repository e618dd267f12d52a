"""Smoothing of the wire: the banded P-spline both reconstructions fit, and polyline measures.

:func:`fit_pspline` is step 5 of the single-view reconstruction (``single_view``) and the weighted
smoothing of the two-view one (``triangulation``); :func:`smooth_wire` is step 5 itself (lambda
halved until the smoothed wire projects onto the 2D wire again).
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import BSpline
from scipy.linalg import solveh_banded

__all__ = ["fit_pspline", "smooth_wire", "arclength", "tangents", "curvature"]


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
    x0, x1 = float(x[0]), float(x[-1])
    nint = max(int(round((x1 - x0) / knot)), 1)
    t = np.r_[[x0] * 3, np.linspace(x0, x1, nint + 1), [x1] * 3]
    Bm = BSpline.design_matrix(np.clip(x, x0, x1), t, 3)
    nb = Bm.shape[1]
    M = len(x)
    # the data weights, summing to 1 (uniform 1/M without weights)
    wn = np.full(M, 1.0 / M) if weights is None else np.asarray(weights, float) / float(np.sum(weights))
    ab = np.zeros((4, nb))  # upper banded form: ab[3 + i - j, j] = A[i, j]
    rows4 = Bm.nnz == 4 * M and np.all(np.diff(Bm.indptr) == 4)
    if rows4:
        D, J = Bm.data.reshape(M, 4), Bm.indices.reshape(M, 4)
        rows4 = bool(np.all(np.diff(J, axis=1) == 1))
    if rows4:
        # B^T W B straight into the banded form (each row of B holds 4 consecutive basis functions)
        for a in range(4):
            for b in range(a, 4):
                ab[3 - (b - a)] += np.bincount(J[:, b], weights=wn * D[:, a] * D[:, b], minlength=nb)[:nb]
        BtY = np.column_stack([np.bincount(J.ravel(), weights=(wn[:, None] * D * Y[:, [d]]).ravel(), minlength=nb)[:nb]
                               for d in range(Y.shape[1])])
    else:
        Bw = Bm.multiply(wn[:, None]).tocsr()
        BtB = (Bm.T @ Bw).tocsr()
        for k in range(4):
            ab[3 - k, k:] = BtB.diagonal(k)
        BtY = np.asarray(Bw.T @ Y)
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
    coef = solveh_banded(ab, BtY)
    return BSpline(t, coef, 3, extrapolate=True), Bm


def smooth_wire(ctx, X, uv, *, lam: float, opt):
    """Smooth 3D points ``X`` (M, 3) keeping their projection near ``uv`` (M, 2): ``(points, lambda)``.

    The P-spline over the 2D arclength with ``lam``, halved (at most 8 times) until the projection
    (``ctx.project``) stays within ``opt.max_projection_px`` of ``uv`` (mean) and 2.5x that (max);
    the lambda used is returned with the points.
    """
    x = arclength(uv)
    if len(X) < 5 or x[-1] < 2 * opt.knot_px:
        return X.copy(), lam
    for _ in range(8):
        spl, Bm = fit_pspline(x, X, lam=lam, knot=opt.knot_px)
        Xs = Bm @ spl.c
        err = np.linalg.norm(ctx.project(Xs) - uv, axis=1)
        if err.mean() <= opt.max_projection_px and err.max() <= 2.5 * opt.max_projection_px:
            return Xs, lam
        lam *= 0.5
    return Xs, lam


def arclength(p) -> np.ndarray:
    """(N,) cumulative length along the polyline ``p`` (N, D), from 0 at its first point."""
    return np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]


def tangents(X) -> np.ndarray:
    """(N, 3) unit tangents of a polyline (central differences)."""
    if len(X) < 2:
        return np.tile([1.0, 0.0, 0.0], (len(X), 1))
    T = np.gradient(X, axis=0)
    return T / np.maximum(np.linalg.norm(T, axis=1, keepdims=True), 1e-12)


def curvature(X) -> np.ndarray:
    """(N,) curvature of a polyline ``X`` (N, 3) (central differences; 0 for fewer than 3 points)."""
    n = len(X)
    if n < 3:
        return np.zeros(n)
    d1 = np.gradient(X, axis=0)
    d2 = np.gradient(d1, axis=0)
    num = np.linalg.norm(np.cross(d1, d2), axis=1)
    den = np.maximum(np.linalg.norm(d1, axis=1) ** 3, 1e-12)
    return num / den
