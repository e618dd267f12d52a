"""The two-view triangulation's compiled kernels (guidewire3d.kernels) against the numpy / SciPy code
they replaced in guidewire3d.reconstruction.triangulation (candidates, DLT, Viterbi, nearest point):
same numbers to rounding and the same choices, on random inputs (ties and missing candidates included)."""
from __future__ import annotations

import numpy as np
import pytest
from guidewire3d import kernels
from guidewire3d.geometry import Pose
from guidewire3d.reconstruction.uncertainty import pose_jacobian
from scipy.spatial import cKDTree

_INF = 1e18


# --- the former numpy code ---------------------------------------------------------------------------
def _candidates_numpy(F, a, b, touch_px):
    ah = np.column_stack([a, np.ones(len(a))])
    lines = ah @ F.T
    lines /= np.maximum(np.linalg.norm(lines[:, :2], axis=1, keepdims=True), 1e-12)
    d = lines[:, :2] @ b.T + lines[:, 2:3]
    s = d >= 0
    cross = s[:, :-1] != s[:, 1:]
    ia, jb = np.nonzero(cross)
    d0, d1 = d[ia, jb], d[ia, jb + 1]
    den = d0 - d1
    frac = d0 / np.where(np.abs(den) > 1e-12, den, 1.0)
    j = jb + np.clip(frac, 0.0, 1.0)
    ad = np.abs(d)
    if ad.shape[1] >= 3:
        mid = (ad[:, 1:-1] <= ad[:, :-2]) & (ad[:, 1:-1] <= ad[:, 2:]) & (ad[:, 1:-1] < touch_px)
        mid &= ~cross[:, :-1] & ~cross[:, 1:]
        ti, tj = np.nonzero(mid)
        ia = np.r_[ia, ti]
        j = np.r_[j, tj + 1.0]
    tb = np.gradient(b, axis=0)
    tb /= np.maximum(np.linalg.norm(tb, axis=1, keepdims=True), 1e-12)
    jr = np.clip(np.rint(j).astype(int), 0, len(b) - 1)
    sin_ang = np.abs(np.sum(tb[jr] * lines[ia, :2], axis=1))
    return ia, j, sin_ang


def _triangulate_numpy(a, b, P_a, P_b):
    A = np.stack([a[:, :1] * P_a[2] - P_a[0], a[:, 1:] * P_a[2] - P_a[1],
                  b[:, :1] * P_b[2] - P_b[0], b[:, 1:] * P_b[2] - P_b[1]], axis=1)
    A = A / np.linalg.norm(A[:, :, :3], axis=2, keepdims=True)
    M, r = A[:, :, :3], -A[:, :, 3]
    MtM = np.einsum("nki,nkj->nij", M, M)
    Mtr = np.einsum("nki,nk->ni", M, r)
    return np.linalg.solve(MtM, Mtr[..., None])[..., 0]


def _viterbi_numpy(n, ia, jb, X, unary, step_mm, direction, K, G, dense_px, tol, sigma_step, back_px, skip_cost,
                   px_other_mm, spread):
    order = np.lexsort((unary, ia))
    ia_s = ia[order]
    starts = np.searchsorted(ia_s, np.arange(n + 1))
    rank = np.arange(len(ia_s)) - starts[ia_s]
    ok = rank < K
    idx = -np.ones((n, K), int)
    idx[ia_s[ok], rank[ok]] = order[ok]
    has = idx >= 0
    Xp = np.where(has[..., None], X[np.maximum(idx, 0)], np.nan)
    jp = np.where(has, jb[np.maximum(idx, 0)], np.nan)
    U = np.where(has, unary[np.maximum(idx, 0)], _INF)
    Tin = np.full((n, G, K, K), _INF)
    for g in range(1, min(G, n - 1) + 1):
        dX = np.linalg.norm(Xp[:-g, :, None, :] - Xp[g:, None, :, :], axis=3)
        dj = (jp[g:, None, :] - jp[:-g, :, None]) * direction * dense_px
        m_mm, o_mm = g * step_mm, np.abs(dj) * px_other_mm
        over = np.maximum(dX - np.sqrt(m_mm**2 + o_mm**2) * spread - tol, 0.0)
        jump = np.maximum(o_mm - dX - tol, 0.0)
        with np.errstate(invalid="ignore"):
            pen = np.where(dj < -back_px, _INF, (over**2 + jump**2) / sigma_step**2)
        Tin[g:, g - 1] = np.where(np.isfinite(pen), pen + (g - 1) * skip_cost, _INF)
    cp = np.full((n + G, K), _INF)
    skip = float(skip_cost)
    cp[G] = U[0]
    for i in range(1, n):
        tot = cp[i:i + G][::-1, :, None] + Tin[i]
        cp[i + G] = np.minimum(tot.min(axis=(0, 1)), i * skip) + U[i]
    costs = cp[G:]
    end = costs + (n - 1 - np.arange(n))[:, None] * skip
    i, k = np.unravel_index(int(end.argmin()), end.shape)
    best = float(end[i, k])
    chosen = -np.ones(n, int)
    while True:
        chosen[i] = idx[i, k]
        if i == 0:
            break
        tot = cp[i:i + G][::-1] + Tin[i][:, :, k]
        m = float(tot.min())
        if i * skip <= m:
            break
        gi, k = np.unravel_index(int(tot.argmin()), tot.shape)
        i = int(i - 1 - gi)
    return chosen, best


