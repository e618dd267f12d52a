"""The reconstruction's compiled kernels (guidewire3d.kernels) against the numpy / SciPy code they
replaced in guidewire3d.reconstruction (path, placement, uncertainty, smoothing): same numbers to
rounding, on random inputs (ties and degenerate cases included where the plain code has a rule)."""
from __future__ import annotations

import numpy as np
import pytest
from guidewire3d import kernels
from guidewire3d.reconstruction.placement import ALONG_SCALE_MM, DIST_SCALE_MM
from guidewire3d.reconstruction.smoothing import _penalised_banded  # the penalty fit_pspline adds (LAPACK path)
from scipy.interpolate import BSpline
from scipy.linalg import solveh_banded

RTOL = 1e-12


def _tree_tables(rng, N=60, B=5):
    """Random stand-ins for a ReconstructionContext's tables (the kernels only index them)."""
    s = rng.uniform(0.0, 80.0, N)
    point_branch = rng.integers(0, B, N)
    lca = rng.uniform(0.0, 40.0, (B, B))
    lca = np.minimum(lca, lca.T)
    lca[rng.random((B, B)) < 0.3] = np.inf          # branches on one root path
    np.fill_diagonal(lca, np.inf)
    points = rng.normal(0.0, 30.0, (N, 3)) + [10.0, -200.0, 150.0]
    uv = rng.uniform(0.0, 512.0, (N, 2))
    return s, point_branch, lca, points, uv


def _lca_s(s, point_branch, lca, i, j):
    return np.minimum(np.minimum(s[i], s[j]), lca[point_branch[i], point_branch[j]])


@pytest.mark.parametrize("seed", range(4))
def test_viterbi_pairwise_is_the_numpy_formulation(seed):
    """The pairwise costs of reconstruction.path.viterbi_path as it computed them in numpy."""
    rng = np.random.default_rng(seed)
    s, pb, lca, points, uvt = _tree_tables(rng)
    A, K = int(rng.integers(2, 30)), int(rng.integers(1, 17))
    safe = rng.integers(0, len(s), (A, K))
    uv_a = rng.uniform(0.0, 512.0, (A, 2))
    sst, sj, sr = 3.0, 0.5, 1.0
    # the former numpy code
    i, j = safe[:-1, :, None], safe[1:, None, :]
    slca = _lca_s(s, pb, lca, i, j)
    up = s[i] - slca
    geo = up + (s[j] - slca)
    Xc, Uc = points[safe], uvt[safe]
    n2 = np.einsum("akx,akx->ak", Xc, Xc)
    e3 = np.sqrt(np.maximum(n2[:-1, :, None] + n2[1:, None, :] - 2.0 * Xc[:-1] @ np.transpose(Xc[1:], (0, 2, 1)), 0.0))
    a = Uc[1:] - (uv_a[1:] - uv_a[:-1])[:, None, :]
    m2 = (np.einsum("akx,akx->ak", Uc[:-1], Uc[:-1])[:, :, None] + np.einsum("akx,akx->ak", a, a)[:, None, :]
          - 2.0 * Uc[:-1] @ np.transpose(a, (0, 2, 1)))
    ref = (2.0 * (np.sqrt(1.0 + np.maximum(m2, 0.0) / sst**2) - 1.0) + np.maximum(geo - e3, 0.0) / sj + up / sr)
    got = kernels.viterbi_pairwise(safe, s, pb, lca, points, uvt, uv_a, sigma_step_px=sst, sigma_jump_mm=sj,
                                   sigma_retreat_mm=sr)
    assert got.shape == (A - 1, K, K)
    # the expanded |a|^2 + |b|^2 - 2 a.b loses digits on points ~200 mm from the origin: absolute tolerance
    np.testing.assert_allclose(got, ref, rtol=RTOL, atol=1e-9)


