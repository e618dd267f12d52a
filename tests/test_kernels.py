"""The compiled kernels against the numpy / SciPy code they replace (guidewire3d.kernels)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage as ndi

from guidewire3d import kernels

SAMPLE_TOL = 1e-12   # relative to the image's range: a rounding difference, not an interpolation one


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.uint8, np.uint16, bool])
@pytest.mark.parametrize("mode", ["nearest", "constant"])
def test_sample_bilinear_is_map_coordinates_order_1(dtype, mode):
    rng = np.random.default_rng(7)
    img = (rng.random((23, 31)) * (1 if dtype is bool else 200)).astype(dtype) if dtype is not bool \
        else rng.random((23, 31)) > 0.5
    r = rng.uniform(-3.0, 25.0, 5000)
    c = rng.uniform(-3.0, 33.0, 5000)
    r[:40], c[40:80] = np.round(r[:40]), np.round(c[40:80])          # on pixel centres
    r[80:90], c[90:100] = 22.0, 30.0                                  # exactly on the last row / column
    r[100:110], c[110:120] = -1e-12, 30.0 + 1e-12                     # just outside
    ref = ndi.map_coordinates(img.astype(np.float64), [r, c], order=1, mode=mode, cval=0.0)
    got = kernels.sample_bilinear(img, r, c, mode=mode)
    assert got.dtype == np.float64 and got.shape == r.shape
    np.testing.assert_allclose(got, ref, rtol=0, atol=SAMPLE_TOL * max(float(np.ptp(ref)), 1.0))
    if mode == "constant":
        outside = (r < 0) | (r > 22) | (c < 0) | (c > 30)
        assert np.all(got[outside] == 0.0)


def test_sample_bilinear_keeps_the_shape_and_refuses_other_modes():
    img = np.arange(12.0).reshape(3, 4)
    rows, cols = np.full((2, 5), 1.5), np.full((2, 5), 2.25)
    out = kernels.sample_bilinear(img, rows, cols)
    assert out.shape == (2, 5)
    np.testing.assert_allclose(out, 1.5 * 4 + 2.25)     # a linear image is reproduced exactly
    with pytest.raises(ValueError, match="mode"):
        kernels.sample_bilinear(img, [0.0], [0.0], mode="reflect")


def _viterbi_reference(acc0, U, C, skip):
    """The numpy recursions that the Viterbi (reconstruction.path.viterbi_path) ran before the kernels."""
    A, K = U.shape
    acc = acc0.copy()
    alpha = np.empty((A, K))
    alpha[0] = acc
    back = np.zeros((A - 1, K), np.int64)
    end_t, end_k = 0, int(np.argmin(acc))
    end_cost = float(acc[end_k]) + skip * (A - 1)
    for t in range(A - 1):
        tot = acc[:, None] + C[t]
        b = tot.argmin(axis=0)
        back[t] = b
        acc = tot[b, np.arange(K)] + U[t + 1]
        alpha[t + 1] = acc
        k = int(np.argmin(acc))
        c = float(acc[k]) + skip * (A - 2 - t)
        if c < end_cost:
            end_t, end_k, end_cost = t + 1, k, c
    beta = np.zeros((end_t + 1, K))
    for t in range(end_t - 1, -1, -1):
        beta[t] = (C[t] + (U[t + 1] + beta[t + 1])).min(axis=1)
    return alpha, back, end_t, end_k, end_cost, beta


@pytest.mark.parametrize("seed", range(6))
def test_viterbi_kernels_equal_the_numpy_recursions(seed):
    rng = np.random.default_rng(seed)
    A, K = int(rng.integers(2, 40)), int(rng.integers(1, 12))
    U = rng.random((A, K)) * 3.0
    U[rng.random((A, K)) < 0.3] = np.inf            # anchors without some candidates
    C = np.round(rng.random((A - 1, K, K)) * 4.0, 1)  # rounded: ties, which the first minimum breaks
    acc0 = U[0] + rng.random(K)
    skip = float(rng.choice([0.5, 2.0, 50.0]))
    alpha, back, end_t, end_k, end_cost, beta = _viterbi_reference(acc0, U, C, skip)
    a2, b2, t2, k2, c2 = kernels.viterbi_forward(acc0, U, C, skip)
    np.testing.assert_array_equal(a2, alpha)
    np.testing.assert_array_equal(b2, back)
    assert (int(t2), int(k2), float(c2)) == (end_t, end_k, end_cost)
    np.testing.assert_array_equal(kernels.viterbi_backward(C, U, end_t), beta)


def _cover_cells_reference(cells, g, c, call):
    """The recursive bisection of kernels.cover_cells written plainly (numpy per cut)."""
    def fit(i0, i1, j0, j1):
        sub = cells[i0:i1, j0:j1]
        rows = np.flatnonzero(sub.any(axis=1))
        if rows.size == 0:
            return None
        cols = np.flatnonzero(sub.any(axis=0))
        return (i0 + rows[0], i0 + rows[-1] + 1, j0 + cols[0], j0 + cols[-1] + 1)

    def cost(b):
        return 0 if b is None else ((b[1] - b[0]) * g + 2 * c) * ((b[3] - b[2]) * g + 2 * c) + call

    out, todo = [], [fit(0, cells.shape[0], 0, cells.shape[1])]
    while todo:
        b = todo.pop()
        if b is None:
            continue
        i0, i1, j0, j1 = b
        rows = min(((cost(fit(i0, k, j0, j1)) + cost(fit(k, i1, j0, j1)), k) for k in range(i0 + 1, i1)), default=None)
        cols = min(((cost(fit(i0, i1, j0, k)) + cost(fit(i0, i1, k, j1)), k) for k in range(j0 + 1, j1)), default=None)
        if rows is not None and rows[0] < cost(b) and (cols is None or rows[0] <= cols[0]):
            todo += [fit(i0, rows[1], j0, j1), fit(rows[1], i1, j0, j1)]
        elif cols is not None and cols[0] < cost(b):
            todo += [fit(i0, i1, j0, cols[1]), fit(i0, i1, cols[1], j1)]
        else:
            out.append(tuple(int(x) for x in b))
    return out


@pytest.mark.parametrize("seed", range(12))
def test_cover_cells_is_the_plain_bisection_and_covers_every_cell(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 40))
    cells = np.zeros((n, int(rng.integers(1, 40))), bool)
    # a random walk (a wire's band) plus a few isolated cells
    i, j = rng.integers(0, cells.shape[0]), rng.integers(0, cells.shape[1])
    for _ in range(int(rng.integers(1, 80))):
        cells[i, j] = True
        i = int(np.clip(i + rng.integers(-1, 2), 0, cells.shape[0] - 1))
        j = int(np.clip(j + rng.integers(-1, 2), 0, cells.shape[1] - 1))
    cells[rng.integers(0, cells.shape[0], 3), rng.integers(0, cells.shape[1], 3)] = True
    got = [tuple(int(x) for x in b) for b in kernels.cover_cells(cells, 8, 8, 2000)]
    assert sorted(got) == sorted(_cover_cells_reference(cells, 8, 8, 2000))
    covered = np.zeros_like(cells)
    for i0, i1, j0, j1 in got:
        assert cells[i0:i1, j0:j1].any()
        covered[i0:i1, j0:j1] = True
    assert not (cells & ~covered).any()


def test_cover_cells_of_an_empty_grid_is_empty():
    assert kernels.cover_cells(np.zeros((5, 7), bool), 8, 8, 2000).shape == (0, 4)


def _frangi_reference(F, idx, sp, s, alpha=0.5, beta=0.5, gamma=0.15):
    """The numpy formulation kernels.frangi_at replaced (derivs_at, LAPACK eigvalsh, Frangi's formula)."""
    from guidewire3d.cta.grid import derivs_at

    _, H = derivs_at(F, idx, sp)
    lam = np.linalg.eigvalsh(H * (s * s))
    lam = np.take_along_axis(lam, np.argsort(np.abs(lam), axis=1), axis=1)
    l1, l2, l3 = lam[:, 0], lam[:, 1], lam[:, 2]
    ra = np.abs(l2) / np.maximum(np.abs(l3), 1e-12)
    rb = np.abs(l1) / np.sqrt(np.maximum(np.abs(l2 * l3), 1e-24))
    S2 = l1 * l1 + l2 * l2 + l3 * l3
    v = (1 - np.exp(-ra * ra / (2 * alpha ** 2))) * np.exp(-rb * rb / (2 * beta ** 2)) * (1 - np.exp(-S2 / (2 * gamma ** 2)))
    return np.where((l2 < 0) & (l3 < 0), v, 0.0).astype(np.float32)


def test_frangi_at_is_the_numpy_formulation():
    """On a smoothed bright tube and noise: the same vesselness within float32 rounding, at the
    tube's axis high and in the background 0; and diagonal (p1 = 0) Hessians handled."""
    rng = np.random.default_rng(3)
    z, y, x = np.mgrid[0:30, 0:40, 0:50].astype(float)
    tube = np.exp(-((y - 20.0) ** 2 + (z - 15.0) ** 2) / (2 * 2.5 ** 2))          # along x
    F = ndi.gaussian_filter(tube + 0.05 * rng.standard_normal(tube.shape), 1.0).astype(np.float32)
    sp = np.array([1.2, 0.7, 0.7])
    idx = np.argwhere(np.ones(F.shape, bool)[1:-1, 1:-1, 1:-1]) + 1
    for s in (0.8, 2.0, 4.0):
        got = kernels.frangi_at(F, idx, sp, s, alpha=0.5, beta=0.5, gamma=0.15)
        ref = _frangi_reference(F, idx, sp, s)
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6)
    on_axis, far = kernels.frangi_at(F, np.array([[15, 20, 25], [15, 3, 25]]), sp, 2.0, alpha=0.5, beta=0.5, gamma=0.15)
    assert on_axis > 0.1 and far < 0.01 * on_axis
    flat = np.zeros((5, 5, 5), np.float32)
    flat[2, 2, 2] = -1.0          # a dark point: diagonal Hessian, positive eigenvalues
    assert kernels.frangi_at(flat, np.array([[2, 2, 2]]), np.ones(3), 1.0, alpha=0.5, beta=0.5, gamma=0.15)[0] == 0.0