# --- helpers --------------------------------------------------------------------------------------
def _projections(rng):
    """Two pinhole views ~90 deg apart looking at the origin (LPS mm -> px)."""
    Ps = []
    for ang in (rng.uniform(-0.3, 0.3), np.pi / 2 + rng.uniform(-0.3, 0.3)):
        c, s = np.cos(ang), np.sin(ang)
        R = np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])
        K = np.array([[1200.0, 0.0, 256.0], [0.0, 1200.0, 256.0], [0.0, 0.0, 1.0]])
        Ps.append(K @ np.column_stack([R, [0.0, 0.0, 700.0]]))
    return Ps


def _fundamental(P_a, P_b):
    _, _, vt = np.linalg.svd(P_a)
    e = P_b @ vt[-1]
    ex = np.array([[0, -e[2], e[1]], [e[2], 0, -e[0]], [-e[1], e[0], 0]])
    F = ex @ P_b @ np.linalg.pinv(P_a)
    return F / np.linalg.norm(F)


def _project(P, X):
    x = np.column_stack([X, np.ones(len(X))]) @ P.T
    return x[:, :2] / x[:, 2:]


def _wire3d(rng, n=200):
    """A smooth random 3D curve (mm) around the origin."""
    t = np.linspace(0.0, 1.0, n)
    X = np.zeros((n, 3))
    for d in range(3):
        for f in range(1, 4):
            X[:, d] += rng.normal(0.0, 25.0 / f) * np.sin(np.pi * f * t + rng.uniform(0, np.pi))
    return X


# --- tests ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(6))
def test_epipolar_candidates_are_the_numpy_ones(seed):
    rng = np.random.default_rng(seed)
    P_a, P_b = _projections(rng)
    F = _fundamental(P_a, P_b)
    X = _wire3d(rng)
    a = _project(P_a, X)[:: int(rng.integers(2, 5))]
    b = _project(P_b, X) + rng.normal(0.0, 0.3, (len(X), 2))
    touch = float(rng.uniform(0.5, 3.0))  # large: touches are many
    ref = _candidates_numpy(F, a, b, touch)
    got = kernels.epipolar_candidates(F, a, b, touch_px=touch)
    assert len(ref[0]) > len(a) // 2
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_allclose(got[1], ref[1], rtol=0, atol=1e-9)
    np.testing.assert_allclose(got[2], ref[2], rtol=0, atol=1e-12)
    # ground truth: each master sample's true partner (the same 3D point) is among its candidates
    ia, j = got[0], got[1]
    step = len(X) // len(a) if len(a) else 1
    hits = [np.any(np.abs(j[ia == i] - min(i * (len(X) - 1) / max(len(a) - 1, 1), len(X) - 1)) < 3 * step)
            for i in range(len(a))]
    assert np.mean(hits) > 0.8


def test_epipolar_candidates_touch_and_degenerate():
    """A wire that touches a line without crossing it (a touch at its apex), and a 2-sample wire."""
    F = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # line of (u, v): y = v (horizontal)
    a = np.array([[0.0, 10.0], [0.0, 20.0]])
    u = np.arange(-10.0, 11.0)
    b = np.column_stack([u, 10.3 + 0.01 * u**2])  # apex 0.3 px from y = 10
    for bb in (b, b[:2], b[::-1]):
        ref = _candidates_numpy(F, a, bb, 0.7)
        got = kernels.epipolar_candidates(F, a, bb, touch_px=0.7)
        for r, g in zip(ref, got):
            np.testing.assert_allclose(g, r, rtol=0, atol=1e-12)
    got = kernels.epipolar_candidates(F, a, b, touch_px=0.7)
    assert list(got[0]) == [0] and got[1][0] == 10.0 and got[2][0] == pytest.approx(0.0)  # along the line


@pytest.mark.parametrize("seed", range(4))
def test_triangulate_dlt_is_the_numpy_solve(seed):
    rng = np.random.default_rng(seed)
    P_a, P_b = _projections(rng)
    X = rng.normal(0.0, 40.0, (300, 3))
    a = _project(P_a, X) + rng.normal(0.0, 0.5, (300, 2))
    b = _project(P_b, X) + rng.normal(0.0, 0.5, (300, 2))
    ref = _triangulate_numpy(a, b, P_a, P_b)
    got = kernels.triangulate_dlt(a, b, P_a, P_b)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)
    # ground truth: exact pixels give the points back
    np.testing.assert_allclose(kernels.triangulate_dlt(_project(P_a, X), _project(P_b, X), P_a, P_b), X, atol=1e-8)