def _place_reference(o, d, P, points, radius, offset, lo, hi, W, p):
    """reconstruction.placement.place_on_path's former numpy code, from its segment window on."""
    seg = lo[:, None] + np.arange(W)[None, :]
    segok = seg < np.minimum(hi, lo + W)[:, None]
    seg = np.minimum(seg, len(P) - 2)
    pa_ids, pb_ids = P[:-1], P[1:]
    A, B, rA, rB = points[pa_ids], points[pb_ids], radius[pa_ids], radius[pb_ids]
    e = B - A
    w0 = A - o
    c = np.einsum("sk,sk->s", e, e)[seg]
    q = np.einsum("sk,sk->s", e, w0)[seg]
    w2 = np.einsum("sk,sk->s", w0, w0)[seg]
    b = np.einsum("mwk,mk->mw", e[seg], d)
    pp = np.einsum("mwk,mk->mw", w0[seg], d)
    den = c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(den > 1e-12, (pp * b - q) / den, 0.5)
    u = np.clip(u, 0.0, 1.0)
    s = pp + u * b
    dist = np.sqrt(np.maximum(s * s - 2 * s * u * b - 2 * s * pp + u * u * c + 2 * u * q + w2, 0.0))
    r = rA[seg] + u * (rB - rA)[seg]
    sin2 = np.clip(1.0 - b * b / np.maximum(c, 1e-24), 1e-6, 1.0)
    half = np.sqrt(np.clip(r * r - dist * dist, 0.0, None) / sin2)
    half = np.minimum(half, 0.5 * np.abs(b) + r)
    seg_len = np.linalg.norm(B - A, axis=1)[seg]
    along = (seg + u - p[:, None]) * seg_len
    cost = np.where(segok, (dist / DIST_SCALE_MM) ** 2 + (along / ALONG_SCALE_MM) ** 2, np.inf)
    m = np.arange(len(d))
    w = np.argmin(cost, axis=1)
    s_, d_, u_, h_, r_ = (x[m, w] for x in (s, dist, u, half, r))
    sw = seg[m, w]
    a_ids, b_ids = pa_ids[sw], pb_ids[sw]
    off = offset[a_ids] + u_[:, None] * (offset[b_ids] - offset[a_ids])
    Y = points[a_ids] + u_[:, None] * (points[b_ids] - points[a_ids]) + off
    s_ = np.clip(np.einsum("mk,mk->m", Y - o, d), s_ - h_, s_ + h_)
    X = o + s_[:, None] * d
    return X, np.where(u_ < 0.5, a_ids, b_ids), h_, d_, r_


@pytest.mark.parametrize("seed", range(4))
def test_place_on_path_kernel_is_the_numpy_formulation(seed):
    """Rays from a source through points near a curved tube (and a stretch along the beam, where
    many segments touch a ray): the same segment, depth and chord as the numpy code."""
    rng = np.random.default_rng(seed)
    N = 80
    tt = np.linspace(0.0, 3.0, N)
    points = np.column_stack([30 * np.sin(tt), 40 * tt, 10 * np.cos(2 * tt)]) + rng.normal(0, 0.05, (N, 3))
    points[30:38, 2] = np.linspace(points[30, 2], points[30, 2] + 25.0, 8)   # along the beam (z)
    points[30:38, :2] = points[30, :2]
    radius = rng.uniform(0.8, 2.5, N)
    offset = rng.normal(0.0, 0.3, (N, 3))
    P = np.arange(N)[::-1].copy() if seed % 2 else np.arange(N)      # either direction along the ids
    o = np.array([0.0, 0.0, -700.0])
    M = 150
    k = np.sort(rng.uniform(0, N - 1.001, M))
    target = points[P[k.astype(int)]] + rng.normal(0.0, 1.5, (M, 3))
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    p = k + rng.normal(0.0, 1.0, M)
    lo = np.clip(np.floor(p).astype(int) - 4, 0, N - 2)
    hi = np.clip(np.ceil(p).astype(int) + 4 + rng.integers(0, 3, M), 1, N - 1)
    W = int((hi - lo).max()) - int(rng.integers(0, 2))     # sometimes narrower than a window
    got = kernels.place_on_path(o, d, P, points, radius, offset, lo, np.minimum(hi, lo + W), W, p,
                                dist_scale_mm=DIST_SCALE_MM, along_scale_mm=ALONG_SCALE_MM)
    ref = _place_reference(o, d, P, points, radius, offset, lo, hi, W, p)
    np.testing.assert_array_equal(got[1], ref[1])
    # the ray-axis distance comes from an expanded square (|w0|^2 ~ (700 mm)^2 cancels): equal to
    # ~1e-10 mm^2 in the squares, which is what the half chord and the depth inherit
    X, _, half, dist, r = got
    np.testing.assert_allclose(dist**2, ref[3] ** 2, rtol=0, atol=1e-9)
    np.testing.assert_allclose(half**2, ref[2] ** 2, rtol=0, atol=1e-7)  # (divided by sin^2 of ray and vessel)
    np.testing.assert_allclose(r, ref[4], rtol=RTOL, atol=1e-12)
    np.testing.assert_allclose(X, ref[0], rtol=0, atol=1e-7)