def _random_masks(seed: int, n: int):
    """Random masks of the shapes a wire segmenter answers: smooth blobs and bands, and noise."""
    rng = np.random.default_rng(seed)
    for i in range(n):
        shape = tuple(int(x) for x in rng.integers(3, 70, 2))
        if i % 3 == 0:
            yield rng.random(shape) < rng.uniform(0.1, 0.9)
        else:
            yield ndi.gaussian_filter(rng.random(shape), rng.uniform(0.6, 3.0)) > 0.5 + rng.uniform(-0.04, 0.04)


@pytest.mark.parametrize("seed", range(4))
def test_skeleton_pixels_is_skimage_skeletonize(seed):
    """The compiled thinning gives scikit-image's skeleton pixel for pixel (its pixels in
    row-major order) and the mask's area, on blobs, bands and noise."""
    from skimage.morphology import skeletonize

    for mask in _random_masks(seed, 400):
        rows, cols, n_on = kernels.skeleton_pixels(mask)
        ref_r, ref_c = np.nonzero(skeletonize(mask))
        np.testing.assert_array_equal(rows, ref_r)
        np.testing.assert_array_equal(cols, ref_c)
        assert n_on == int(mask.sum())


def test_skeleton_pixels_of_a_thick_wire_and_of_other_dtypes():
    from skimage.morphology import skeletonize

    yy, xx = np.mgrid[0:80, 0:120]
    band = np.abs(yy - (40 + 25 * np.sin(xx / 15.0))) <= 3.0          # a wavy 7 px wide wire
    ref = np.nonzero(skeletonize(band))
    for m in (band, band.astype(np.uint8) * 7, band.astype(np.float32), band[:, ::-1][:, ::-1]):
        rows, cols, n_on = kernels.skeleton_pixels(m)
        np.testing.assert_array_equal(rows, ref[0])
        np.testing.assert_array_equal(cols, ref[1])
        assert n_on == int(band.sum())
    assert len(ref[0]) > 100
    empty = kernels.skeleton_pixels(np.zeros((4, 5), bool))
    assert len(empty[0]) == 0 and empty[2] == 0