def _viterbi_case(rng, n, K, G):
    """Random candidates along a true chain (one candidate per sample near it, the others off it),
    samples without candidates, and ties of the unary cost."""
    X_true = np.cumsum(rng.normal(0.0, 0.6, (n, 3)), axis=0)
    j_true = np.cumsum(rng.uniform(1.0, 4.0, n))
    ia, jb, X, unary, true = [], [], [], [], []
    for i in range(n):
        if rng.random() < 0.1:
            continue  # no candidate
        for c in range(int(rng.integers(1, K + 3))):
            ia.append(i)
            true.append(c == 0)
            if c == 0:
                jb.append(j_true[i] + rng.normal(0, 0.2))
                X.append(X_true[i] + rng.normal(0, 0.05, 3))
            else:
                jb.append(rng.uniform(0, j_true[-1]))
                X.append(X_true[i] + rng.normal(0, 4.0, 3))
            unary.append(float(rng.choice([0.0, 0.5, 1.0, rng.uniform(0, 3)])))  # ties
    perm = rng.permutation(len(ia))  # the candidates are not sorted by sample
    return (np.asarray(ia)[perm], np.asarray(jb)[perm], np.asarray(X)[perm], np.asarray(unary)[perm],
            np.asarray(true, bool)[perm])


@pytest.mark.parametrize("seed", range(12))
def test_two_view_viterbi_is_the_numpy_recursion(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 60))
    K, G = int(rng.integers(1, 7)), int(rng.integers(1, 6))
    ia, jb, X, unary, _ = _viterbi_case(rng, n, K, G)
    kw = {"step_mm": 0.6, "dense_px": 1.0, "tol": 0.2, "sigma_step": 0.3, "back_px": 1.0,
          "skip_cost": float(rng.choice([2.0, 8.0])), "px_other_mm": 0.25, "spread": 1.2}
    for direction in (1, -1):
        ref = _viterbi_numpy(n, ia, jb, X, unary, kw["step_mm"], direction, K, G, kw["dense_px"], kw["tol"],
                             kw["sigma_step"], kw["back_px"], kw["skip_cost"], kw["px_other_mm"], kw["spread"])
        got = kernels.two_view_viterbi(n, ia, jb, X, unary, step_mm=kw["step_mm"], direction=direction,
                                       max_candidates=K, max_gap=G, dense_px=kw["dense_px"],
                                       step_tolerance_mm=kw["tol"], sigma_step_mm=kw["sigma_step"],
                                       back_px=kw["back_px"], skip_cost=kw["skip_cost"],
                                       px_other_mm=kw["px_other_mm"], spread=kw["spread"])
        np.testing.assert_array_equal(got[0], ref[0])
        assert got[1] == pytest.approx(ref[1], rel=1e-12, abs=1e-9)


def test_two_view_viterbi_follows_the_true_chain():
    """Ground truth: with one candidate per sample on the true chain (the others scattered), the
    forward walk picks the true candidate almost everywhere."""
    rng = np.random.default_rng(7)
    n = 80
    ia, jb, X, unary, true = _viterbi_case(rng, n, 4, 4)
    unary = np.zeros_like(unary)  # no prior: the pairwise term alone must find the chain
    chosen, _ = kernels.two_view_viterbi(n, ia, jb, X, unary, step_mm=0.6, direction=1, max_candidates=8, max_gap=4,
                                         dense_px=1.0, step_tolerance_mm=0.2, sigma_step_mm=0.3, back_px=1.0,
                                         skip_cost=8.0, px_other_mm=0.25, spread=1.2)
    picked = chosen[chosen >= 0]
    assert len(picked) > 0.7 * n
    assert np.mean(true[picked]) > 0.95


@pytest.mark.parametrize("dim", [2, 3])
def test_nearest_grid_is_the_kdtree(dim):
    rng = np.random.default_rng(dim)
    P = np.cumsum(rng.normal(0.0, 0.5, (3000, dim)), axis=0)  # a random walk: clustered, like a polyline
    grid = kernels.NearestGrid(P, 4.0)
    Q = np.vstack([P[rng.integers(0, len(P), 500)] + rng.normal(0.0, 2.0, (500, dim)),  # near
                   rng.uniform(P.min(0) - 50.0, P.max(0) + 50.0, (100, dim))])  # anywhere, outside the grid too
    d, i = grid.query(Q)
    d0, i0 = cKDTree(P).query(Q)
    np.testing.assert_array_equal(i, i0)
    np.testing.assert_array_equal(d, d0)


