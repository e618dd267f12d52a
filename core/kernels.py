"""Compiled kernels of the live path (numba): the loops that numpy cannot vectorise.

The per-frame engine (:class:`guidewire3d.live.session.Session`) spends its time in a few loops over small
arrays: the Viterbi recursion of the 3D reconstruction (one step per anchor of the 2D wire) and the
bilinear sampling of profiles across the 2D wire (sub-pixel centring, end caps, the presence test);
and the ordered 2D wire's graph work: the mask's thinning (scikit-image's Zhang-Suen, over the mask's
pixels instead of its bounding box), the skeleton's 8-connected pixel graph, its components and
shortest paths (SciPy's csgraph answers where a tie makes its path depend on its heap), and the
skeleton's distances to the traced curve.
Each kernel here computes what the numpy / SciPy code it replaces computes, in the same order of
floating-point operations where that is possible (the tests compare them on random inputs).

numba is imported on the first call of a kernel, not when this module is imported, so that
``import guidewire3d`` stays light; the compiled code is cached on disk (``cache=True``) and
:func:`warm_up` compiles (or loads) every kernel ahead of the first frame.
"""
from __future__ import annotations

import threading
import warnings

import numpy as np

__all__ = ["viterbi_forward", "viterbi_backward", "sample_bilinear", "cover_cells", "frangi_at",
           "skeleton_pixels", "pixel_graph", "induced_subgraph", "graph_components", "dijkstra",
           "diameter_path", "nearest_sq_dist", "warm_up"]

_LOCK = threading.Lock()
#: image dtypes sampled as they are (one compiled specialisation each); others are converted to float64
_DIRECT = tuple(np.dtype(t) for t in (np.float64, np.float32, np.uint8, np.uint16, np.int16, np.int32, np.int64))
_WARM = (np.float64, np.float32, np.uint8, np.uint16)
_COMPILED: dict = {}