def test_place_on_path_kernel_with_no_valid_segment_takes_the_first():
    """A window with no segment that counts (the numpy argmin over inf): the first segment."""
    points = np.array([[0.0, 0.0, 100.0], [1.0, 0.0, 100.0], [2.0, 0.0, 100.0]])
    d = np.array([[0.015, 0.0, 1.0]]) / np.linalg.norm([0.015, 0.0, 1.0])
    X, tid, *_ = kernels.place_on_path(np.zeros(3), d, np.arange(3), points, np.ones(3), np.zeros((3, 3)),
                                       np.array([0]), np.array([0]), 2, np.array([0.0]),
                                       dist_scale_mm=DIST_SCALE_MM, along_scale_mm=ALONG_SCALE_MM)
    ref = _place_reference(np.zeros(3), d, np.arange(3), points, np.ones(3), np.zeros((3, 3)), np.array([0]),
                           np.array([0]), 2, np.array([0.0]))
    np.testing.assert_allclose(X, ref[0], rtol=RTOL)
    assert tid[0] == ref[1][0]


def _cross(a, b):
    a, b = np.broadcast_arrays(a, b)
    return np.column_stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]])


def _outer(a, b=None):
    return a[:, :, None] * (a if b is None else b)[:, None, :]


def _lumen_covariance_reference(d, t, X, Rc, tc, focal, R, tp, sg, g, si, C, hw, miss, amb, k2, spread, scl):
    """reconstruction.uncertainty.covariance_lumen's former numpy code."""
    M = len(X)
    n = _cross(d, t)
    sin = np.linalg.norm(n, axis=1)
    alt = _cross(d, np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]]))
    along = sin <= 1e-6
    n = np.where(along[:, None], alt, n)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = np.where(along[:, None], _cross(n, d), t)
    cos = np.abs(np.einsum("mk,mk->m", d, t))
    q = _cross(t, n)
    m = _cross(n, d)
    gain = cos / np.maximum(cos**2 + k2 * sin**2, 1e-12)
    xc = X @ Rc.T + tc
    z = xc[:, 2]
    J = np.zeros((M, 2, 3))
    J[:, 0, 0] = J[:, 1, 1] = focal / z
    J[:, 0, 2] = -focal * xc[:, 0] / z**2
    J[:, 1, 2] = -focal * xc[:, 1] / z**2
    J = J @ Rc
    JJt = J @ np.transpose(J, (0, 2, 1))
    det = JJt[:, 0, 0] * JJt[:, 1, 1] - JJt[:, 0, 1] * JJt[:, 1, 0]
    inv = np.stack([np.stack([JJt[:, 1, 1], -JJt[:, 0, 1]], -1), np.stack([-JJt[:, 1, 0], JJt[:, 0, 0]], -1)], 1)
    inv /= det[:, None, None]
    Jn = np.einsum("mij,mjk,mk->mi", inv, J, n)
    Jm = np.einsum("mij,mjk,mk->mi", inv, J, m)
    s_nn = sg**2 * np.einsum("mi,mi->m", Jn, Jn)
    s_nm = sg**2 * np.einsum("mi,mi->m", Jn, Jm)
    s_mm = sg**2 * np.einsum("mi,mi->m", Jm, Jm)
    if g is not None:
        gn, gm = np.einsum("mi,mi->m", g, Jn), np.einsum("mi,mi->m", g, Jm)
        s_nn, s_nm, s_mm = s_nn + si**2 * gn * gn, s_nm + si**2 * gn * gm, s_mm + si**2 * gm * gm
    if C is not None:
        x_room = X @ R.T + tp
        vn, vm = n @ R.T, m @ R.T
        bn = np.hstack([vn, _cross(x_room, vn)])
        bm = np.hstack([vm, _cross(x_room, vm)])
        Cbn, Cbm = bn @ C, bm @ C
        s_nn = s_nn + np.einsum("mi,mi->m", Cbn, bn)
        s_nm = s_nm + np.einsum("mi,mi->m", Cbn, bm)
        s_mm = s_mm + np.einsum("mi,mi->m", Cbm, bm)
    miss2 = miss**2
    a = s_nn + miss2
    b = gain * s_nm
    c = gain**2 * s_mm + (spread * hw) ** 2 + scl**2 + miss2
    if amb is not None:
        Bn = np.einsum("mij,mj->mi", amb, n)
        a = a + np.einsum("mi,mi->m", Bn, n)
        b = b + np.einsum("mi,mi->m", Bn, q)
        c = c + np.einsum("mi,mj,mij->m", q, q, amb)
    nq = _outer(n, q)
    return a[:, None, None] * _outer(n) + b[:, None, None] * (nq + np.transpose(nq, (0, 2, 1))) \
        + c[:, None, None] * _outer(q)