def _scipy_pixel_graph(mask):
    """The SciPy construction the pixel-graph kernel replaced (coo_matrix -> csr of the 8-neighbours)."""
    from scipy import sparse

    rr, cc = np.nonzero(mask)
    n = rr.size
    index = np.full((mask.shape[0] + 2, mask.shape[1] + 2), -1, np.int64)
    index[rr + 1, cc + 1] = np.arange(n)
    src, dst, wt = [], [], []
    for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):
        j = index[rr + 1 + dr, cc + 1 + dc]
        ok = j >= 0
        src.append(np.nonzero(ok)[0])
        dst.append(j[ok])
        wt.append(np.full(ok.sum(), np.hypot(dr, dc)))
    src, dst, wt = np.concatenate(src), np.concatenate(dst), np.concatenate(wt)
    return rr, cc, sparse.coo_matrix((np.r_[wt, wt], (np.r_[src, dst], np.r_[dst, src])), shape=(n, n)).tocsr()


@pytest.mark.parametrize("seed", range(3))
def test_graph_kernels_are_scipy_csgraph(seed):
    """Pixel graph, induced subgraph, components and Dijkstra against scipy.sparse / csgraph: the
    same CSR arrays and labels, the same distances to the bit, the same predecessors wherever the
    kernel reports no tie."""
    from scipy.sparse import csgraph

    rng = np.random.default_rng(seed)
    n_ties = 0
    for mask in _random_masks(seed + 10, 150):
        rr, cc, g = _scipy_pixel_graph(mask)
        if len(rr) == 0:
            continue
        indptr, indices, w = kernels.pixel_graph(rr, cc, mask.shape)
        np.testing.assert_array_equal(indptr, g.indptr)
        np.testing.assert_array_equal(indices, g.indices)
        np.testing.assert_array_equal(w, g.data)
        n, lab = kernels.graph_components(indptr, indices)
        n_ref, lab_ref = csgraph.connected_components(g, directed=False)
        assert n == n_ref
        np.testing.assert_array_equal(lab, lab_ref)
        nodes = np.flatnonzero(rng.random(len(rr)) < 0.6)
        sub = kernels.induced_subgraph(indptr, indices, w, nodes)
        g_sub = g[nodes][:, nodes]
        for a, b in zip(sub, (g_sub.indptr, g_sub.indices, g_sub.data)):
            np.testing.assert_array_equal(a, b)
        src = rng.choice(len(rr), size=min(3, len(rr)), replace=False)
        dist, _, _ = kernels.dijkstra(indptr, indices, w, src)
        np.testing.assert_array_equal(dist, csgraph.dijkstra(g, directed=False, indices=src, min_only=True))
        dist, pred, tie = kernels.dijkstra(indptr, indices, w, src[:1])
        d_ref, p_ref = csgraph.dijkstra(g, directed=False, indices=int(src[0]), return_predecessors=True)
        np.testing.assert_array_equal(dist, d_ref)
        np.testing.assert_array_equal(pred[~tie], p_ref[~tie])
        n_ties += int(tie.sum())
    assert n_ties > 0                       # the noise masks have tied nodes: the flag is exercised