def _compile():
    """The jitted functions (compiled once per process; loaded from numba's disk cache when present)."""
    with _LOCK:
        if _COMPILED:
            return _COMPILED
        import heapq

        import numba

        def jit(f):
            try:  # cached on disk beside the module, or in the user's cache folder
                return numba.njit(cache=True, nogil=True)(f)
            except RuntimeError:  # no writable cache location: compiled in memory, once per process
                return numba.njit(cache=False, nogil=True)(f)

        @jit
        def viterbi_forward(acc0, U, C, skip_cost):
            A, K = U.shape
            alpha = np.empty((A, K))
            back = np.zeros((max(A - 1, 0), K), np.int64)
            acc = acc0.copy()
            alpha[0] = acc
            end_t = 0
            end_k = 0
            for k in range(1, K):
                if acc[k] < acc[end_k]:
                    end_k = k
            end_cost = acc[end_k] + skip_cost * (A - 1)
            new = np.empty(K)
            for t in range(A - 1):
                for j in range(K):
                    bi = 0
                    best = acc[0] + C[t, 0, j]
                    for i in range(1, K):
                        v = acc[i] + C[t, i, j]
                        if v < best:
                            best = v
                            bi = i
                    back[t, j] = bi
                    new[j] = best + U[t + 1, j]
                k = 0
                for j in range(K):
                    acc[j] = new[j]
                    alpha[t + 1, j] = new[j]
                    if new[j] < new[k]:
                        k = j
                c = acc[k] + skip_cost * (A - 2 - t)
                if c < end_cost:
                    end_t, end_k, end_cost = t + 1, k, c
            return alpha, back, end_t, end_k, end_cost

        @jit
        def viterbi_backward(C, U, end_t):
            K = U.shape[1]
            beta = np.zeros((end_t + 1, K))
            w = np.empty(K)
            for t in range(end_t - 1, -1, -1):
                for j in range(K):
                    w[j] = U[t + 1, j] + beta[t + 1, j]
                for i in range(K):
                    m = C[t, i, 0] + w[0]
                    for j in range(1, K):
                        v = C[t, i, j] + w[j]
                        if v < m:
                            m = v
                    beta[t, i] = m
            return beta

        @jit
        def sample_bilinear(img, rows, cols, nearest, cval):
            H, W = img.shape
            n = rows.shape[0]
            out = np.empty(n)
            for k in range(n):
                r = rows[k]
                c = cols[k]
                if nearest:
                    r = min(max(r, 0.0), H - 1.0)
                    c = min(max(c, 0.0), W - 1.0)
                elif not (r >= 0.0 and r <= H - 1.0 and c >= 0.0 and c <= W - 1.0):
                    out[k] = cval
                    continue
                r0 = int(np.floor(r))
                c0 = int(np.floor(c))
                tr = r - r0
                tc = c - c0
                r1 = min(r0 + 1, H - 1)
                c1 = min(c0 + 1, W - 1)
                # SciPy's order: the sum over the 2 x 2 neighbours of (value * row weight) * col weight
                t = 0.0
                t += (img[r0, c0] * (1.0 - tr)) * (1.0 - tc)
                t += (img[r0, c1] * (1.0 - tr)) * tc
                t += (img[r1, c0] * tr) * (1.0 - tc)
                t += (img[r1, c1] * tr) * tc
                out[k] = t
            return out

        @jit
        def cover_cells(cells, g, c2, call_cost):
            nh, nw = cells.shape
            out = np.empty((nh * nw + 1, 4), np.int64)
            stack = np.empty((nh * nw + 2, 4), np.int64)
            n_out = 0
            b0, b1, a0, a1 = nh, 0, nw, 0
            for i in range(nh):
                for j in range(nw):
                    if cells[i, j]:
                        b0 = min(b0, i)
                        b1 = max(b1, i + 1)
                        a0 = min(a0, j)
                        a1 = max(a1, j + 1)
            if b1 == 0:
                return out[:0]
            stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3] = b0, b1, a0, a1
            ns = 1
            n_max = max(nh, nw)
            lo = np.empty(n_max, np.int64)      # per line (row or column): first occupied cell
            hi = np.empty(n_max, np.int64)      # ... and last (lo > hi: an empty line)
            s_lo = np.empty(n_max, np.int64)    # suffix minima / maxima / first occupied line
            s_hi = np.empty(n_max, np.int64)
            s_first = np.empty(n_max, np.int64)
            best_box = np.empty((2, 2, 4), np.int64)    # [axis][part] -> fitted child (i0, i1, j0, j1)
            for _ in range(4 * nh * nw + 4):
                if ns == 0:
                    break
                ns -= 1
                i0, i1, j0, j1 = stack[ns, 0], stack[ns, 1], stack[ns, 2], stack[ns, 3]
                here = ((i1 - i0) * g + c2) * ((j1 - j0) * g + c2) + call_cost
                best = np.array([here + 1, here + 1])
                for axis in range(2):
                    # lines along the cut axis: rows (axis 0) or columns (axis 1) of the box
                    L0, L1 = (i0, i1) if axis == 0 else (j0, j1)
                    M0, M1 = (j0, j1) if axis == 0 else (i0, i1)
                    n = L1 - L0
                    if n < 2:
                        continue
                    for t in range(n):
                        f, l = M1, M0 - 1
                        for m in range(M0, M1):
                            v = cells[L0 + t, m] if axis == 0 else cells[m, L0 + t]
                            if v:
                                if f == M1:
                                    f = m
                                l = m
                        lo[t], hi[t] = f, l
                    cur_lo, cur_hi, cur_first = M1, M0 - 1, n
                    for t in range(n - 1, -1, -1):
                        cur_lo = min(cur_lo, lo[t])
                        cur_hi = max(cur_hi, hi[t])
                        if lo[t] <= hi[t]:
                            cur_first = t
                        s_lo[t], s_hi[t], s_first[t] = cur_lo, cur_hi, cur_first
                    p_lo, p_hi, p_last = M1, M0 - 1, -1
                    for k in range(1, n):
                        t = k - 1
                        p_lo = min(p_lo, lo[t])
                        p_hi = max(p_hi, hi[t])
                        if lo[t] <= hi[t]:
                            p_last = t
                        top = ((p_last + 1) * g + c2) * ((p_hi - p_lo + 1) * g + c2) + call_cost
                        cost = top
                        if s_first[k] < n:
                            cost += ((n - s_first[k]) * g + c2) * ((s_hi[k] - s_lo[k] + 1) * g + c2) + call_cost
                        if cost < best[axis]:
                            best[axis] = cost
                            if axis == 0:
                                best_box[0, 0, 0], best_box[0, 0, 1] = L0, L0 + p_last + 1
                                best_box[0, 0, 2], best_box[0, 0, 3] = p_lo, p_hi + 1
                                best_box[0, 1, 0], best_box[0, 1, 1] = L0 + s_first[k], L1
                                best_box[0, 1, 2], best_box[0, 1, 3] = s_lo[k], s_hi[k] + 1
                            else:
                                best_box[1, 0, 0], best_box[1, 0, 1] = p_lo, p_hi + 1
                                best_box[1, 0, 2], best_box[1, 0, 3] = L0, L0 + p_last + 1
                                best_box[1, 1, 0], best_box[1, 1, 1] = s_lo[k], s_hi[k] + 1
                                best_box[1, 1, 2], best_box[1, 1, 3] = L0 + s_first[k], L1
                            best_box[axis, 1, 0] = best_box[axis, 1, 0] if s_first[k] < n else -1
                if best[0] < here and best[0] <= best[1]:
                    axis = 0
                elif best[1] < here:
                    axis = 1
                else:
                    out[n_out, 0], out[n_out, 1], out[n_out, 2], out[n_out, 3] = i0, i1, j0, j1
                    n_out += 1
                    continue
                for part in range(2):
                    if best_box[axis, part, 0] >= 0:
                        for q in range(4):
                            stack[ns, q] = best_box[axis, part, q]
                        ns += 1
            return out[:n_out]

        @jit
        def frangi_at(F, idx, sp, s2, alpha, beta, gamma):
            n = idx.shape[0]
            out = np.zeros(n, np.float32)
            H = np.empty((3, 3))
            lam = np.empty(3)
            two_pi_3 = 2.0943951023931957
            for k in range(n):
                z, y, x = idx[k, 0], idx[k, 1], idx[k, 2]
                c = np.float64(F[z, y, x])
                for i in range(3):
                    di = np.zeros(3, np.int64)
                    di[i] = 1
                    pp = np.float64(F[z + di[0], y + di[1], x + di[2]])
                    mm = np.float64(F[z - di[0], y - di[1], x - di[2]])
                    H[i, i] = (pp - 2 * c + mm) / sp[i] ** 2
                    for j in range(i + 1, 3):
                        dj = np.zeros(3, np.int64)
                        dj[j] = 1
                        a = np.float64(F[z + di[0] + dj[0], y + di[1] + dj[1], x + di[2] + dj[2]])
                        b = np.float64(F[z + di[0] - dj[0], y + di[1] - dj[1], x + di[2] - dj[2]])
                        cc = np.float64(F[z - di[0] + dj[0], y - di[1] + dj[1], x - di[2] + dj[2]])
                        d = np.float64(F[z - di[0] - dj[0], y - di[1] - dj[1], x - di[2] - dj[2]])
                        v = (a - b - cc + d) / (4 * sp[i] * sp[j])
                        H[i, j] = v
                        H[j, i] = v
                for i in range(3):
                    for j in range(3):
                        H[i, j] *= s2
                # eigenvalues of the symmetric 3 x 3 (trigonometric method)
                p1 = H[0, 1] ** 2 + H[0, 2] ** 2 + H[1, 2] ** 2
                q = (H[0, 0] + H[1, 1] + H[2, 2]) / 3.0
                if p1 == 0.0:
                    lam[0], lam[1], lam[2] = H[0, 0], H[1, 1], H[2, 2]
                else:
                    p2 = (H[0, 0] - q) ** 2 + (H[1, 1] - q) ** 2 + (H[2, 2] - q) ** 2 + 2.0 * p1
                    p = np.sqrt(p2 / 6.0)
                    b00, b11, b22 = (H[0, 0] - q) / p, (H[1, 1] - q) / p, (H[2, 2] - q) / p
                    b01, b02, b12 = H[0, 1] / p, H[0, 2] / p, H[1, 2] / p
                    r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02)
                               + b02 * (b01 * b12 - b11 * b02))
                    r = min(max(r, -1.0), 1.0)
                    phi = np.arccos(r) / 3.0
                    lam[0] = q + 2.0 * p * np.cos(phi)
                    lam[2] = q + 2.0 * p * np.cos(phi + two_pi_3)
                    lam[1] = 3.0 * q - lam[0] - lam[2]
                # |l1| <= |l2| <= |l3|
                for i in range(1, 3):
                    v = lam[i]
                    j = i - 1
                    while j >= 0 and abs(lam[j]) > abs(v):
                        lam[j + 1] = lam[j]
                        j -= 1
                    lam[j + 1] = v
                l1, l2, l3 = lam[0], lam[1], lam[2]
                if not (l2 < 0 and l3 < 0):
                    continue
                ra = abs(l2) / max(abs(l3), 1e-12)
                rb = abs(l1) / np.sqrt(max(abs(l2 * l3), 1e-24))
                S2 = l1 * l1 + l2 * l2 + l3 * l3
                out[k] = ((1 - np.exp(-ra * ra / (2 * alpha ** 2))) * np.exp(-rb * rb / (2 * beta ** 2))
                          * (1 - np.exp(-S2 / (2 * gamma ** 2))))
            return out

        @jit
        def pixel_graph(rows, cols, h, w, diag_px):
            n = rows.shape[0]
            index = np.full((h + 2, w + 2), -1, np.int32)
            for k in range(n):
                index[rows[k] + 1, cols[k] + 1] = k
            indptr = np.zeros(n + 1, np.int64)
            indices = np.empty(8 * n, np.int64)
            weights = np.empty(8 * n)
            m = 0
            for k in range(n):
                for dr in range(-1, 2):          # neighbours in row-major order: sorted node indices
                    for dc in range(-1, 2):
                        if dr == 0 and dc == 0:
                            continue
                        j = index[rows[k] + 1 + dr, cols[k] + 1 + dc]
                        if j >= 0:
                            indices[m] = j
                            weights[m] = 1.0 if dr == 0 or dc == 0 else diag_px
                            m += 1
                indptr[k + 1] = m
            return indptr, indices[:m].copy(), weights[:m].copy()

        @jit
        def induced_subgraph(indptr, indices, weights, nodes):
            n = indptr.shape[0] - 1
            remap = np.full(n, -1, np.int64)
            for k in range(nodes.shape[0]):
                remap[nodes[k]] = k
            sub_ptr = np.zeros(nodes.shape[0] + 1, np.int64)
            sub_idx = np.empty(indices.shape[0], np.int64)
            sub_w = np.empty(indices.shape[0])
            m = 0
            for k in range(nodes.shape[0]):
                u = nodes[k]
                for e in range(indptr[u], indptr[u + 1]):
                    j = remap[indices[e]]
                    if j >= 0:
                        sub_idx[m] = j
                        sub_w[m] = weights[e]
                        m += 1
                sub_ptr[k + 1] = m
            return sub_ptr, sub_idx[:m].copy(), sub_w[:m].copy()

        @jit
        def graph_components(indptr, indices):
            n = indptr.shape[0] - 1
            labels = np.full(n, -1, np.int64)
            stack = np.empty(n, np.int64)
            n_comp = 0
            for s in range(n):                    # labels in the order of each component's first node
                if labels[s] >= 0:
                    continue
                labels[s] = n_comp
                top = 1
                stack[0] = s
                while top > 0:
                    top -= 1
                    u = stack[top]
                    for e in range(indptr[u], indptr[u + 1]):
                        v = indices[e]
                        if labels[v] < 0:
                            labels[v] = n_comp
                            stack[top] = v
                            top += 1
                n_comp += 1
            return n_comp, labels

        @jit
        def dijkstra(indptr, indices, weights, sources):
            n = indptr.shape[0] - 1
            dist = np.full(n, np.inf)
            pred = np.full(n, -9999, np.int64)
            tie = np.zeros(n, np.bool_)
            done = np.zeros(n, np.bool_)
            heap = [(0.0, np.int64(0)) for _ in range(0)]
            for k in range(sources.shape[0]):
                s = sources[k]
                if dist[s] > 0.0:
                    dist[s] = 0.0
                    heapq.heappush(heap, (0.0, np.int64(s)))
            while len(heap) > 0:
                d, u = heapq.heappop(heap)
                if done[u] or d > dist[u]:
                    continue
                done[u] = True
                for e in range(indptr[u], indptr[u + 1]):
                    v = indices[e]
                    if done[v]:
                        continue
                    nd = d + weights[e]
                    if nd < dist[v]:
                        dist[v] = nd
                        pred[v] = u
                        tie[v] = False
                        heapq.heappush(heap, (nd, v))
                    elif nd == dist[v]:
                        tie[v] = True             # two predecessors at the same distance
            return dist, pred, tie

        @jit
        def walk_predecessors(pred, tie, end):
            n_seq = 0
            node = end
            ambiguous = False
            while node >= 0:
                ambiguous = ambiguous or tie[node]
                n_seq += 1
                node = pred[node]
            seq = np.empty(n_seq, np.int64)
            node = end
            for k in range(n_seq - 1, -1, -1):
                seq[k] = node
                node = pred[node]
            return seq, ambiguous

        @jit
        def zhang_suen(mask, lut):
            H, W = mask.shape
            img = np.zeros((H + 2, W + 2), np.uint8)      # a zero border: no bounds checks
            n = 0
            for r in range(H):
                for c in range(W):
                    if mask[r, c]:
                        img[r + 1, c + 1] = 1
                        n += 1
            n_on = n
            rs = np.empty(n, np.int64)
            cs = np.empty(n, np.int64)
            k = 0
            for r in range(H):
                for c in range(W):
                    if mask[r, c]:
                        rs[k] = r
                        cs[k] = c
                        k += 1
            remove = np.empty(n, np.bool_)
            removed = True
            while removed:
                removed = False
                for sub in range(2):                       # the two sub-iterations (LUT class 1, then 2)
                    want = sub + 1
                    hit = False
                    for k in range(n):                     # decided on the image before the sub-iteration
                        r = rs[k] + 1
                        c = cs[k] + 1
                        v = lut[img[r - 1, c - 1] + 2 * img[r - 1, c] + 4 * img[r - 1, c + 1]
                                + 8 * img[r, c + 1] + 16 * img[r + 1, c + 1] + 32 * img[r + 1, c]
                                + 64 * img[r + 1, c - 1] + 128 * img[r, c - 1]]
                        remove[k] = v == 3 or v == want
                        hit = hit or remove[k]
                    if hit:
                        removed = True
                        m = 0
                        for k in range(n):                 # then applied at once; the order is kept
                            if remove[k]:
                                img[rs[k] + 1, cs[k] + 1] = 0
                            else:
                                rs[m] = rs[k]
                                cs[m] = cs[k]
                                m += 1
                        n = m
            return rs[:n].copy(), cs[:n].copy(), n_on

        @jit
        def nearest_sq_dist(points, curve, cell):
            n = points.shape[0]
            m = curve.shape[0]
            out = np.full(n, np.inf)
            if m == 0:
                return out
            x0, y0 = curve[0, 0], curve[0, 1]
            x1, y1 = x0, y0
            for k in range(m):
                x0, x1 = min(x0, curve[k, 0]), max(x1, curve[k, 0])
                y0, y1 = min(y0, curve[k, 1]), max(y1, curve[k, 1])
            nx = int((x1 - x0) // cell) + 1
            ny = int((y1 - y0) // cell) + 1
            cell_of = np.empty(m, np.int64)
            start = np.zeros(nx * ny + 1, np.int64)
            for k in range(m):                     # the curve's points bucketed in cells (counting sort)
                c = int((curve[k, 1] - y0) // cell) * nx + int((curve[k, 0] - x0) // cell)
                cell_of[k] = c
                start[c + 1] += 1
            for c in range(nx * ny):
                start[c + 1] += start[c]
            fill = start[:-1].copy()
            order = np.empty(m, np.int64)
            for k in range(m):
                order[fill[cell_of[k]]] = k
                fill[cell_of[k]] += 1
            for i in range(n):
                fx = (points[i, 0] - x0) // cell
                fy = (points[i, 1] - y0) // cell
                if fx < -1.0 or fy < -1.0 or fx > nx or fy > ny:
                    continue
                cx, cy = int(fx), int(fy)
                best = np.inf
                for gy in range(max(cy - 1, 0), min(cy + 2, ny)):
                    for gx in range(max(cx - 1, 0), min(cx + 2, nx)):
                        c = gy * nx + gx
                        for e in range(start[c], start[c + 1]):
                            k = order[e]
                            dx = points[i, 0] - curve[k, 0]
                            dy = points[i, 1] - curve[k, 1]
                            best = min(best, dx * dx + dy * dy)
                out[i] = best
            return out

        _COMPILED.update(viterbi_forward=viterbi_forward, viterbi_backward=viterbi_backward,
                         sample_bilinear=sample_bilinear, cover_cells=cover_cells,
                         frangi_at=frangi_at, pixel_graph=pixel_graph, induced_subgraph=induced_subgraph,
                         graph_components=graph_components, dijkstra=dijkstra, walk_predecessors=walk_predecessors,
                         zhang_suen=zhang_suen, nearest_sq_dist=nearest_sq_dist)
        return _COMPILED


def viterbi_forward(acc0: np.ndarray, U: np.ndarray, C: np.ndarray, skip_cost: float):
    """Min-sum forward pass of the reconstruction's Viterbi with an early end.

    Parameters
    ----------
    acc0 : (K,) ndarray of float
        Cost of each candidate of the first anchor.
    U : (A, K) ndarray of float
        Unary costs (``inf`` where there is no candidate).
    C : (A - 1, K, K) ndarray of float
        Pairwise costs of step ``t``: candidate ``i`` of anchor ``t`` to ``j`` of anchor ``t + 1``.
    skip_cost : float
        Cost per anchor left unexplained when the path ends early.

    Returns
    -------
    alpha : (A, K) forward costs; back : (A - 1, K) int64 back-pointers (first minimum on ties,
    as ``numpy.argmin``); end_t, end_k : the best end; end_cost : its cost with the skipped anchors.
    """
    f = _compile()["viterbi_forward"]
    return f(np.ascontiguousarray(acc0, np.float64), np.ascontiguousarray(U, np.float64),
             np.ascontiguousarray(C, np.float64), float(skip_cost))


def viterbi_backward(C: np.ndarray, U: np.ndarray, end_t: int) -> np.ndarray:
    """Backward min-sum costs ``beta (end_t + 1, K)`` of the path ending at anchor ``end_t``:
    ``beta[t, i] = min_j C[t, i, j] + (U[t + 1, j] + beta[t + 1, j])``, ``beta[end_t] = 0``."""
    f = _compile()["viterbi_backward"]
    return f(np.ascontiguousarray(C, np.float64), np.ascontiguousarray(U, np.float64), int(end_t))


def sample_bilinear(image: np.ndarray, rows, cols, *, mode: str = "nearest", cval: float = 0.0) -> np.ndarray:
    """Bilinear samples of a 2D image at (row, col) points: ``scipy.ndimage.map_coordinates(image,
    [rows, cols], order=1, mode=mode, cval=cval)`` for ``mode`` "nearest" (coordinates clamped to
    the image) or "constant" (``cval`` outside ``[0, H - 1] x [0, W - 1]``), as float64.

    Parameters
    ----------
    image : (H, W) ndarray of a real or bool dtype (sampled without a float copy of the image)
    rows, cols : array_like of float, same shape
    """
    if mode not in ("nearest", "constant"):
        raise ValueError(f"sample_bilinear: mode must be 'nearest' or 'constant', got {mode!r}")
    img = np.asarray(image)
    if img.dtype == bool:
        img = img.view(np.uint8)
    elif img.dtype not in _DIRECT:
        img = img.astype(np.float64)
    r = np.asarray(rows, np.float64)
    shape = r.shape
    f = _compile()["sample_bilinear"]
    out = f(np.ascontiguousarray(img), np.ascontiguousarray(r.ravel()),
            np.ascontiguousarray(np.asarray(cols, np.float64).ravel()), mode == "nearest", float(cval))
    return out.reshape(shape)


def cover_cells(cells: np.ndarray, cell_px: int, context_px: int, call_cost_px: int) -> np.ndarray:
    """Boxes ``(i0, i1, j0, j1)`` (cells, end-exclusive; an (n, 4) int64 array) covering every True
    cell of ``cells`` at a low network cost; see :func:`guidewire3d.xray.segmentation.cover_boxes`.

    From the bounding box of the True cells, a box is split in two (across its rows, or across its
    columns: the cheaper; rows on a tie), each part shrunk to the cells it holds, at the cut that
    lowers ``sum((h cell_px + 2 context_px)(w cell_px + 2 context_px) + call_cost_px)`` most, and
    recursively, until no cut lowers it.
    """
    f = _compile()["cover_cells"]
    return f(np.ascontiguousarray(cells, np.bool_), int(cell_px), 2 * int(context_px), int(call_cost_px))


def frangi_at(image_zyx: np.ndarray, idx_zyx: np.ndarray, spacing: np.ndarray, sigma_mm: float, *,
              alpha: float, beta: float, gamma: float) -> np.ndarray:
    """Frangi's vesselness of bright tubes (float32, 0 where the two largest-magnitude eigenvalues
    are not both negative) at the voxels ``idx_zyx`` (K, 3) of a smoothed image, from its Hessian by
    the stencils of :func:`guidewire3d.cta.grid.derivs_at` times ``sigma_mm ** 2`` (float64), whose
    eigenvalues come in closed form (the trigonometric method) instead of LAPACK: the loop of
    :func:`guidewire3d.cta.segment.frangi_at` over one scale, in one pass. Voxels must be at least 1
    from the border.
    """
    f = _compile()["frangi_at"]
    img = np.asarray(image_zyx)
    if img.dtype not in (np.dtype(np.float32), np.dtype(np.float64)):
        img = img.astype(np.float64)
    return f(np.ascontiguousarray(img), np.ascontiguousarray(idx_zyx, np.int64),
             np.ascontiguousarray(spacing, np.float64), float(sigma_mm) ** 2, float(alpha), float(beta), float(gamma))


def _zhang_suen_lut() -> np.ndarray:
    """Zhang-Suen removal classes of the 256 neighbourhoods of a pixel (bit ``i`` of the code: the
    neighbour ``i`` clockwise from the upper left; 1: removed in the first sub-iteration, 2: in the
    second, 3: in both, 0: kept): scikit-image's table (``skimage.morphology.skeletonize``, method
    "zhang"), which refines the paper's conditions; identified from its output and checked against
    it (tests/test_kernels.py)."""
    lut = np.zeros(256, np.uint8)
    lut[[3, 6, 11, 12, 14, 131, 134, 143, 159, 161, 194, 198, 207, 227, 231, 243]] = 1
    lut[[24, 26, 56, 62, 63, 96, 104, 108, 126, 176, 192, 224, 248, 249, 252]] = 2
    lut[[7, 10, 15, 28, 30, 31, 40, 60, 112, 120, 124, 130, 135, 160, 193, 195, 199, 225, 240, 241]] = 3
    lut.setflags(write=False)
    return lut


_ZHANG_SUEN_LUT = _zhang_suen_lut()


def skeleton_pixels(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Zhang-Suen thinning of a 2D mask, as ``skimage.morphology.skeletonize(mask)`` (to the pixel):
    the skeleton's pixels ``(rows, cols)`` in row-major order (``np.nonzero`` of the skeleton) and
    the number of pixels of the mask.

    The same parallel sub-iterations as scikit-image, but over the list of remaining foreground
    pixels instead of the whole image: the cost scales with the mask's area, not its bounding box.
    """
    m = np.asarray(mask)
    if m.ndim != 2:
        raise ValueError(f"skeleton_pixels: expected a 2D mask, got shape {m.shape}")
    if m.dtype == bool:
        m = m.view(np.uint8)
    elif m.dtype != np.uint8:
        m = (m != 0).view(np.uint8)
    f = _compile()["zhang_suen"]
    rows, cols, n_on = f(np.ascontiguousarray(m), _ZHANG_SUEN_LUT)
    return rows, cols, int(n_on)


def nearest_sq_dist(points, curve, radius: float) -> np.ndarray:
    """Squared Euclidean distance ``(N,)`` from each of ``points (N, 2)`` to the nearest of
    ``curve (M, 2)`` (``dx * dx + dy * dy``, as ``scipy.spatial.cKDTree`` sums it), exact for
    every point within ``radius`` of the curve; farther points get a distance > ``radius ** 2``
    (``inf`` when no curve point is within about 2 ``radius``). A grid of cells of about ``radius``
    instead of a tree: for a few hundred points, no build cost."""
    f = _compile()["nearest_sq_dist"]
    return f(np.ascontiguousarray(points, np.float64).reshape(-1, 2),
             np.ascontiguousarray(curve, np.float64).reshape(-1, 2), float(radius) + 1.0)


def pixel_graph(rows, cols, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """8-connected graph of pixels as CSR arrays ``(indptr, indices, weights_px)``: node ``k`` is pixel
    ``(rows[k], cols[k])``, its neighbours sorted by node index (as scipy's ``coo_matrix(...).tocsr()``
    of the same edges), edge lengths 1 or sqrt 2 px. Pixels must be distinct and inside ``shape``."""
    f = _compile()["pixel_graph"]
    return f(np.ascontiguousarray(rows, np.int64), np.ascontiguousarray(cols, np.int64),
             int(shape[0]), int(shape[1]), float(np.hypot(1.0, 1.0)))


def induced_subgraph(indptr: np.ndarray, indices: np.ndarray, weights: np.ndarray,
                     nodes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CSR arrays of the subgraph on ``nodes`` (sorted, distinct), renumbered ``0 .. len(nodes) - 1``:
    scipy's ``g[nodes][:, nodes]``."""
    f = _compile()["induced_subgraph"]
    return f(indptr, indices, weights, np.ascontiguousarray(nodes, np.int64))


def graph_components(indptr: np.ndarray, indices: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of a symmetric CSR graph: ``(n, labels)``, numbered in the order of
    their lowest node, as ``scipy.sparse.csgraph.connected_components(g, directed=False)``."""
    f = _compile()["graph_components"]
    n, labels = f(indptr, indices)
    return int(n), labels


def dijkstra(indptr: np.ndarray, indices: np.ndarray, weights: np.ndarray,
             sources) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shortest distances from the nearest of ``sources`` in a symmetric CSR graph with positive
    weights: ``(dist, pred, tie)``. ``dist`` (``inf`` where unreachable) is that of
    ``scipy.sparse.csgraph.dijkstra(g, directed=False, indices=sources, min_only=True)``, to the
    last bit (each distance is the same sum in the same order); ``pred`` is the predecessor
    (-9999 at the sources and where unreachable), which is scipy's wherever ``tie`` is False;
    ``tie`` marks the nodes reached at the same distance from two predecessors (where scipy's
    choice depends on its heap)."""
    f = _compile()["dijkstra"]
    return f(indptr, indices, weights, np.atleast_1d(np.asarray(sources, np.int64)))


def diameter_path(indptr: np.ndarray, indices: np.ndarray, weights: np.ndarray,
                  node0: int) -> tuple[np.ndarray, float, bool]:
    """Double Dijkstra from ``node0``: the farthest node ``a`` of its component, then the farthest
    ``b`` from ``a`` (the first on ties, as ``numpy.argmax``); returns the node path ``a -> b``, its
    length and ``ambiguous``: True when a node on the path has two predecessors at the same
    distance (scipy's path may then differ; see :func:`dijkstra`). Two calls of the
    :func:`dijkstra` kernel (a jitted function here never calls another: numba's disk cache
    misses for a closure that holds another dispatcher)."""
    d0, _, _ = dijkstra(indptr, indices, weights, [node0])
    a = int(np.argmax(np.where(np.isfinite(d0), d0, -1.0)))
    d1, pred, tie = dijkstra(indptr, indices, weights, [a])
    b = int(np.argmax(np.where(np.isfinite(d1), d1, -1.0)))
    seq, ambiguous = _compile()["walk_predecessors"](pred, tie, b)
    return seq, float(d1[b]), bool(ambiguous)

def warm_up() -> None:
    """Compile (or load from the disk cache) every kernel on tiny inputs: the first live frame then
    pays no compilation."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numba's cache-locator notes on a read-only install
        U = np.zeros((3, 2))
        C = np.zeros((2, 2, 2))
        viterbi_forward(U[0], U, C, 1.0)
        viterbi_backward(C, U, 2)
        for dt in _WARM:  # the masks and the usual frame dtypes (others compile on first use)
            sample_bilinear(np.zeros((3, 3), dt), [0.5], [0.5], mode="nearest")
        cover_cells(np.eye(3, dtype=bool), 8, 8, 2000)
        g = pixel_graph([0, 0, 1], [0, 1, 1], (2, 2))
        sub = induced_subgraph(*g, [0, 1])
        graph_components(sub[0], sub[1])
        dijkstra(*g, [0])
        diameter_path(*g, 0)
        skeleton_pixels(np.eye(3, dtype=bool))
        nearest_sq_dist(np.zeros((1, 2)), np.ones((2, 2)), 1.0)