def test_nearest_grid_ties_and_errors():
    P = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [9.0, 9.0, 9.0]])
    d, i = kernels.NearestGrid(P, 0.5).query([[1.0, 0.1, 0.0], [0.5, 0.0, 0.0]])
    assert list(i) == [1, 0] and d[0] == pytest.approx(0.1) and d[1] == 0.5  # exact ties: the lower index
    with pytest.raises(ValueError):
        kernels.NearestGrid(np.zeros((0, 3)), 1.0)


def _resample_numpy(uv, step):
    seg = np.linalg.norm(np.diff(uv, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    n = max(int(np.ceil(s[-1] / step)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    return np.column_stack([np.interp(t, s, uv[:, d]) for d in range(uv.shape[1])]), t


@pytest.mark.parametrize("seed", range(4))
def test_resample_polyline_is_numpy_interp(seed):
    rng = np.random.default_rng(seed)
    for _ in range(30):
        uv = np.cumsum(rng.normal(0.0, 2.0, (int(rng.integers(2, 300)), int(rng.integers(2, 4)))), axis=0)
        if len(uv) > 8:
            uv[4:7] = uv[4]  # repeated points: zero-length segments
        for step in (0.25, 1.0, 3.0, 1e4):
            ref, t_ref = _resample_numpy(uv, step)
            got, t = kernels.resample_polyline(uv, step)
            np.testing.assert_array_equal(t, t_ref)
            np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    # ground truth: a straight line resampled is evenly spaced on it
    got, t = kernels.resample_polyline(np.array([[0.0, 0.0], [10.0, 0.0]]), 3.0)
    np.testing.assert_allclose(got[:, 0], np.linspace(0.0, 10.0, 5))
    np.testing.assert_allclose(t, got[:, 0])


def _covariance_numpy(X, tan3, cams, s2d, pose, C):
    H = np.zeros((len(X), 3, 3))
    for Rc, tc, f in cams:
        xc = X @ Rc.T + tc
        z = xc[:, 2]
        J = np.zeros((len(X), 2, 3))
        J[:, 0, 0] = J[:, 1, 1] = f / z
        J[:, 0, 2] = -f * xc[:, 0] / z**2
        J[:, 1, 2] = -f * xc[:, 1] / z**2
        J = J @ Rc
        t2 = np.einsum("nij,nj->ni", J, tan3)
        t2 /= np.maximum(np.linalg.norm(t2, axis=1, keepdims=True), 1e-12)
        nrm = np.column_stack([-t2[:, 1], t2[:, 0]])
        jn = np.einsum("ni,nij->nj", nrm, J)
        H += jn[:, :, None] * jn[:, None, :] / s2d**2
    Pperp = np.eye(3)[None] - tan3[:, :, None] * tan3[:, None, :]
    big = 1e6 * tan3[:, :, None] * tan3[:, None, :]
    cov = Pperp @ np.linalg.inv(H + big) @ Pperp
    if C is not None:
        G = pose_jacobian(pose, X)
        cov = cov + Pperp @ (G @ C @ np.transpose(G, (0, 2, 1))) @ Pperp
    return cov, np.sqrt(np.clip(np.trace(cov, axis1=1, axis2=2), 0.0, None))


@pytest.mark.parametrize("seed", range(4))
def test_two_view_covariance_is_the_numpy_formula(seed):
    rng = np.random.default_rng(seed)
    X = _wire3d(rng, 120)
    tan3 = np.gradient(X, axis=0)
    tan3 /= np.linalg.norm(tan3, axis=1, keepdims=True)
    cams = []
    for ang in (0.2, 1.6):
        c, s = np.cos(ang), np.sin(ang)
        cams.append((np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]), np.array([1.0, -2.0, 700.0]), 1100.0))
    pose = Pose.from_rotvec_about([0.05, -0.08, 0.1], [10.0, -20.0, 30.0])
    L = rng.normal(0.0, 0.1, (6, 6))
    for C in (None, L @ L.T):
        ref_cov, ref_unc = _covariance_numpy(X, tan3, cams, 0.5, pose, C)
        G = None if C is None else pose_jacobian(pose, X)
        cov, unc = kernels.two_view_covariance(X, tan3, cams, sigma_2d_px=0.5, pose_jacobians=G,
                                               registration_covariance=C)
        # the inverse of H + 1e6 t t^T loses digits (condition up to ~1e8 where a plane sees the wire
        # along its epipolar line): the same to 1e-6 relative
        np.testing.assert_allclose(cov, ref_cov, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(unc, ref_unc, rtol=1e-7, atol=1e-9)
        # ground truth: nothing along the wire (the tangent is in the null space)
        np.testing.assert_allclose(np.einsum("nij,nj->ni", cov, tan3), 0.0, atol=1e-9)