def _rotation(rng):
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return Q * np.sign(np.linalg.det(Q))


@pytest.mark.parametrize("terms", [(False, False, False), (True, True, True), (True, False, True), (False, True, False)])
def test_lumen_covariance_kernel_is_the_numpy_formulation(terms):
    """Each optional term (image gradient, registration covariance, branch ambiguity) on or off;
    rays along the vessel (both fallback normals) included."""
    has_img, has_reg, has_amb = terms
    rng = np.random.default_rng(11)
    M = 120
    Rc, tc = _rotation(rng), np.array([3.0, -5.0, 800.0])
    R, tp = _rotation(rng), rng.normal(0.0, 20.0, 3)
    X = rng.normal(0.0, 40.0, (M, 3))
    source = -Rc.T @ tc
    d = X - source
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = rng.normal(size=(M, 3))
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    t[:3] = d[:3]                                           # a ray along the vessel
    d[3] = [0.95, 0.0, np.sqrt(1 - 0.95**2)]                # ... with |d_x| >= 0.9 (the other normal)
    t[3] = d[3]
    g = rng.normal(0.0, 0.05, (M, 2)) if has_img else None
    L = rng.normal(size=(6, 6))
    C = (L @ L.T) * 1e-2 if has_reg else None
    Ba = rng.normal(size=(M, 3, 3))
    amb = Ba @ np.transpose(Ba, (0, 2, 1)) if has_amb else None
    hw, miss = rng.uniform(0.0, 2.0, M), np.where(rng.random(M) < 0.3, rng.uniform(0.0, 1.0, M), 0.0)
    k2 = (ALONG_SCALE_MM / DIST_SCALE_MM) ** 2
    ref = _lumen_covariance_reference(d, t, X, Rc, tc, 4000.0, R, tp, 2.0, g, 0.1, C, hw, miss, amb, k2, 0.3, 0.2)
    got = kernels.lumen_covariance(d, t, X, Rc=Rc, tc=tc, focal_px=4000.0, pose_R=R, pose_t=tp, sigma_geo_px=2.0,
                                   image_gradient=g, sigma_img=0.1, registration_covariance=C, half_width_mm=hw,
                                   miss_mm=miss, ambiguity_mm2=amb, k2=k2, lumen_spread=0.3, sigma_centerline_mm=0.2)
    # where the ray runs along the vessel the gain cos / max(cos^2, 1e-12) of the sideways shift is
    # rounding noise (cos ~ 1e-17 after t is made normal to the ray) in both: compare n^T Sigma n there
    tol = 1e-12 * float(np.abs(ref).max())
    np.testing.assert_allclose(got[4:], ref[4:], rtol=1e-10, atol=tol)
    n = _cross(d[:4], np.where(np.abs(d[:4, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]]))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    np.testing.assert_allclose(np.einsum("mi,mij,mj->m", n, got[:4], n), np.einsum("mi,mij,mj->m", n, ref[:4], n),
                               rtol=1e-10, atol=tol)
    assert np.allclose(got[:4], np.transpose(got[:4], (0, 2, 1))) and np.all(np.linalg.eigvalsh(got[:4]) > -tol)