def test_diameter_path_reports_a_tie_on_its_path():
    """A 4-cycle of diagonal steps (a diamond) between the ends: two paths of the same length."""
    mask = np.zeros((7, 3), bool)
    mask[[0, 1, 2, 2, 3, 4, 5, 6], [1, 1, 0, 2, 1, 1, 1, 1]] = True      # stem, diamond at rows 1-3, stem
    rr, cc, _ = _scipy_pixel_graph(mask)
    seq, length, ambiguous = kernels.diameter_path(*kernels.pixel_graph(rr, cc, mask.shape), 0)
    assert ambiguous and length == pytest.approx(4.0 + 2 * np.sqrt(2.0))
    straight = np.zeros((5, 5), bool)
    straight[2, :] = True
    rr, cc, _ = _scipy_pixel_graph(straight)
    seq, length, ambiguous = kernels.diameter_path(*kernels.pixel_graph(rr, cc, straight.shape), 2)
    assert not ambiguous and length == 4.0 and list(seq) == [0, 1, 2, 3, 4]


@pytest.mark.parametrize("seed", range(3))
def test_nearest_sq_dist_is_ckdtree_within_the_radius(seed):
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    for _ in range(50):
        pts = rng.integers(-10, 60, (int(rng.integers(0, 300)), 2)).astype(float)
        t = np.linspace(0.0, 1.0, int(rng.integers(1, 200)))[:, None]
        curve = rng.uniform(-5, 55, 2) + t * rng.uniform(-60, 60, 2) + rng.normal(0, 0.5, (len(t), 2))
        radius = float(rng.uniform(0.5, 8.0))
        d2 = kernels.nearest_sq_dist(pts, curve, radius)
        d_ref, _ = cKDTree(curve).query(pts) if len(pts) else (np.zeros(0), None)
        near = d_ref <= radius
        brute = ((pts[:, None, :] - curve[None]) ** 2).sum(axis=2).min(axis=1) if len(pts) else np.zeros(0)
        np.testing.assert_array_equal(d2[near], brute[near])
        assert np.all(d2[~near] > radius ** 2)