def _normal_equations_reference(x, t, wn, Y):
    """The former fit_pspline: SciPy's design matrix and the bincount normal equations."""
    Bm = BSpline.design_matrix(x, t, 3)
    nb, M = Bm.shape[1], len(x)
    D, J = Bm.data.reshape(M, 4), Bm.indices.reshape(M, 4)
    ab = np.zeros((4, nb))
    for a in range(4):
        for b in range(a, 4):
            ab[3 - (b - a)] += np.bincount(J[:, b], weights=wn * D[:, a] * D[:, b], minlength=nb)[:nb]
    BtY = np.column_stack([np.bincount(J.ravel(), weights=(wn[:, None] * D * Y[:, [d]]).ravel(), minlength=nb)[:nb]
                           for d in range(Y.shape[1])])
    return Bm, D, J[:, 0], ab, BtY


@pytest.mark.parametrize("nint", [1, 2, 7, 40])
def test_pspline_kernels_are_scipy_and_lapack(nint):
    """The design rows equal SciPy's design matrix (data points on knots and at both ends
    included), the normal equations the bincount ones, and the penalised fit LAPACK's banded solve
    (with its projection error against the numpy projection)."""
    rng = np.random.default_rng(nint)
    M = 200
    x = np.sort(np.r_[0.0, rng.uniform(0.0, 100.0, M - 2), 100.0])
    t = np.r_[[0.0] * 3, np.linspace(0.0, 100.0, nint + 1), [100.0] * 3]
    x[5:8] = t[3:6] if nint >= 2 else x[5:8]                 # on interior knots
    x.sort()
    wn = rng.uniform(0.5, 1.5, M)
    wn /= wn.sum()
    Y = np.column_stack([np.sin(x / 10), np.cos(x / 13), x / 50]) * 20 + [0.0, 0.0, 50.0] + rng.normal(0, 0.2, (M, 3))
    Bm, D_ref, first_ref, ab_ref, BtY_ref = _normal_equations_reference(x, t, wn, Y)
    D, first, ab, BtY = kernels.pspline_system(x, t, wn, Y)
    np.testing.assert_array_equal(first, first_ref)
    np.testing.assert_allclose(D, D_ref, rtol=0, atol=1e-15)
    np.testing.assert_allclose(ab, ab_ref, rtol=RTOL, atol=1e-17)
    np.testing.assert_allclose(BtY, BtY_ref, rtol=RTOL, atol=1e-15)
    Rc, tc, focal, pp = _rotation(rng), np.array([1.0, 2.0, 700.0]), 3000.0, np.array([256.0, 256.0])
    for lam in (0.1, 1e-3):
        coef = solveh_banded(_penalised_banded(ab_ref, lam), BtY_ref)
        Xs_ref = Bm @ coef
        xc = Xs_ref @ Rc.T + tc
        uv = focal * xc[:, :2] / xc[:, 2:3] + pp + rng.normal(0.0, 0.5, (M, 2))
        xc_ref = Xs_ref @ Rc.T + tc
        err = np.linalg.norm(focal * xc_ref[:, :2] / xc_ref[:, 2:3] + pp - uv, axis=1)
        Xs, mean_px, max_px = kernels.penalised_fit(D, first, ab, BtY, lam=lam, uv_px=uv, Rc=Rc, tc=tc,
                                                    focal_px=focal, principal_point_px=pp)
        np.testing.assert_allclose(Xs, Xs_ref, rtol=1e-9, atol=1e-9)
        assert mean_px == pytest.approx(err.mean(), rel=1e-9) and max_px == pytest.approx(err.max(), rel=1e-9)


def test_penalised_fit_of_a_singular_system_is_nan():
    """A system that is not positive definite gives NaN (the caller reports it), not a wrong fit."""
    D = np.full((3, 4), 0.25)
    ab = np.zeros((4, 4))
    ab[3] = [1.0, -1.0, 1.0, 1.0]
    Xs, mean_px, max_px = kernels.penalised_fit(D, np.zeros(3, np.int64), ab, np.ones((4, 3)), lam=0.0,
                                                uv_px=np.zeros((3, 2)), Rc=np.eye(3), tc=np.array([0, 0, 10.0]),
                                                focal_px=1.0, principal_point_px=np.zeros(2))
    assert np.all(np.isnan(Xs)) and np.isnan(mean_px) and np.isnan(max_px)


@pytest.mark.parametrize("n", [2, 3, 50])
def test_polyline_measures_are_numpy_gradient_and_cross(n):
    rng = np.random.default_rng(n)
    X = np.cumsum(rng.normal(0.0, 1.0, (n, 3)), axis=0)
    X[n // 2] = X[n // 2 - 1] if n > 2 else X[n // 2]       # a repeated point (zero first derivative)
    d1 = np.gradient(X, axis=0)
    T_ref = d1 / np.maximum(np.linalg.norm(d1, axis=1, keepdims=True), 1e-12)
    T, kappa = kernels.polyline_measures(X)
    np.testing.assert_allclose(T, T_ref, rtol=RTOL, atol=1e-15)
    if n >= 3:
        d2 = np.gradient(d1, axis=0)
        k_ref = np.linalg.norm(np.cross(d1, d2), axis=1) / np.maximum(np.linalg.norm(d1, axis=1) ** 3, 1e-12)
        np.testing.assert_allclose(kappa, k_ref, rtol=1e-11, atol=1e-15)


@pytest.mark.parametrize("seed", range(3))
def test_branch_ambiguity_is_the_numpy_formulation(seed):
    """reconstruction.path.ambiguity_mm2's former einsum, with missing candidates and infinite excess."""
    rng = np.random.default_rng(seed)
    s, pb, lca, points, _ = _tree_tables(rng)
    A, K = 25, 12
    cand = rng.integers(0, len(s), (A, K))
    cand[rng.random((A, K)) < 0.2] = -1
    excess = rng.exponential(3.0, (A, K))
    excess[rng.random((A, K)) < 0.1] = np.inf
    excess[:, 0] = 0.0
    nodes = rng.integers(0, len(s), A)
    safe = np.maximum(cand, 0)
    w = np.where((cand >= 0) & np.isfinite(excess), np.exp(-excess / 2.0), 0.0)
    w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    D = points[safe] - points[nodes][:, None, :]
    geo = s[safe] + s[nodes][:, None] - 2.0 * _lca_s(s, pb, lca, safe, nodes[:, None])
    other = geo - np.linalg.norm(D, axis=2) > 0.5
    ref = np.einsum("ak,aki,akj->aij", w * other, D, D)
    got = kernels.branch_ambiguity(cand, excess, nodes, points, s, pb, lca, scale=2.0, sigma_jump_mm=0.5)
    np.testing.assert_allclose(got, ref, rtol=1e-11, atol=1e-12)


def test_warm_up_compiles_the_one_specialisation_the_reconstruction_uses():
    """Whatever the callers' arrays (writable here, read-only tree tables in a context), each kernel
    has the one compiled specialisation warm_up made: the first live frame compiles nothing."""
    kernels.warm_up()
    compiled = kernels._compile_reconstruction()
    before = {name: len(f.signatures) for name, f in compiled.items()}
    assert set(before.values()) == {1}
    test_viterbi_pairwise_is_the_numpy_formulation(0)
    test_place_on_path_kernel_is_the_numpy_formulation(1)
    test_lumen_covariance_kernel_is_the_numpy_formulation((True, True, True))
    test_lumen_covariance_kernel_is_the_numpy_formulation((False, False, False))
    test_pspline_kernels_are_scipy_and_lapack(7)
    test_polyline_measures_are_numpy_gradient_and_cross(50)
    test_branch_ambiguity_is_the_numpy_formulation(0)
    ro = np.arange(9.0).reshape(3, 3)
    ro.flags.writeable = False
    kernels.polyline_measures(ro)
    assert {name: len(f.signatures) for name, f in compiled.items()} == before
