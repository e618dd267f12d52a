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

The single-view 3D reconstruction's per-point and per-candidate loops (``_compile_reconstruction``:
the Viterbi pairwise costs, the placement on the tree path, the lumen covariance, the P-spline
system and fit, polyline tangents and curvature, the branch ambiguity) are compiled apart: each is
one call per frame instead of dozens of small numpy temporaries (tests/test_kernels_reconstruction.py
compares them with the numpy code they replaced). A jitted function here never calls another one
(numba's disk cache misses for a closure that holds another dispatcher).

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
           "diameter_path", "nearest_sq_dist", "warm_up", "dilate_ball", "ball_offsets", "skeleton_paths",
           "viterbi_pairwise", "place_on_path", "lumen_covariance", "pspline_system", "penalised_fit",
           "polyline_measures", "branch_ambiguity", "epipolar_candidates", "triangulate_dlt", "two_view_viterbi",
           "NearestGrid", "resample_polyline", "two_view_covariance", "best_line"]

_LOCK = threading.Lock()
#: image dtypes sampled as they are (one compiled specialisation each); others are converted to float64
_DIRECT = tuple(np.dtype(t) for t in (np.float64, np.float32, np.uint8, np.uint16, np.int16, np.int32, np.int64))
_WARM = (np.float64, np.float32, np.uint8, np.uint16)
_COMPILED: dict = {}


def _jit(f):
    """numba's ``njit`` (nogil), cached on disk beside the module or in the user's cache folder; with no
    writable cache location, compiled in memory once per process."""
    import numba

    try:
        return numba.njit(cache=True, nogil=True)(f)
    except RuntimeError:
        return numba.njit(cache=False, nogil=True)(f)


def _compile():
    """The jitted functions (compiled once per process; loaded from numba's disk cache when present)."""
    with _LOCK:
        if _COMPILED:
            return _COMPILED
        import heapq

        jit = _jit

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

        @jit
        def best_line(c, max_step):
            n_o, n = c.shape
            acc = c[:, 0].copy()
            nxt = np.empty(n_o)
            back = np.zeros((n_o, n), np.int64)
            for i in range(1, n):
                for o in range(n_o):
                    best = -np.inf
                    arg = o
                    for src in range(min(o + max_step, n_o - 1), max(o - max_step, 0) - 1, -1):
                        if acc[src] > best:            # the first largest, from the highest row down
                            best = acc[src]
                            arg = src
                    nxt[o] = best + c[o, i]
                    back[o, i] = arg
                acc[:] = nxt
            k = 0
            for o in range(1, n_o):
                if acc[o] > acc[k]:
                    k = o
            line = np.empty(n, np.int64)
            line[n - 1] = k
            for i in range(n - 1, 0, -1):
                line[i - 1] = back[line[i], i]
            return acc[k], line

        _COMPILED.update(viterbi_forward=viterbi_forward, viterbi_backward=viterbi_backward,
                         sample_bilinear=sample_bilinear, cover_cells=cover_cells,
                         pixel_graph=pixel_graph, induced_subgraph=induced_subgraph,
                         graph_components=graph_components, dijkstra=dijkstra, walk_predecessors=walk_predecessors,
                         zhang_suen=zhang_suen, nearest_sq_dist=nearest_sq_dist, best_line=best_line)
        return _COMPILED


#: the reconstruction's kernels (``guidewire3d.reconstruction``), compiled apart from the others
_COMPILED_RECON: dict = {}


def _compile_reconstruction():
    """The jitted kernels of the single-view reconstruction (one frame's path, placement, smoothing
    and covariance), compiled once per process (loaded from numba's disk cache when present)."""
    with _LOCK:
        if _COMPILED_RECON:
            return _COMPILED_RECON
        jit = _jit

        @jit
        def viterbi_pairwise(cand, s, point_branch, branch_lca_s, points, uv_tree, uv_anchor, ss2, sj, sr):
            A, K = cand.shape
            C = np.empty((max(A - 1, 0), K, K))
            # the candidates' data gathered once, one contiguous row per anchor
            cs = np.empty((A, K))
            cb = np.empty((A, K), np.int64)
            X0, X1, X2 = np.empty((A, K)), np.empty((A, K)), np.empty((A, K))
            V0, V1 = np.empty((A, K)), np.empty((A, K))
            n2 = np.empty((A, K))
            u2 = np.empty((A, K))
            for a in range(A):
                for k in range(K):
                    c = cand[a, k]
                    cs[a, k], cb[a, k] = s[c], point_branch[c]
                    X0[a, k], X1[a, k], X2[a, k] = points[c, 0], points[c, 1], points[c, 2]
                    V0[a, k], V1[a, k] = uv_tree[c, 0], uv_tree[c, 1]
                    n2[a, k] = X0[a, k] * X0[a, k] + X1[a, k] * X1[a, k] + X2[a, k] * X2[a, k]
                    u2[a, k] = V0[a, k] * V0[a, k] + V1[a, k] * V1[a, k]
            a0, a1, a2 = np.empty(K), np.empty(K), np.empty(K)
            lrow = np.empty(K)
            for t in range(A - 1):
                du = uv_anchor[t + 1, 0] - uv_anchor[t, 0]
                dv = uv_anchor[t + 1, 1] - uv_anchor[t, 1]
                for j in range(K):
                    a0[j] = V0[t + 1, j] - du
                    a1[j] = V1[t + 1, j] - dv
                    a2[j] = a0[j] * a0[j] + a1[j] * a1[j]
                for i in range(K):
                    si = cs[t, i]
                    bi = cb[t, i]
                    for j in range(K):
                        lrow[j] = branch_lca_s[bi, cb[t + 1, j]]
                    x0, x1, x2 = 2.0 * X0[t, i], 2.0 * X1[t, i], 2.0 * X2[t, i]
                    w0, w1 = 2.0 * V0[t, i], 2.0 * V1[t, i]
                    n2i, u2i = n2[t, i], u2[t, i]
                    Ct = C[t, i]
                    for j in range(K):
                        sj_ = cs[t + 1, j]
                        slca = min(min(si, sj_), lrow[j])
                        up = si - slca
                        geo = up + (sj_ - slca)
                        dot = x0 * X0[t + 1, j] + x1 * X1[t + 1, j] + x2 * X2[t + 1, j]
                        e3 = np.sqrt(max(n2i + n2[t + 1, j] - dot, 0.0))
                        m2 = u2i + a2[j] - (w0 * a0[j] + w1 * a1[j])
                        Ct[j] = 2.0 * (np.sqrt(1.0 + max(m2, 0.0) / ss2) - 1.0) + max(geo - e3, 0.0) / sj + up / sr
            return C

        @jit
        def place_on_path(o, d, P, points, radius, offset, lo, lim, width, pos, dist_scale, along_scale):
            S = P.shape[0] - 1
            M = d.shape[0]
            # per segment (structure of arrays): e = B - A, w0 = A - o, c = e.e, q = e.w0, w2 = w0.w0
            e0, e1, e2 = np.empty(S), np.empty(S), np.empty(S)
            f0, f1, f2 = np.empty(S), np.empty(S), np.empty(S)
            c, q, w2, seg_len = np.empty(S), np.empty(S), np.empty(S), np.empty(S)
            for g in range(S):
                ia, ib = P[g], P[g + 1]
                e0[g], e1[g], e2[g] = points[ib, 0] - points[ia, 0], points[ib, 1] - points[ia, 1], \
                    points[ib, 2] - points[ia, 2]
                f0[g], f1[g], f2[g] = points[ia, 0] - o[0], points[ia, 1] - o[1], points[ia, 2] - o[2]
                c[g] = e0[g] * e0[g] + e1[g] * e1[g] + e2[g] * e2[g]
                q[g] = e0[g] * f0[g] + e1[g] * f1[g] + e2[g] * f2[g]
                w2[g] = f0[g] * f0[g] + f1[g] * f1[g] + f2[g] * f2[g]
                seg_len[g] = np.sqrt(c[g])
            X = np.empty((M, 3))
            tid = np.empty(M, np.int64)
            out_dist, out_half, out_r = np.empty(M), np.empty(M), np.empty(M)
            cost = np.empty(width)
            # each window segment's closest approach, kept for the chosen one
            cb, cu, cs, cdist = np.empty(width), np.empty(width), np.empty(width), np.empty(width)
            for m in range(M):
                d0, d1, d2 = d[m, 0], d[m, 1], d[m, 2]
                for w in range(width):
                    inside = lo[m] + w < lim[m]
                    if not inside and w > 0:
                        cost[w] = np.inf  # outside the ray's window (segment 0 is the fallback choice)
                        continue
                    g = min(lo[m] + w, S - 1)
                    b = e0[g] * d0 + e1[g] * d1 + e2[g] * d2
                    p = f0[g] * d0 + f1[g] * d1 + f2[g] * d2
                    den = c[g] - b * b
                    u = (p * b - q[g]) / den if den > 1e-12 else 0.5
                    u = min(max(u, 0.0), 1.0)
                    s_ = p + u * b
                    dist = np.sqrt(max(s_ * s_ - 2 * s_ * u * b - 2 * s_ * p + u * u * c[g] + 2 * u * q[g] + w2[g], 0.0))
                    cb[w], cu[w], cs[w], cdist[w] = b, u, s_, dist
                    if not inside:
                        cost[w] = np.inf
                        continue
                    along = (g + u - pos[m]) * seg_len[g]
                    cost[w] = (dist / dist_scale) ** 2 + (along / along_scale) ** 2
                # the first minimum (numpy.argmin: a NaN wins, the first segment when none counts)
                bw = 0
                for w in range(1, width):
                    if cost[bw] != cost[bw]:
                        break
                    if cost[w] < cost[bw] or cost[w] != cost[w]:
                        bw = w
                g = min(lo[m] + bw, S - 1)
                b, u, s_, dist = cb[bw], cu[bw], cs[bw], cdist[bw]
                ia, ib = P[g], P[g + 1]
                r = radius[ia] + u * (radius[ib] - radius[ia])
                sin2 = min(max(1.0 - b * b / max(c[g], 1e-24), 1e-6), 1.0)
                half = min(np.sqrt(max(r * r - dist * dist, 0.0) / sin2), 0.5 * abs(b) + r)
                # within the chord, the depth of the expected wire position Y
                sy = 0.0
                for k in range(3):
                    off = offset[ia, k] + u * (offset[ib, k] - offset[ia, k])
                    y = points[ia, k] + u * (points[ib, k] - points[ia, k]) + off
                    sy += (y - o[k]) * d[m, k]
                sy = min(max(sy, s_ - half), s_ + half)
                for k in range(3):
                    X[m, k] = o[k] + sy * d[m, k]
                tid[m] = ia if u < 0.5 else ib
                out_dist[m], out_half[m], out_r[m] = dist, half, r
            return X, tid, out_half, out_dist, out_r

        @jit
        def lumen_covariance(d, t, X, Rc, tc, focal, R, tp, sg2, g, si2, has_img, C, has_reg, hw, miss, amb,
                             has_amb, k2, spread, scl2):
            M = d.shape[0]
            cov = np.empty((M, 3, 3))
            n = np.empty(3)
            tt = np.empty(3)
            q = np.empty(3)
            mv = np.empty(3)
            J = np.empty((2, 3))
            Jn = np.empty(2)
            Jm = np.empty(2)
            bn = np.empty(6)
            bm = np.empty(6)
            xr = np.empty(3)
            vn = np.empty(3)
            vm = np.empty(3)
            for i in range(M):
                d0, d1, d2 = d[i, 0], d[i, 1], d[i, 2]
                n[0] = d1 * t[i, 2] - d2 * t[i, 1]
                n[1] = d2 * t[i, 0] - d0 * t[i, 2]
                n[2] = d0 * t[i, 1] - d1 * t[i, 0]
                sin = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
                tt[0], tt[1], tt[2] = t[i, 0], t[i, 1], t[i, 2]
                if sin <= 1e-6:  # a ray (nearly) along the vessel: any direction normal to the ray
                    if abs(d0) < 0.9:
                        n[0], n[1], n[2] = 0.0, d2, -d1
                    else:
                        n[0], n[1], n[2] = -d2, 0.0, d0
                nn = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
                n[0], n[1], n[2] = n[0] / nn, n[1] / nn, n[2] / nn
                if sin <= 1e-6:
                    tt[0] = n[1] * d2 - n[2] * d1
                    tt[1] = n[2] * d0 - n[0] * d2
                    tt[2] = n[0] * d1 - n[1] * d0
                cos = abs(d0 * tt[0] + d1 * tt[1] + d2 * tt[2])
                q[0] = tt[1] * n[2] - tt[2] * n[1]
                q[1] = tt[2] * n[0] - tt[0] * n[2]
                q[2] = tt[0] * n[1] - tt[1] * n[0]
                mv[0] = n[1] * d2 - n[2] * d1
                mv[1] = n[2] * d0 - n[0] * d2
                mv[2] = n[0] * d1 - n[1] * d0
                gain = cos / max(cos * cos + k2 * (sin * sin), 1e-12)
                # projection Jacobian J (2 x 3) and J+^T v = (J J^T)^-1 J v
                xc0 = X[i, 0] * Rc[0, 0] + X[i, 1] * Rc[0, 1] + X[i, 2] * Rc[0, 2] + tc[0]
                xc1 = X[i, 0] * Rc[1, 0] + X[i, 1] * Rc[1, 1] + X[i, 2] * Rc[1, 2] + tc[1]
                z = X[i, 0] * Rc[2, 0] + X[i, 1] * Rc[2, 1] + X[i, 2] * Rc[2, 2] + tc[2]
                fz = focal / z
                j02 = -focal * xc0 / z ** 2
                j12 = -focal * xc1 / z ** 2
                for k in range(3):
                    J[0, k] = fz * Rc[0, k] + j02 * Rc[2, k]
                    J[1, k] = fz * Rc[1, k] + j12 * Rc[2, k]
                a00 = J[0, 0] * J[0, 0] + J[0, 1] * J[0, 1] + J[0, 2] * J[0, 2]
                a01 = J[0, 0] * J[1, 0] + J[0, 1] * J[1, 1] + J[0, 2] * J[1, 2]
                a11 = J[1, 0] * J[1, 0] + J[1, 1] * J[1, 1] + J[1, 2] * J[1, 2]
                det = a00 * a11 - a01 * a01
                jn0 = J[0, 0] * n[0] + J[0, 1] * n[1] + J[0, 2] * n[2]
                jn1 = J[1, 0] * n[0] + J[1, 1] * n[1] + J[1, 2] * n[2]
                jm0 = J[0, 0] * mv[0] + J[0, 1] * mv[1] + J[0, 2] * mv[2]
                jm1 = J[1, 0] * mv[0] + J[1, 1] * mv[1] + J[1, 2] * mv[2]
                Jn[0] = (a11 * jn0 - a01 * jn1) / det
                Jn[1] = (-a01 * jn0 + a00 * jn1) / det
                Jm[0] = (a11 * jm0 - a01 * jm1) / det
                Jm[1] = (-a01 * jm0 + a00 * jm1) / det
                s_nn = sg2 * (Jn[0] * Jn[0] + Jn[1] * Jn[1])
                s_nm = sg2 * (Jn[0] * Jm[0] + Jn[1] * Jm[1])
                s_mm = sg2 * (Jm[0] * Jm[0] + Jm[1] * Jm[1])
                if has_img:
                    gn = g[i, 0] * Jn[0] + g[i, 1] * Jn[1]
                    gm = g[i, 0] * Jm[0] + g[i, 1] * Jm[1]
                    s_nn = s_nn + si2 * gn * gn
                    s_nm = s_nm + si2 * gn * gm
                    s_mm = s_mm + si2 * gm * gm
                if has_reg:
                    # G = R^T [-I | [x]x]  =>  G^T v = -(R v, x x R v), x the point in room coordinates
                    for k in range(3):
                        xr[k] = X[i, 0] * R[k, 0] + X[i, 1] * R[k, 1] + X[i, 2] * R[k, 2] + tp[k]
                        vn[k] = n[0] * R[k, 0] + n[1] * R[k, 1] + n[2] * R[k, 2]
                        vm[k] = mv[0] * R[k, 0] + mv[1] * R[k, 1] + mv[2] * R[k, 2]
                    bn[0], bn[1], bn[2] = vn[0], vn[1], vn[2]
                    bn[3] = xr[1] * vn[2] - xr[2] * vn[1]
                    bn[4] = xr[2] * vn[0] - xr[0] * vn[2]
                    bn[5] = xr[0] * vn[1] - xr[1] * vn[0]
                    bm[0], bm[1], bm[2] = vm[0], vm[1], vm[2]
                    bm[3] = xr[1] * vm[2] - xr[2] * vm[1]
                    bm[4] = xr[2] * vm[0] - xr[0] * vm[2]
                    bm[5] = xr[0] * vm[1] - xr[1] * vm[0]
                    r_nn = 0.0
                    r_nm = 0.0
                    r_mm = 0.0
                    for a in range(6):
                        cbn = 0.0
                        cbm = 0.0
                        for b in range(6):
                            cbn += bn[b] * C[b, a]
                            cbm += bm[b] * C[b, a]
                        r_nn += cbn * bn[a]
                        r_nm += cbn * bm[a]
                        r_mm += cbm * bm[a]
                    s_nn = s_nn + r_nn
                    s_nm = s_nm + r_nm
                    s_mm = s_mm + r_mm
                miss2 = miss[i] * miss[i]
                aa = s_nn + miss2
                bb = gain * s_nm
                cc = gain * gain * s_mm + (spread * hw[i]) ** 2 + scl2 + miss2
                if has_amb:
                    an = 0.0
                    aq = 0.0
                    qq = 0.0
                    for r in range(3):
                        bnr = amb[i, r, 0] * n[0] + amb[i, r, 1] * n[1] + amb[i, r, 2] * n[2]
                        an += bnr * n[r]
                        aq += bnr * q[r]
                        qq += q[r] * (amb[i, r, 0] * q[0] + amb[i, r, 1] * q[1] + amb[i, r, 2] * q[2])
                    aa = aa + an
                    bb = bb + aq
                    cc = cc + qq
                for r in range(3):
                    for k in range(3):
                        cov[i, r, k] = aa * (n[r] * n[k]) + bb * (n[r] * q[k] + q[r] * n[k]) + cc * (q[r] * q[k])
            return cov

        @jit
        def pspline_system(x, t, wn, Y):
            k = 3
            M = x.shape[0]
            n = t.shape[0] - k - 1
            # the design matrix's rows: basis functions first[m] .. first[m] + 3 at x[m]
            D = np.empty((M, k + 1))
            first = np.empty(M, np.int64)
            h = np.empty(k + 1)
            hh = np.empty(k + 1)
            ell = k
            for m in range(M):
                xv = x[m]
                # the knot interval t[ell] <= x < t[ell + 1] (the last one closed), from the previous
                if not k < ell < n:
                    ell = k
                while xv < t[ell] and ell != k:
                    ell -= 1
                ell += 1
                while xv >= t[ell] and ell != n:
                    ell += 1
                ell -= 1
                # de Boor - Cox recursion (Dierckx's fpbspl)
                h[0] = 1.0
                for j in range(1, k + 1):
                    for i in range(j):
                        hh[i] = h[i]
                    h[0] = 0.0
                    for i in range(1, j + 1):
                        xb = t[ell + i]
                        xa = t[ell + i - j]
                        if xb == xa:
                            h[i] = 0.0
                            continue
                        w = hh[i - 1] / (xb - xa)
                        h[i - 1] += w * (xb - xv)
                        h[i] = w * (xv - xa)
                for i in range(k + 1):
                    D[m, i] = h[i]
                first[m] = ell - k
            # B^T W B (upper banded, ab[3 + i - j, j]) and B^T W Y, in numpy.bincount's order
            ab = np.zeros((k + 1, n))
            tmp = np.empty(n)
            for a in range(k + 1):
                for b in range(a, k + 1):
                    tmp[:] = 0.0
                    for m in range(M):
                        tmp[first[m] + b] += wn[m] * D[m, a] * D[m, b]
                    for j in range(n):
                        ab[k - (b - a), j] += tmp[j]
            nd = Y.shape[1]
            BtY = np.zeros((n, nd))
            for dd in range(nd):
                for m in range(M):
                    for a in range(k + 1):
                        BtY[first[m] + a, dd] += wn[m] * D[m, a] * Y[m, dd]
            return D, first, ab, BtY

        @jit
        def penalised_fit(D, first, ab_data, BtY, lam, uv, Rc, tc, focal, pp):
            # ab = B^T W B + lam / (nb - 2) D^T D (+ 1e-12 I), upper banded (4, nb), as smoothing.fit_pspline
            nb = ab_data.shape[1]
            ab = ab_data.copy()
            w = lam / max(nb - 2, 1)
            if nb >= 3:
                for j in range(nb):
                    p0 = 6.0
                    if j == 0 or j == nb - 1:
                        p0 = 1.0
                    elif j == 1 or j == nb - 2:
                        p0 = 5.0
                    ab[3, j] += w * p0
                for j in range(1, nb):
                    ab[2, j] += w * (-2.0 if (j - 1 == 0 or j - 1 == nb - 2) else -4.0)
                for j in range(2, nb):
                    ab[1, j] += w * 1.0
            for j in range(nb):
                ab[3, j] += 1e-12
            # banded Cholesky U^T U (LAPACK dpbtf2's order); not positive definite: NaN
            kd = 3
            M, nd = D.shape[0], BtY.shape[1]
            for j in range(nb):
                ajj = ab[kd, j]
                if not ajj > 0.0:
                    return np.full((M, nd), np.nan), np.nan, np.nan
                ajj = np.sqrt(ajj)
                ab[kd, j] = ajj
                kn = min(kd, nb - 1 - j)
                for i in range(1, kn + 1):
                    ab[kd - i, j + i] /= ajj
                for i in range(1, kn + 1):
                    ui = ab[kd - i, j + i]
                    for l in range(i, kn + 1):
                        ab[kd - (l - i), j + l] -= ui * ab[kd - l, j + l]
            coef = BtY.copy()
            for dd in range(nd):
                for j in range(nb):  # U^T y = b
                    v = coef[j, dd]
                    for i in range(max(0, j - kd), j):
                        v -= ab[kd + i - j, j] * coef[i, dd]
                    coef[j, dd] = v / ab[kd, j]
                for j in range(nb - 1, -1, -1):  # U x = y
                    v = coef[j, dd]
                    for i in range(j + 1, min(nb, j + kd + 1)):
                        v -= ab[kd + j - i, i] * coef[i, dd]
                    coef[j, dd] = v / ab[kd, j]
            # the fitted points B coef (scipy's CSR product order) and their projection error
            Xs = np.zeros((M, nd))
            for m in range(M):
                for a in range(4):
                    for dd in range(nd):
                        Xs[m, dd] += D[m, a] * coef[first[m] + a, dd]
            tot = 0.0
            worst = 0.0
            nan = False
            for m in range(M):
                xc0 = Xs[m, 0] * Rc[0, 0] + Xs[m, 1] * Rc[0, 1] + Xs[m, 2] * Rc[0, 2] + tc[0]
                xc1 = Xs[m, 0] * Rc[1, 0] + Xs[m, 1] * Rc[1, 1] + Xs[m, 2] * Rc[1, 2] + tc[1]
                z = Xs[m, 0] * Rc[2, 0] + Xs[m, 1] * Rc[2, 1] + Xs[m, 2] * Rc[2, 2] + tc[2]
                du = focal * xc0 / z + pp[0] - uv[m, 0]
                dv = focal * xc1 / z + pp[1] - uv[m, 1]
                e = np.sqrt(du * du + dv * dv)
                tot += e
                if np.isnan(e):
                    nan = True
                elif e > worst:
                    worst = e
            return Xs, tot / M, np.nan if nan else worst

        @jit
        def polyline_measures(X):
            n = X.shape[0]
            G = np.empty((3, n, 3))  # X, X' and X'' (numpy.gradient: central inside, one-sided at the ends)
            G[0] = X
            for lev in range(2):
                for c in range(3):
                    G[lev + 1, 0, c] = G[lev, 1, c] - G[lev, 0, c]
                    G[lev + 1, n - 1, c] = G[lev, n - 1, c] - G[lev, n - 2, c]
                    for i in range(1, n - 1):
                        G[lev + 1, i, c] = (G[lev, i + 1, c] - G[lev, i - 1, c]) / 2.0
            T = np.empty((n, 3))
            kappa = np.empty(n)
            for i in range(n):
                a0, a1, a2 = G[1, i, 0], G[1, i, 1], G[1, i, 2]
                b0, b1, b2 = G[2, i, 0], G[2, i, 1], G[2, i, 2]
                nd = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
                sc = max(nd, 1e-12)
                T[i, 0], T[i, 1], T[i, 2] = a0 / sc, a1 / sc, a2 / sc
                c0 = a1 * b2 - a2 * b1
                c1 = a2 * b0 - a0 * b2
                c2 = a0 * b1 - a1 * b0
                kappa[i] = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2) / max(nd ** 3.0, 1e-12)
            return T, kappa

        @jit
        def branch_ambiguity(cand, excess, nodes, points, s, point_branch, branch_lca_s, scale, sigma_jump):
            A, K = cand.shape
            out = np.zeros((A, 3, 3))
            w = np.empty(K)
            for a in range(A):
                nd = nodes[a]
                tot = 0.0
                for k in range(K):
                    ok = cand[a, k] >= 0 and np.isfinite(excess[a, k])
                    w[k] = np.exp(-excess[a, k] / scale) if ok else 0.0
                    tot += w[k]
                tot = max(tot, 1e-300)
                for k in range(K):
                    c = max(cand[a, k], 0)
                    D0 = points[c, 0] - points[nd, 0]
                    D1 = points[c, 1] - points[nd, 1]
                    D2 = points[c, 2] - points[nd, 2]
                    lca = min(min(s[c], s[nd]), branch_lca_s[point_branch[c], point_branch[nd]])
                    geo = s[c] + s[nd] - 2.0 * lca
                    if not geo - np.sqrt(D0 * D0 + D1 * D1 + D2 * D2) > sigma_jump:
                        continue  # the same hypothesis moved along the vessel: no displacement
                    wk = w[k] / tot
                    out[a, 0, 0] += wk * D0 * D0
                    out[a, 0, 1] += wk * D0 * D1
                    out[a, 0, 2] += wk * D0 * D2
                    out[a, 1, 1] += wk * D1 * D1
                    out[a, 1, 2] += wk * D1 * D2
                    out[a, 2, 2] += wk * D2 * D2
                out[a, 1, 0] = out[a, 0, 1]
                out[a, 2, 0] = out[a, 0, 2]
                out[a, 2, 1] = out[a, 1, 2]
            return out

        _COMPILED_RECON.update(viterbi_pairwise=viterbi_pairwise, place_on_path=place_on_path,
                               lumen_covariance=lumen_covariance, pspline_system=pspline_system,
                               penalised_fit=penalised_fit, polyline_measures=polyline_measures,
                               branch_ambiguity=branch_ambiguity)
        return _COMPILED_RECON


#: the two-view triangulation's kernels (``guidewire3d.reconstruction.triangulation``), compiled apart
_COMPILED_TRI: dict = {}


def _compile_triangulation():
    """The jitted kernels of the two-view (biplane) wire: the epipolar candidates, their
    triangulation, the Viterbi over the master plane's samples and the nearest-point queries,
    compiled once per process (loaded from numba's disk cache when present)."""
    with _LOCK:
        if _COMPILED_TRI:
            return _COMPILED_TRI
        jit = _jit

        @jit
        def epipolar_candidates(F, a, b, touch):
            n, m = a.shape[0], b.shape[0]
            lines = np.empty((n, 3))
            for i in range(n):
                for r in range(3):
                    lines[i, r] = a[i, 0] * F[r, 0] + a[i, 1] * F[r, 1] + F[r, 2]
                nr = max(np.sqrt(lines[i, 0] * lines[i, 0] + lines[i, 1] * lines[i, 1]), 1e-12)
                for r in range(3):
                    lines[i, r] /= nr
            cap = n * max(m - 1, 0)
            c_i = np.empty(cap, np.int64)
            c_j = np.empty(cap)
            t_i = np.empty(n * max(m - 2, 0), np.int64)
            t_j = np.empty(n * max(m - 2, 0))
            nc = 0
            nt = 0
            d = np.empty(m)
            cross = np.empty(max(m - 1, 0), np.bool_)
            for i in range(n):
                l0, l1, l2 = lines[i, 0], lines[i, 1], lines[i, 2]
                for jj in range(m):
                    d[jj] = (l0 * b[jj, 0] + l1 * b[jj, 1]) + l2
                for jj in range(m - 1):
                    cross[jj] = (d[jj] >= 0) != (d[jj + 1] >= 0)
                    if cross[jj]:
                        d0, d1 = d[jj], d[jj + 1]
                        den = d0 - d1
                        frac = d0 / (den if abs(den) > 1e-12 else 1.0)
                        c_i[nc] = i
                        c_j[nc] = jj + min(max(frac, 0.0), 1.0)
                        nc += 1
                if m >= 3:
                    for jj in range(1, m - 1):
                        v = abs(d[jj])
                        if (v <= abs(d[jj - 1]) and v <= abs(d[jj + 1]) and v < touch
                                and not cross[jj - 1] and not cross[jj]):
                            t_i[nt] = i
                            t_j[nt] = float(jj)
                            nt += 1
            N = nc + nt
            ia = np.empty(N, np.int64)
            jo = np.empty(N)
            ia[:nc] = c_i[:nc]
            jo[:nc] = c_j[:nc]
            ia[nc:] = t_i[:nt]
            jo[nc:] = t_j[:nt]
            # b's unit tangents (numpy.gradient: one-sided at the ends)
            tb = np.empty((m, 2))
            for jj in range(m):
                if m == 1:
                    tb[jj, 0] = 0.0
                    tb[jj, 1] = 0.0
                elif jj == 0:
                    tb[jj, 0] = b[1, 0] - b[0, 0]
                    tb[jj, 1] = b[1, 1] - b[0, 1]
                elif jj == m - 1:
                    tb[jj, 0] = b[m - 1, 0] - b[m - 2, 0]
                    tb[jj, 1] = b[m - 1, 1] - b[m - 2, 1]
                else:
                    tb[jj, 0] = (b[jj + 1, 0] - b[jj - 1, 0]) / 2.0
                    tb[jj, 1] = (b[jj + 1, 1] - b[jj - 1, 1]) / 2.0
                nr = max(np.sqrt(tb[jj, 0] * tb[jj, 0] + tb[jj, 1] * tb[jj, 1]), 1e-12)
                tb[jj, 0] /= nr
                tb[jj, 1] /= nr
            sin = np.empty(N)
            for q in range(N):
                jr = min(max(int(np.rint(jo[q])), 0), m - 1)
                i = ia[q]
                sin[q] = abs(tb[jr, 0] * lines[i, 0] + tb[jr, 1] * lines[i, 1])
            return ia, jo, sin

        @jit
        def triangulate_dlt(ua, ub, Pa, Pb):
            N = ua.shape[0]
            out = np.empty((N, 3))
            A = np.empty((4, 4))
            M = np.empty((3, 4))
            for n in range(N):
                for r in range(4):
                    P = Pa if r < 2 else Pb
                    u = ua[n, r] if r < 2 else ub[n, r - 2]
                    row = r % 2
                    for c in range(4):
                        A[r, c] = u * P[2, c] - P[row, c]
                    nr = np.sqrt(A[r, 0] * A[r, 0] + A[r, 1] * A[r, 1] + A[r, 2] * A[r, 2])
                    for c in range(4):
                        A[r, c] /= nr
                # normal equations [MtM | Mtr] (3 x 4), solved by Gaussian elimination with partial pivoting
                for i in range(3):
                    for j in range(3):
                        s = 0.0
                        for k in range(4):
                            s += A[k, i] * A[k, j]
                        M[i, j] = s
                    s = 0.0
                    for k in range(4):
                        s += A[k, i] * -A[k, 3]
                    M[i, 3] = s
                for c in range(3):
                    p = c
                    for r in range(c + 1, 3):
                        if abs(M[r, c]) > abs(M[p, c]):
                            p = r
                    if p != c:
                        for q in range(4):
                            M[c, q], M[p, q] = M[p, q], M[c, q]
                    for r in range(c + 1, 3):
                        f = M[r, c] / M[c, c]
                        for q in range(c, 4):
                            M[r, q] -= f * M[c, q]
                for c in range(2, -1, -1):
                    s = M[c, 3]
                    for q in range(c + 1, 3):
                        s -= M[c, q] * out[n, q]
                    out[n, c] = s / M[c, c]
            return out

        @jit
        def two_view_viterbi(n, ia, jb, X, unary, step_mm, direction, K, G, dense_px, tol, sigma_step, back_px,
                             skip, px_other_mm, spread):
            INF = 1e18
            N = ia.shape[0]
            # per master sample its K most plausible candidates (lowest unary; stable: the lower index on ties)
            idx = -np.ones((n, K), np.int64)
            cnt = np.zeros(n, np.int64)
            for q in range(N):
                i = ia[q]
                c = cnt[i]
                # insertion into the sorted row (kept to K): after every equal or lower unary
                if c == K and not (unary[q] < unary[idx[i, K - 1]]):
                    continue
                p = min(c, K - 1)
                while p > 0 and unary[q] < unary[idx[i, p - 1]]:
                    if p < K:
                        idx[i, p] = idx[i, p - 1]
                    p -= 1
                idx[i, p] = q
                if c < K:
                    cnt[i] = c + 1
            Xp = np.full((n, K, 3), np.nan)
            jp = np.full((n, K), np.nan)
            U = np.full((n, K), INF)
            for i in range(n):
                for k in range(K):
                    q = idx[i, k]
                    if q >= 0:
                        Xp[i, k, 0], Xp[i, k, 1], Xp[i, k, 2] = X[q, 0], X[q, 1], X[q, 2]
                        jp[i, k] = jb[q]
                        U[i, k] = unary[q]
            # Tin[i, g - 1, j, k]: from candidate j of sample i - g to candidate k of sample i
            Tin = np.full((n, G, K, K), INF)
            ss2 = sigma_step * sigma_step
            for g in range(1, min(G, n - 1) + 1):
                m_mm = g * step_mm
                gap = (g - 1) * skip
                for i in range(g, n):
                    for j in range(K):
                        if idx[i - g, j] < 0:
                            continue
                        for k in range(K):
                            if idx[i, k] < 0:
                                continue
                            e0 = Xp[i - g, j, 0] - Xp[i, k, 0]
                            e1 = Xp[i - g, j, 1] - Xp[i, k, 1]
                            e2 = Xp[i - g, j, 2] - Xp[i, k, 2]
                            dX = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
                            dj = (jp[i, k] - jp[i - g, j]) * direction * dense_px
                            o_mm = abs(dj) * px_other_mm
                            over = max(dX - np.sqrt(m_mm ** 2 + o_mm ** 2) * spread - tol, 0.0)
                            jump = max(o_mm - dX - tol, 0.0)
                            if dj < -back_px:
                                pen = INF
                            else:
                                pen = (over ** 2 + jump ** 2) / ss2
                            if np.isfinite(pen):
                                Tin[i, g - 1, j, k] = pen + gap
            # forward pass (rows of cp: G rows of INF, then one per sample)
            cp = np.full((n + G, K), INF)
            for k in range(K):
                cp[G, k] = U[0, k]
            for i in range(1, n):
                for k in range(K):
                    best = np.inf
                    for gg in range(G):
                        r = i + G - 1 - gg
                        for j in range(K):
                            best = min(best, cp[r, j] + Tin[i, gg, j, k])
                    cp[i + G, k] = min(best, i * skip) + U[i, k]
            bi = 0
            bk = 0
            best = np.inf
            for i in range(n):
                for k in range(K):
                    v = cp[i + G, k] + (n - 1 - i) * skip
                    if v < best:
                        best, bi, bk = v, i, k
            chosen = -np.ones(n, np.int64)
            i, k = bi, bk
            while True:
                chosen[i] = idx[i, k]
                if i == 0:
                    break
                m = np.inf
                mg = 0
                mj = 0
                for gg in range(G):
                    r = i + G - 1 - gg
                    for j in range(K):
                        v = cp[r, j] + Tin[i, gg, j, k]
                        if v < m:
                            m, mg, mj = v, gg, j
                if i * skip <= m:
                    break
                k = mj
                i = i - 1 - mg
            return chosen, best

        @jit
        def grid_build(P, cell):
            N, D = P.shape
            lo = np.empty(D)
            dims = np.empty(D, np.int64)
            for d in range(D):
                lo[d] = P[0, d] if N else 0.0
                hi = lo[d]
                for p in range(N):
                    lo[d] = min(lo[d], P[p, d])
                    hi = max(hi, P[p, d])
                dims[d] = int((hi - lo[d]) / cell) + 1
            ncell = 1
            for d in range(D):
                ncell *= dims[d]
            cid = np.empty(N, np.int64)
            for p in range(N):
                c = 0
                for d in range(D):
                    c = c * dims[d] + min(int((P[p, d] - lo[d]) / cell), dims[d] - 1)
                cid[p] = c
            start = np.zeros(ncell + 1, np.int64)
            for p in range(N):
                start[cid[p] + 1] += 1
            for c in range(ncell):
                start[c + 1] += start[c]
            fill = start[:-1].copy()
            order = np.empty(N, np.int64)
            for p in range(N):  # within a cell, by point index
                order[fill[cid[p]]] = p
                fill[cid[p]] += 1
            return lo, dims, start, order

        @jit
        def grid_nearest(P, lo, dims, start, order, cell, Q):
            D = P.shape[1]
            M = Q.shape[0]
            dist = np.empty(M)
            nearest = np.empty(M, np.int64)
            cq = np.empty(D, np.int64)
            cmin = np.empty(D, np.int64)
            cmax = np.empty(D, np.int64)
            nmax = 0
            for d in range(D):
                nmax = max(nmax, dims[d])
            for q in range(M):
                for d in range(D):
                    cq[d] = int(np.floor((Q[q, d] - lo[d]) / cell))
                best2 = np.inf
                bp = -1
                ring_max = 0
                for d in range(D):
                    ring_max = max(ring_max, abs(cq[d]), abs(dims[d] - 1 - cq[d]))
                # shells of cells around the query's (Chebyshev distance ``ring``), until no unseen cell
                # can hold a nearer point: a cell ``ring`` away is at least ``(ring - 1) cell`` away
                for ring in range(ring_max + 1):
                    if bp >= 0 and ring >= 1:
                        # the distance from the query to the cells not yet seen: outside the box of
                        # the shells 0 .. ring - 1
                        gap = np.inf
                        for d in range(D):
                            gap = min(gap, Q[q, d] - (lo[d] + (cq[d] - ring + 1) * cell),
                                      (lo[d] + (cq[d] + ring) * cell) - Q[q, d])
                        if gap > 0.0 and gap * gap > best2:
                            break
                    empty = False
                    for d in range(D):
                        cmin[d] = max(cq[d] - ring, 0)
                        cmax[d] = min(cq[d] + ring, dims[d] - 1)
                        if cmin[d] > cmax[d]:
                            empty = True
                    if empty:
                        continue
                    for c0 in range(cmin[0], cmax[0] + 1):
                        for c1 in range(cmin[1], cmax[1] + 1):
                            edge = abs(c0 - cq[0]) == ring or abs(c1 - cq[1]) == ring
                            if D == 2:
                                if not edge:
                                    continue
                                c2a, c2b, c2s = 0, 1, 1
                            elif edge:
                                c2a, c2b, c2s = cmin[2], cmax[2] + 1, 1
                            else:  # inside the shell's side faces: only its two caps along the last axis
                                c2a, c2b, c2s = cq[2] - ring, cq[2] + ring + 1, 2 * ring
                            for c2 in range(c2a, c2b, max(c2s, 1)):
                                if D == 3:
                                    if c2 < 0 or c2 >= dims[2]:
                                        continue
                                    c = (c0 * dims[1] + c1) * dims[2] + c2
                                else:
                                    c = c0 * dims[1] + c1
                                for s in range(start[c], start[c + 1]):
                                    p = order[s]
                                    v = 0.0
                                    for d in range(D):
                                        e = Q[q, d] - P[p, d]
                                        v += e * e
                                    if v < best2 or (v == best2 and p < bp):
                                        best2, bp = v, p
                dist[q] = np.sqrt(best2)
                nearest[q] = bp
            return dist, nearest

        @jit
        def resample_polyline(uv, step):
            N, D = uv.shape
            s = np.zeros(N)
            for p in range(1, N):
                v = 0.0
                for d in range(D):
                    e = uv[p, d] - uv[p - 1, d]
                    v += e * e
                s[p] = s[p - 1] + np.sqrt(v)
            L = s[N - 1]
            n = max(int(np.ceil(L / step)), 1)
            t = np.empty(n + 1)
            dt = L / n
            for k in range(n + 1):
                t[k] = k * dt if dt != 0.0 else k / n * L
            t[n] = L
            out = np.empty((n + 1, D))
            j = 0
            for k in range(n + 1):
                x = t[k]
                # numpy.interp: the segment [s[j], s[j + 1]) holding x (the last point at its end)
                while j < N - 2 and s[j + 1] <= x:
                    j += 1
                for d in range(D):
                    if N == 1:
                        out[k, d] = uv[0, d]
                    elif x >= s[N - 1]:
                        out[k, d] = uv[N - 1, d]
                    else:
                        slope = (uv[j + 1, d] - uv[j, d]) / (s[j + 1] - s[j]) if s[j + 1] != s[j] else np.nan
                        y = slope * (x - s[j]) + uv[j, d]
                        if np.isnan(y):
                            y = slope * (x - s[j + 1]) + uv[j + 1, d]
                            if np.isnan(y) and uv[j, d] == uv[j + 1, d]:
                                y = uv[j, d]
                        out[k, d] = y
            return out, t

        @jit
        def two_view_covariance(X, T, Rc_a, tc_a, f_a, Rc_b, tc_b, f_b, s2, G, C, has_reg):
            N = X.shape[0]
            cov = np.empty((N, 3, 3))
            unc = np.empty(N)
            H = np.empty((3, 3))
            J = np.empty((2, 3))
            Jc = np.empty((2, 3))
            jn = np.empty(3)
            Pp = np.empty((3, 3))
            A = np.empty((3, 6))
            Mi = np.empty((3, 3))
            W = np.empty((3, 3))
            GC = np.empty((3, 6))
            for n in range(N):
                for i in range(3):
                    for j in range(3):
                        H[i, j] = 0.0
                t0, t1, t2 = T[n, 0], T[n, 1], T[n, 2]
                for k in range(2):
                    Rc = Rc_a if k == 0 else Rc_b
                    tc = tc_a if k == 0 else tc_b
                    f = f_a if k == 0 else f_b
                    x0 = X[n, 0] * Rc[0, 0] + X[n, 1] * Rc[0, 1] + X[n, 2] * Rc[0, 2] + tc[0]
                    x1 = X[n, 0] * Rc[1, 0] + X[n, 1] * Rc[1, 1] + X[n, 2] * Rc[1, 2] + tc[1]
                    z = X[n, 0] * Rc[2, 0] + X[n, 1] * Rc[2, 1] + X[n, 2] * Rc[2, 2] + tc[2]
                    Jc[0, 0], Jc[0, 1], Jc[0, 2] = f / z, 0.0, -f * x0 / z ** 2
                    Jc[1, 0], Jc[1, 1], Jc[1, 2] = 0.0, f / z, -f * x1 / z ** 2
                    for r in range(2):
                        for c in range(3):
                            J[r, c] = Jc[r, 0] * Rc[0, c] + Jc[r, 1] * Rc[1, c] + Jc[r, 2] * Rc[2, c]
                    u = J[0, 0] * t0 + J[0, 1] * t1 + J[0, 2] * t2
                    v = J[1, 0] * t0 + J[1, 1] * t1 + J[1, 2] * t2
                    nr = max(np.sqrt(u * u + v * v), 1e-12)
                    u /= nr
                    v /= nr
                    for c in range(3):
                        jn[c] = -v * J[0, c] + u * J[1, c]
                    for i in range(3):
                        for j in range(3):
                            H[i, j] += jn[i] * jn[j] / s2
                # across the 3D wire: the inverse of H + 1e6 t t^T (Gauss-Jordan, partial pivoting),
                # projected by I - t t^T on both sides
                for i in range(3):
                    for j in range(3):
                        tt = T[n, i] * T[n, j]
                        Pp[i, j] = (1.0 if i == j else 0.0) - tt
                        A[i, j] = H[i, j] + 1e6 * tt
                        A[i, 3 + j] = 1.0 if i == j else 0.0
                for c in range(3):
                    p = c
                    for r in range(c + 1, 3):
                        if abs(A[r, c]) > abs(A[p, c]):
                            p = r
                    if p != c:
                        for q in range(6):
                            A[c, q], A[p, q] = A[p, q], A[c, q]
                    d = A[c, c]
                    for q in range(6):
                        A[c, q] /= d
                    for r in range(3):
                        if r != c:
                            fr = A[r, c]
                            for q in range(6):
                                A[r, q] -= fr * A[c, q]
                for i in range(3):
                    for j in range(3):
                        Mi[i, j] = A[i, 3 + j]
                if has_reg:  # + the registration covariance pushed through the pose: G C G^T
                    for i in range(3):
                        for j in range(6):
                            sacc = 0.0
                            for q in range(6):
                                sacc += G[n, i, q] * C[q, j]
                            GC[i, j] = sacc
                    for i in range(3):
                        for j in range(3):
                            sacc = 0.0
                            for q in range(6):
                                sacc += GC[i, q] * G[n, j, q]
                            Mi[i, j] += sacc
                # both terms projected across the wire at once: (I - t t^T) Mi (I - t t^T)
                for i in range(3):
                    for j in range(3):
                        sacc = 0.0
                        for q in range(3):
                            sacc += Mi[i, q] * Pp[q, j]
                        W[i, j] = sacc
                tr = 0.0
                for i in range(3):
                    for j in range(3):
                        sacc = 0.0
                        for q in range(3):
                            sacc += Pp[i, q] * W[q, j]
                        cov[n, i, j] = sacc
                for i in range(3):
                    tr += cov[n, i, i]
                unc[n] = np.sqrt(max(tr, 0.0))
            return cov, unc

        _COMPILED_TRI.update(epipolar_candidates=epipolar_candidates, triangulate_dlt=triangulate_dlt,
                             two_view_viterbi=two_view_viterbi, grid_build=grid_build, grid_nearest=grid_nearest,
                             resample_polyline=resample_polyline, two_view_covariance=two_view_covariance)
        return _COMPILED_TRI


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
              alpha: float, beta: float, gamma: float, threads: int = 1) -> np.ndarray:
    """Frangi's vesselness of bright tubes (float32, 0 where the two largest-magnitude eigenvalues
    are not both negative) at the voxels ``idx_zyx`` (K, 3) of a smoothed image, from its Hessian by
    the stencils of :func:`guidewire3d.cta.grid.derivs_at` times ``sigma_mm ** 2`` (float64), whose
    eigenvalues come in closed form (the trigonometric method) instead of LAPACK: the loop of
    :func:`guidewire3d.cta.segment.frangi_at` over one scale, in one pass. Voxels must be at least 1
    from the border.

    The CTA stage's kernel (``_compile_cta``): the same operations in the same order as the first
    version (bit-identical output), without the small arrays that version allocated per voxel and
    axis (2-4x faster; ``tests/test_kernels.py`` checks it against the numpy formulation).
    ``threads`` > 1 splits the voxels among that many
    threads (the kernel releases the GIL; each voxel's value is the same).
    """
    f = _compile_cta()["frangi_at"]
    img = np.asarray(image_zyx)
    if img.dtype not in (np.dtype(np.float32), np.dtype(np.float64)):
        img = img.astype(np.float64)
    img = np.ascontiguousarray(img)
    idx = np.ascontiguousarray(idx_zyx, np.int64)
    args = (np.ascontiguousarray(spacing, np.float64), float(sigma_mm) ** 2, float(alpha), float(beta), float(gamma))
    n_t = max(1, min(int(threads), len(idx) // 50_000))
    if n_t == 1:
        return f(img, idx, *args)
    from concurrent.futures import ThreadPoolExecutor

    parts = np.array_split(np.arange(len(idx)), n_t)
    with ThreadPoolExecutor(n_t) as ex:
        outs = list(ex.map(lambda p: f(img, idx[p[0]:p[-1] + 1], *args), parts))
    return np.concatenate(outs)


# --------------------------------------------------------------------------------------
# the CTA vessel stage (guidewire3d.cta: segment, centerline), compiled apart from the live path
# --------------------------------------------------------------------------------------
_COMPILED_CTA: dict = {}


def _compile_cta():
    """The jitted kernels of the CTA vessel stage (compiled once per process; loaded from numba's disk
    cache when present)."""
    with _LOCK:
        if _COMPILED_CTA:
            return _COMPILED_CTA
        jit = _jit

        @jit
        def frangi_at(F, idx, sp, s2, alpha, beta, gamma):
            n = idx.shape[0]
            out = np.zeros(n, np.float32)
            H = np.empty((3, 3))
            lam = np.empty(3)
            E = np.eye(3).astype(np.int64)
            two_pi_3 = 2.0943951023931957
            for k in range(n):
                z, y, x = idx[k, 0], idx[k, 1], idx[k, 2]
                c = np.float64(F[z, y, x])
                for i in range(3):
                    di0, di1, di2 = E[i, 0], E[i, 1], E[i, 2]
                    pp = np.float64(F[z + di0, y + di1, x + di2])
                    mm = np.float64(F[z - di0, y - di1, x - di2])
                    H[i, i] = (pp - 2 * c + mm) / sp[i] ** 2
                    for j in range(i + 1, 3):
                        dj0, dj1, dj2 = E[j, 0], E[j, 1], E[j, 2]
                        a = np.float64(F[z + di0 + dj0, y + di1 + dj1, x + di2 + dj2])
                        b = np.float64(F[z + di0 - dj0, y + di1 - dj1, x + di2 - dj2])
                        cc = np.float64(F[z - di0 + dj0, y - di1 + dj1, x - di2 + dj2])
                        d = np.float64(F[z - di0 - dj0, y - di1 - dj1, x - di2 - dj2])
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
        def dilate_ball(mask, offsets):
            nz, ny, nx = mask.shape
            out = mask.copy()
            n_off = offsets.shape[0]
            for z in range(nz):
                for y in range(ny):
                    for x in range(nx):
                        if not mask[z, y, x]:
                            continue
                        # only voxels with a 6-neighbour outside the mask: the nearest mask voxel to
                        # any voxel outside it is one of those
                        edge = ((z > 0 and not mask[z - 1, y, x]) or (z < nz - 1 and not mask[z + 1, y, x])
                                or (y > 0 and not mask[z, y - 1, x]) or (y < ny - 1 and not mask[z, y + 1, x])
                                or (x > 0 and not mask[z, y, x - 1]) or (x < nx - 1 and not mask[z, y, x + 1]))
                        if not edge:
                            continue
                        for k in range(n_off):
                            zz, yy, xx = z + offsets[k, 0], y + offsets[k, 1], x + offsets[k, 2]
                            if 0 <= zz < nz and 0 <= yy < ny and 0 <= xx < nx:
                                out[zz, yy, xx] = True
            return out

        @jit
        def skeleton_paths(indptr, indices, data, degrees):
            n_nodes = indptr.shape[0] - 1
            visited = np.zeros(indices.shape[0], np.bool_)
            n_end = 0
            for v in range(n_nodes):
                if degrees[v] != 2:
                    n_end += degrees[v]
            cap_paths = n_end + indices.shape[0] // 4 + 1
            cap_pts = indices.shape[0] + indices.shape[0] // 4 + 1
            for v in range(n_nodes):
                if degrees[v] != 2 and degrees[v] > 1:
                    cap_pts += degrees[v] - 1
            path_ptr = np.zeros(cap_paths + 1, np.int64)
            path_ids = np.zeros(cap_pts, np.int64)
            lengths = np.zeros(cap_paths)
            n_paths = 0
            m = 0
            for sweep in range(2):
                for node in range(n_nodes):
                    if sweep == 0 and not (degrees[node] > 2 or degrees[node] == 1):
                        continue
                    if sweep == 1 and degrees[node] <= 0:
                        continue
                    e_lo = indptr[node]
                    e_hi = indptr[node + 1] if sweep == 0 else indptr[node] + 1
                    for e in range(e_lo, e_hi):
                        nb = indices[e]
                        if visited[e]:
                            continue
                        # walk from node through nb while the nodes have degree 2 (skan's _walk_path)
                        start = node
                        u, w = node, nb
                        path_ids[m] = u
                        m += 1
                        while True:
                            euw = -1
                            for f in range(indptr[u], indptr[u + 1]):
                                if indices[f] == w:
                                    euw = f
                                    break
                            if visited[euw]:
                                # skan counts one slot more here (left at 0); kept for the same paths
                                path_ids[m] = 0
                                m += 1
                                break
                            visited[euw] = True
                            for f in range(indptr[w], indptr[w + 1]):
                                if indices[f] == u:
                                    visited[f] = True
                                    break
                            path_ids[m] = w
                            m += 1
                            if degrees[w] != 2 or w == start:
                                break
                            a, b = indices[indptr[w]], indices[indptr[w] + 1]
                            nxt = a if a != u else b
                            u, w = w, nxt
                        n_paths += 1
                        path_ptr[n_paths] = m
            # lengths as skan's _path_distance: the weight of each consecutive pair's edge (0 if none)
            for k in range(n_paths):
                length = 0.0
                for i in range(path_ptr[k], path_ptr[k + 1] - 1):
                    u, w = path_ids[i], path_ids[i + 1]
                    d = 0.0
                    for f in range(indptr[u], indptr[u + 1]):
                        if indices[f] == w:
                            d = data[f]
                            break
                    length += d
                lengths[k] = length
            return path_ptr[:n_paths + 1], path_ids[:m], lengths[:n_paths]

        _COMPILED_CTA.update(frangi_at=frangi_at, dilate_ball=dilate_ball, skeleton_paths=skeleton_paths)
        return _COMPILED_CTA


def ball_offsets(radius_mm: float, spacing: np.ndarray) -> np.ndarray:
    """``(K, 3)`` int64 voxel offsets ``o`` with ``|o * spacing| <= radius_mm`` (the ball of a dilation)."""
    sp = np.asarray(spacing, dtype=np.float64)
    n = np.floor(radius_mm / sp + 1e-9).astype(np.int64)
    g = np.stack(np.meshgrid(*[np.arange(-k, k + 1) for k in n], indexing="ij"), axis=-1).reshape(-1, 3)
    d = np.sqrt(((g * sp) ** 2).sum(axis=1))
    return np.ascontiguousarray(g[d <= radius_mm], dtype=np.int64)


def dilate_ball(mask_zyx: np.ndarray, radius_mm: float, spacing: np.ndarray) -> np.ndarray:
    """Dilation of a 3D bool mask by the ball of ``radius_mm`` (``spacing`` per axis, mm): the voxels
    within ``radius_mm`` of a True voxel, i.e. ``distance_transform_edt(~mask, sampling=spacing) <=
    radius_mm``, without the distance transform. Each voxel of the mask with a 6-neighbour outside it
    stamps the ball's offsets (the nearest mask voxel to any voxel outside the mask is such a voxel:
    one step from it toward the outside voxel along an axis where they differ is nearer, hence
    outside the mask), so the cost is the mask's surface times the ball, not the box.
    """
    m = np.ascontiguousarray(mask_zyx, dtype=np.bool_)
    return _compile_cta()["dilate_ball"](m, ball_offsets(float(radius_mm), spacing))


def skeleton_paths(indptr: np.ndarray, indices: np.ndarray, weights: np.ndarray):
    """The paths of a skeleton's pixel graph (CSR, symmetric) between its end points and junctions:
    ``(path_ptr, path_ids, lengths)``, path ``k`` being ``path_ids[path_ptr[k]:path_ptr[k + 1]]`` (its
    end nodes included) of length ``lengths[k]`` (the sum of its edges' weights); then the isolated
    cycles. The walk of skan's ``Skeleton`` (``skan.csr._build_paths``, 0.13) in the same order,
    without its per-process compilation of numba's jitclass (~5 s).
    """
    indptr = np.ascontiguousarray(indptr, np.int64)
    degrees = np.diff(indptr)
    return _compile_cta()["skeleton_paths"](indptr, np.ascontiguousarray(indices, np.int64),
                                            np.ascontiguousarray(weights, np.float64), degrees)


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
    # C-contiguous and writeable (a read-only input would compile a second specialisation)
    rows, cols, n_on = f(np.require(m, requirements=["C", "W"]), _ZHANG_SUEN_LUT)
    return rows, cols, int(n_on)


def nearest_sq_dist(points, curve, radius: float) -> np.ndarray:
    """Squared Euclidean distance ``(N,)`` from each of ``points (N, 2)`` to the nearest of
    ``curve (M, 2)`` (``dx * dx + dy * dy``, as ``scipy.spatial.cKDTree`` sums it), exact for
    every point within ``radius`` of the curve; farther points get a distance > ``radius ** 2``
    (``inf`` when no curve point is within about 2 ``radius``). A grid of cells of about ``radius``
    instead of a tree: for a few hundred points, no build cost."""
    f = _compile()["nearest_sq_dist"]
    # C-contiguous and writeable (a read-only input would compile a second specialisation)
    return f(np.require(np.asarray(points, np.float64).reshape(-1, 2), requirements=["C", "W"]),
             np.require(np.asarray(curve, np.float64).reshape(-1, 2), requirements=["C", "W"]), float(radius) + 1.0)


def best_line(contrast, max_step: int) -> tuple[float, np.ndarray]:
    """The best line through a table ``contrast`` (rows, samples): one row per sample, moving at most ``max_step``
    rows between neighbouring samples, with the largest sum. Returns ``(sum, rows (samples,) int64)``: a Viterbi
    pass; among equal sums the first row, and the highest predecessor row (the numpy recursion it replaced:
    ``tests/test_continuation.py``)."""
    f = _compile()["best_line"]
    c = np.require(np.asarray(contrast, np.float64), requirements=["C", "W"])
    if c.ndim != 2 or c.shape[0] < 1 or c.shape[1] < 1:
        raise ValueError(f"best_line: contrast must be a non-empty 2D table, got shape {c.shape}")
    total, line = f(c, int(max_step))
    return float(total), line


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


# --- the reconstruction's kernels -------------------------------------------------------------------
def _in(a, dtype) -> np.ndarray:
    """A C-contiguous, read-only view (or copy, for another dtype / layout) of a kernel's input: the
    kernels read their inputs only, and one read-only type per argument means one compiled
    specialisation (the one :func:`warm_up` compiles), whatever the caller's arrays' flags."""
    a = np.ascontiguousarray(a, dtype)
    if a.flags.writeable:
        a = a.view()
        a.flags.writeable = False
    return a

def viterbi_pairwise(cand: np.ndarray, s: np.ndarray, point_branch: np.ndarray, branch_lca_s: np.ndarray,
                     points: np.ndarray, uv_tree: np.ndarray, uv_anchor: np.ndarray, *, sigma_step_px: float,
                     sigma_jump_mm: float, sigma_retreat_mm: float) -> np.ndarray:
    """Pairwise costs ``C (A - 1, K, K)`` of the reconstruction's Viterbi
    (:func:`guidewire3d.reconstruction.path.viterbi_path`), in one pass without temporaries.

    ``C[t, i, j]`` joins candidate ``i`` of anchor ``t`` to candidate ``j`` of anchor ``t + 1``:
    ``2 (sqrt(1 + m2 / sigma_step_px^2) - 1) + max(geo - e3, 0) / sigma_jump_mm + up / sigma_retreat_mm``
    with ``m2`` the squared mismatch of the tree point's 2D step and the anchors' (pseudo-Huber),
    ``e3`` their 3D distance, ``geo`` the geodesic distance through the lowest common ancestor and
    ``up`` its part towards the root. The squared distances are expanded
    (``|a|^2 + |b|^2 - 2 a.b``) as the numpy formulation did.

    Parameters
    ----------
    cand : (A, K) int64 dense tree point ids (no -1: the caller passes ``max(cand, 0)``)
    s : (N,) arclength from the root, mm; point_branch : (N,) int64; branch_lca_s : (B, B) mm
        (the ``ReconstructionContext`` tables of ``lca_s``)
    points : (N, 3) LPS mm; uv_tree : (N, 2) their projections, px; uv_anchor : (A, 2) px
    """
    f = _compile_reconstruction()["viterbi_pairwise"]
    return f(_in(cand, np.int64), _in(s, np.float64),
             _in(point_branch, np.int64), _in(branch_lca_s, np.float64),
             _in(points, np.float64), _in(uv_tree, np.float64),
             _in(uv_anchor, np.float64), float(sigma_step_px) ** 2, float(sigma_jump_mm),
             float(sigma_retreat_mm))


def place_on_path(source: np.ndarray, rays: np.ndarray, path_ids: np.ndarray, points: np.ndarray, radius: np.ndarray,
                  offset: np.ndarray, lo: np.ndarray, lim: np.ndarray, width: int, pos: np.ndarray, *,
                  dist_scale_mm: float, along_scale_mm: float):
    """The 3D point on each ray near a tree path: the loop of
    :func:`guidewire3d.reconstruction.placement.place_on_path` (see there), compiled.

    Ray ``m`` (``source + s rays[m]``, unit ``rays`` (M, 3)) tries the segments
    ``path_ids[g] -> path_ids[g + 1]`` (of ``points`` (N, 3), radii ``radius`` (N,)) for
    ``g = min(lo[m] + w, S - 1)``, ``w < width``, ``S = len(path_ids) - 1 >= 1``; those with
    ``lo[m] + w < lim[m]`` count, at the cost ``(dist / dist_scale_mm)^2 + (along / along_scale_mm)^2``
    of the ray-segment closest approach (``dist`` the ray-axis distance, ``along =
    (g + u - pos[m]) * length`` the distance along the path from the interpolated position ``pos``);
    the first minimum wins (``numpy.argmin``; the first segment when none counts). On it, the depth
    is that of the expected wire position (the centerline plus ``offset`` (N, 3), interpolated) within
    the ray's half chord through the tube of radius ``r(u)``.

    Returns the points (M, 3), the nearer segment end (M,) and, each (M,), the half chord, the
    ray-axis distance and ``r(u)``.
    """
    f = _compile_reconstruction()["place_on_path"]
    return f(_in(source, np.float64), _in(rays, np.float64), _in(path_ids, np.int64), _in(points, np.float64),
             _in(radius, np.float64), _in(offset, np.float64), _in(lo, np.int64), _in(lim, np.int64), int(width),
             _in(pos, np.float64), float(dist_scale_mm), float(along_scale_mm))


def lumen_covariance(rays, tangents, points_lps_mm, *, Rc, tc, focal_px, pose_R, pose_t, sigma_geo_px,
                     image_gradient, sigma_img, registration_covariance, half_width_mm, miss_mm, ambiguity_mm2,
                     k2, lumen_spread, sigma_centerline_mm) -> np.ndarray:
    """(M, 3, 3) covariance of points placed in the lumen: the per-point formula of
    :func:`guidewire3d.reconstruction.uncertainty.covariance_lumen` (see there) in one loop.

    ``image_gradient`` (M, 2), ``registration_covariance`` (6, 6) and ``ambiguity_mm2`` (M, 3, 3)
    may each be None (their term is left out).
    """
    M = len(rays)
    has_img, has_reg, has_amb = image_gradient is not None, registration_covariance is not None, \
        ambiguity_mm2 is not None
    g = _in(image_gradient if has_img else np.zeros((1, 2)), np.float64)
    C = _in(registration_covariance if has_reg else np.zeros((6, 6)), np.float64)
    amb = _in(ambiguity_mm2 if has_amb else np.zeros((1, 3, 3)), np.float64)
    f = _compile_reconstruction()["lumen_covariance"]
    return f(_in(rays, np.float64), _in(tangents, np.float64), _in(points_lps_mm, np.float64).reshape(M, 3),
             _in(Rc, np.float64), _in(tc, np.float64), float(focal_px), _in(pose_R, np.float64),
             _in(pose_t, np.float64), float(sigma_geo_px) ** 2, g, float(sigma_img) ** 2, has_img, C, has_reg,
             _in(half_width_mm, np.float64), _in(miss_mm, np.float64), amb, has_amb, float(k2),
             float(lumen_spread), float(sigma_centerline_mm) ** 2)


def pspline_system(x: np.ndarray, knots: np.ndarray, weights: np.ndarray, Y: np.ndarray):
    """The lambda-free part of a cubic P-spline fit (``reconstruction.smoothing.fit_pspline``):
    ``(values (M, 4), first (M,), ab (4, nb), BtY (nb, D))``.

    ``values``, ``first``: the design matrix ``B`` at ``x`` (M,) (within ``[knots[3], knots[-4]]``)
    as its dense rows, row ``m`` holding basis functions ``first[m] .. first[m] + 3``: what
    ``scipy.interpolate.BSpline.design_matrix(x, knots, 3)`` stores (same interval search and de
    Boor - Cox recursion). ``ab``: ``B^T W B`` in LAPACK's upper banded form (``ab[3 + i - j, j] =
    A[i, j]``) and ``BtY``: ``B^T W Y`` for the data weights ``weights`` (M,) and data ``Y`` (M, D),
    accumulated in the order of the former ``numpy.bincount`` formulation.
    """
    f = _compile_reconstruction()["pspline_system"]
    return f(_in(x, np.float64), _in(knots, np.float64), _in(weights, np.float64),
             _in(Y, np.float64).reshape(len(Y), -1))


def penalised_fit(values: np.ndarray, first: np.ndarray, ab: np.ndarray, BtY: np.ndarray, *, lam: float,
                  uv_px: np.ndarray, Rc: np.ndarray, tc: np.ndarray, focal_px: float, principal_point_px: np.ndarray):
    """One P-spline fit of 3D points from :func:`pspline_system` and its projection error:
    ``(fitted points (M, 3), mean error px, max error px)``.

    The system ``ab`` plus ``lam / (nb - 2)`` times the second-difference penalty ``D^T D`` (and
    1e-12 on the diagonal; as ``reconstruction.smoothing.fit_pspline``) is solved by a banded
    Cholesky factorisation (LAPACK dpbtf2's order; NaN when it is not positive definite); the
    fitted points ``B coef`` are projected (``x_cam = Rc X + tc``, ``focal_px x_cam[:2] / x_cam[2] +
    principal_point_px``) and compared with ``uv_px`` (M, 2).
    """
    f = _compile_reconstruction()["penalised_fit"]
    Xs, mean_px, max_px = f(_in(values, np.float64), _in(first, np.int64), _in(ab, np.float64),
                            _in(BtY, np.float64), float(lam), _in(uv_px, np.float64), _in(Rc, np.float64),
                            _in(tc, np.float64), float(focal_px), _in(principal_point_px, np.float64))
    return Xs, float(mean_px), float(max_px)


def polyline_measures(points: np.ndarray):
    """Unit tangents (N, 3) and curvature (N,) of a 3D polyline (N >= 2 points) by central differences
    (``numpy.gradient`` twice): ``T = X' / max(|X'|, 1e-12)``, ``kappa = |X' x X''| / max(|X'|^3, 1e-12)``
    (the formulas of ``reconstruction.smoothing.tangents`` and ``curvature``)."""
    f = _compile_reconstruction()["polyline_measures"]
    return f(_in(points, np.float64))


def branch_ambiguity(cand: np.ndarray, excess: np.ndarray, nodes: np.ndarray, points: np.ndarray, s: np.ndarray,
                     point_branch: np.ndarray, branch_lca_s: np.ndarray, *, scale: float,
                     sigma_jump_mm: float) -> np.ndarray:
    """(A, 3, 3) weighted second moment, per anchor, of its candidates' positions about the chosen
    tree point ``nodes[a]``: the loop of :func:`guidewire3d.reconstruction.path.ambiguity_mm2` (see
    there). ``cand`` (A, K) candidate ids (-1 none), ``excess`` (A, K) their min-marginal excess cost;
    weights ``exp(-excess / scale)`` normalised per anchor; candidates whose geodesic (through the
    lowest common ancestor, the ``lca_s`` tables) minus Euclidean distance to the chosen point is
    not above ``sigma_jump_mm`` count with no displacement."""
    f = _compile_reconstruction()["branch_ambiguity"]
    return f(_in(cand, np.int64), _in(excess, np.float64), _in(nodes, np.int64), _in(points, np.float64),
             _in(s, np.float64), _in(point_branch, np.int64), _in(branch_lca_s, np.float64), float(scale),
             float(sigma_jump_mm))


# --- the two-view triangulation's kernels -----------------------------------------------------------
def epipolar_candidates(F: np.ndarray, a_px: np.ndarray, b_px: np.ndarray, *, touch_px: float):
    """Where the epipolar lines of the master samples ``a_px`` (n, 2) cross or touch the other plane's
    wire ``b_px`` (m, 2): the loop of ``reconstruction.triangulation._candidates`` (see there) in
    one pass, without the (n, m) distance matrix.

    The line of ``a_i`` is ``F (a_i, 1)`` scaled to a unit normal; a crossing between ``b_j`` and
    ``b_{j+1}`` (a sign change of the signed distance, ``>= 0`` counting as positive) is at
    ``j + clip(d_j / (d_j - d_{j+1}), 0, 1)``; a touch is an interior local minimum of ``|d|``
    below ``touch_px`` with no crossing beside it, at ``j``. Returns flat ``(i (N,) int64, j (N,),
    sin (N,))``: all the crossings (by ``i``, then ``j``), then all the touches (same order), and
    ``|sin|`` of the angle between ``b``'s unit tangent (``numpy.gradient``) at ``rint(j)`` and the line.
    """
    f = _compile_triangulation()["epipolar_candidates"]
    return f(_in(F, np.float64), _in(a_px, np.float64).reshape(-1, 2), _in(b_px, np.float64).reshape(-1, 2),
             float(touch_px))


def triangulate_dlt(uv_a_px: np.ndarray, uv_b_px: np.ndarray, P_a: np.ndarray, P_b: np.ndarray) -> np.ndarray:
    """(N, 3) points from corresponding pixels of two views (``P_a``, ``P_b`` (3, 4)): the linear
    least squares of ``reconstruction.triangulation.triangulate_points`` (the four DLT rows
    ``u P[2] - P[0]``, ``v P[2] - P[1]`` scaled to unit norm over their first three columns, normal
    equations), solved per point by Gaussian elimination with partial pivoting instead of LAPACK
    (the same to rounding)."""
    f = _compile_triangulation()["triangulate_dlt"]
    return f(_in(uv_a_px, np.float64).reshape(-1, 2), _in(uv_b_px, np.float64).reshape(-1, 2),
             _in(P_a, np.float64), _in(P_b, np.float64))


def two_view_viterbi(n: int, ia: np.ndarray, jb: np.ndarray, X: np.ndarray, unary: np.ndarray, *, step_mm: float,
                     direction: int, max_candidates: int, max_gap: int, dense_px: float, step_tolerance_mm: float,
                     sigma_step_mm: float, back_px: float, skip_cost: float, px_other_mm: float, spread: float):
    """The two-view matching's Viterbi over ``n`` master samples: ``reconstruction.triangulation._viterbi``
    (see there for the model), compiled: ``(chosen (n,) int64 candidate index or -1, cost)``.

    Candidates ``q`` (``ia[q]`` the master sample, ``jb[q]`` the position along the other wire,
    ``X[q]`` the 3D point, ``unary[q]``): per sample the ``max_candidates`` lowest ``unary`` (the
    lower ``q`` on ties, as ``numpy.lexsort``). The pairwise cost from sample ``i - g`` to ``i``
    (``g <= max_gap``) is ``(over^2 + jump^2) / sigma_step_mm^2 + (g - 1) skip_cost`` (1e18 when
    the other wire's position moves back more than ``back_px``); a chain may start and end
    anywhere at ``skip_cost`` per sample left out. Ties go to the first minimum in the numpy
    code's order (``numpy.argmin`` over (gap, candidate))."""
    f = _compile_triangulation()["two_view_viterbi"]
    chosen, cost = f(int(n), _in(ia, np.int64), _in(jb, np.float64), _in(X, np.float64).reshape(-1, 3),
                     _in(unary, np.float64), float(step_mm), float(direction), int(max_candidates), int(max_gap),
                     float(dense_px), float(step_tolerance_mm), float(sigma_step_mm), float(back_px),
                     float(skip_cost), float(px_other_mm), float(spread))
    return chosen, float(cost)


def resample_polyline(points: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """A polyline (N, D) resampled at equal arclength: ``n + 1`` points, ``n = max(ceil(L / step), 1)``
    (``L`` its length), and their arclengths ``t`` (``numpy.linspace(0, L, n + 1)``): what
    ``numpy.interp`` of each coordinate over the cumulative segment lengths gives (the same
    formula; a zero-length segment takes its end value)."""
    f = _compile_triangulation()["resample_polyline"]
    P = _in(points, np.float64)
    return f(P.reshape(len(P), -1), float(step))


def two_view_covariance(points_lps_mm: np.ndarray, tangents: np.ndarray, cameras, *, sigma_2d_px: float,
                        pose_jacobians=None, registration_covariance=None) -> tuple[np.ndarray, np.ndarray]:
    """``(covariance (N, 3, 3), uncertainty (N,))`` of a two-view wire's points (the formula of
    ``reconstruction.triangulation.triangulate_wire``'s step 5, per point in one loop).

    Per plane ``(Rc, tc, focal_px)`` of ``cameras`` (two; ``x_cam = Rc X + tc``), the projection's
    Jacobian ``J`` (2, 3) at ``X``, the 2D wire's normal ``n`` (the projected unit tangent turned
    by 90 deg) and ``j = n^T J``: ``H = sum j j^T / sigma_2d_px^2``; the covariance is
    ``P (H + 1e6 t t^T)^-1 P`` with ``P = I - t t^T`` (the unit tangent ``t``: a slide along the
    wire is not an error), plus ``P G C G^T P`` when ``pose_jacobians`` ``G`` (N, 3, 6) and the
    ``registration_covariance`` ``C`` (6, 6) are given; the uncertainty is ``sqrt(max(trace, 0))``.
    The 3 x 3 inverse is a Gauss-Jordan elimination with partial pivoting. Where a plane sees the
    wire along its epipolar line the matrix's condition reaches ~1e12 (the uncertainty there is tens
    to hundreds of mm) and the result depends on the rounding of every step (of the points too: a
    1e-12 mm change of the points moves it by ~1e-6 relative): there this loop and the numpy
    formulation agree to ~1e-6 relative; elsewhere to ~1e-9 mm.
    """
    f = _compile_triangulation()["two_view_covariance"]
    (Ra, ta, fa), (Rb, tb, fb) = ((c[0], c[1], c[2]) for c in cameras)
    X = _in(points_lps_mm, np.float64).reshape(-1, 3)
    has_reg = pose_jacobians is not None and registration_covariance is not None
    G = _in(pose_jacobians if has_reg else np.zeros((1, 3, 6)), np.float64)
    C = _in(registration_covariance if has_reg else np.zeros((6, 6)), np.float64)
    return f(X, _in(tangents, np.float64).reshape(-1, 3), _in(Ra, np.float64), _in(ta, np.float64), float(fa),
             _in(Rb, np.float64), _in(tb, np.float64), float(fb), float(sigma_2d_px) ** 2, G, C, has_reg)


class NearestGrid:
    """Exact nearest-neighbour queries among fixed points (2D or 3D) through a uniform grid of
    cells of ``cell`` (the points' units): what ``scipy.spatial.cKDTree(points).query(q)`` answers
    (distance, index; the lower index on an exact tie), without its per-call overhead, for
    queries near the points (a far query visits more shells of cells)."""

    def __init__(self, points: np.ndarray, cell: float):
        P = np.ascontiguousarray(points, np.float64)
        if P.ndim != 2 or P.shape[1] not in (2, 3) or len(P) == 0 or not np.all(np.isfinite(P)):
            raise ValueError("NearestGrid: points must be a non-empty finite (N, 2) or (N, 3) array")
        self.cell = float(cell)
        self.points = _in(P, np.float64)
        self._grid = _compile_triangulation()["grid_build"](self.points, self.cell)

    def query(self, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(distance (M,), index (M,) int64)`` of each query's nearest point."""
        Q = _in(queries, np.float64).reshape(-1, self.points.shape[1])
        lo, dims, start, order = self._grid
        return _compile_triangulation()["grid_nearest"](self.points, lo, dims, start, order, self.cell, Q)


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
        best_line(np.zeros((3, 2)), 1)
        _warm_up_reconstruction()
        _warm_up_triangulation()


def _warm_up_reconstruction() -> None:
    """Compile (or load) the reconstruction's kernels on tiny inputs."""
    pts = np.array([[0.0, 0.0, 100.0], [1.0, 0.0, 100.0], [2.0, 0.5, 100.0]])
    ids = np.array([[0, 1], [1, 2]])
    viterbi_pairwise(ids, np.arange(3.0), np.zeros(3, np.int64), np.full((1, 1), np.inf), pts, pts[:, :2],
                     pts[:2, :2], sigma_step_px=1.0, sigma_jump_mm=1.0, sigma_retreat_mm=1.0)
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.1, 0.99]])
    place_on_path(np.zeros(3), d, np.arange(3), pts, np.ones(3), np.zeros((3, 3)), np.zeros(2, np.int64),
                  np.ones(2, np.int64), 2, np.zeros(2), dist_scale_mm=1.0, along_scale_mm=1.0)
    for opt in (None, 1):
        lumen_covariance(d, pts[:2] / 100.0, pts[:2], Rc=np.eye(3), tc=np.zeros(3), focal_px=1000.0, pose_R=np.eye(3),
                         pose_t=np.zeros(3), sigma_geo_px=1.0, image_gradient=None if opt is None else np.ones((2, 2)),
                         sigma_img=0.1, registration_covariance=None if opt is None else np.eye(6),
                         half_width_mm=np.ones(2), miss_mm=np.zeros(2),
                         ambiguity_mm2=None if opt is None else np.zeros((2, 3, 3)), k2=1.0, lumen_spread=0.3,
                         sigma_centerline_mm=0.2)
    x = np.linspace(0.0, 1.0, 9)
    knots = np.r_[[0.0] * 3, np.linspace(0.0, 1.0, 3), [1.0] * 3]
    X = np.column_stack([x, x, x + 10.0])
    D, first, ab, BtY = pspline_system(x, knots, np.full(9, 1 / 9), X)
    penalised_fit(D, first, ab, BtY, lam=0.1, uv_px=X[:, :2], Rc=np.eye(3), tc=np.zeros(3), focal_px=1.0,
                  principal_point_px=np.zeros(2))
    polyline_measures(pts)
    branch_ambiguity(ids, np.zeros((2, 2)), np.array([0, 1]), pts, np.arange(3.0), np.zeros(3, np.int64),
                     np.full((1, 1), np.inf), scale=2.0, sigma_jump_mm=0.5)


def _warm_up_triangulation() -> None:
    """Compile (or load) the two-view triangulation's kernels on tiny inputs."""
    P_a = np.array([[1000.0, 0.0, 256.0, 0.0], [0.0, 1000.0, 256.0, 0.0], [0.0, 0.0, 1.0, 1000.0]])
    P_b = np.array([[256.0, 0.0, -1000.0, 0.0], [0.0, 1000.0, 256.0, 0.0], [1.0, 0.0, 0.0, 1000.0]])
    a = np.array([[250.0, 250.0], [260.0, 255.0], [270.0, 262.0]])
    epipolar_candidates(np.eye(3), a, a[::-1], touch_px=0.7)
    X = triangulate_dlt(a, a, P_a, P_b)
    two_view_viterbi(3, np.arange(3), np.arange(3.0), X, np.zeros(3), step_mm=1.0, direction=1, max_candidates=2,
                     max_gap=2, dense_px=1.0, step_tolerance_mm=0.2, sigma_step_mm=0.3, back_px=1.0, skip_cost=8.0,
                     px_other_mm=0.2, spread=1.0)
    for pts in (X, a):
        NearestGrid(pts, 2.0).query(pts)
        resample_polyline(pts, 0.5)
    cams = ((np.eye(3), np.array([0.0, 0.0, 700.0]), 1000.0), (np.eye(3)[[2, 1, 0]], np.array([0.0, 0.0, 700.0]), 1000.0))
    T = np.tile([1.0, 0.0, 0.0], (3, 1))
    for reg in (None, np.eye(6)):
        two_view_covariance(X, T, cams, sigma_2d_px=0.5, pose_jacobians=None if reg is None else np.zeros((3, 3, 6)),
                            registration_covariance=reg)


# --- motion tracking (guidewire3d.motion.tracking) ----------------------------------------------------------------
__all__ += ["motion_solve", "motion_acquire_costs"]
_COMPILED_MOTION: dict = {}
_MOTION_POINT: list = []


def _motion_point_kernel():
    """``(motion_point, motion_rotation, motion_pairs)``, compiled once; ``motion_solve`` and ``motion_linearize``
    call them. ``motion_point``: the tracker's one curve point: at the
    tree sample ``y`` and its neighbour ``yn`` (camera frame, mm), the point-to-tangent residual of curve point
    ``(c0, c1)`` px, returned, and its Jacobian row ``J[i]`` in the tracker's (t, rotation about ``centroid``)."""
    with _LOCK:
        if not _MOTION_POINT:
            @_jit
            def motion_point(c0, c1, y, yn, focal, pp, centroid, J, i):
                u = focal * y[0] / y[2] + pp[0]
                v = focal * y[1] / y[2] + pp[1]
                t0 = focal * yn[0] / yn[2] + pp[0] - u
                t1 = focal * yn[1] / yn[2] + pp[1] - v
                nrm = np.sqrt(t0 * t0 + t1 * t1)
                d0 = c0 - u
                d1 = c1 - v
                if nrm > 1e-9:
                    t0 /= max(nrm, 1e-12)
                    t1 /= max(nrm, 1e-12)
                    n0, n1 = -t1, t0
                else:
                    dn = max(np.sqrt(d0 * d0 + d1 * d1), 1e-12)
                    n0, n1 = d0 / dn, d1 / dn
                z = y[2]
                g0 = n0 * (focal / z)
                g1 = n1 * (focal / z)
                g2 = -(g0 * y[0] + g1 * y[1]) / z
                e0, e1, e2 = y[0] - centroid[0], y[1] - centroid[1], y[2] - centroid[2]
                J[i, 0], J[i, 1], J[i, 2] = g0, g1, g2
                J[i, 3] = e1 * g2 - e2 * g1
                J[i, 4] = e2 * g0 - e0 * g2
                J[i, 5] = e0 * g1 - e1 * g0
                return -(n0 * d0 + n1 * d1)

            @_jit
            def motion_rotation(phi, R):
                """``R`` (3, 3) <- the rotation of the vector ``phi`` (Rodrigues, as ``geometry.so3_exp``)."""
                th = np.sqrt(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
                Km = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
                KK = Km @ Km
                if th < 1e-8:
                    a, b = 1.0, 0.5
                else:
                    a, b = np.sin(th) / th, (1.0 - np.cos(th)) / th ** 2
                for p in range(3):
                    for q in range(3):
                        R[p, q] = (1.0 if p == q else 0.0) + a * Km[p, q] + b * KK[p, q]

            @_jit
            def motion_pairs(uvs, c, sel, j):
                """``j[i]`` <- ``sel`` of the projected sample ``uvs`` (M, 2) nearest curve point ``c[i]`` (the
                lower index on a tie)."""
                for i in range(c.shape[0]):
                    best, bk = np.inf, 0
                    for s in range(uvs.shape[0]):
                        d2 = (uvs[s, 0] - c[i, 0]) ** 2 + (uvs[s, 1] - c[i, 1]) ** 2
                        if d2 < best:
                            best, bk = d2, s
                    j[i] = sel[bk]

            _MOTION_POINT.extend((motion_point, motion_rotation, motion_pairs))
        return tuple(_MOTION_POINT)


def _compile_motion():
    """The pose tracker's Gauss-Newton solve (``MotionTracker._solve``) as one compiled call: the numpy code it
    replaces spent its time in dozens of small temporaries per iteration (a frame's curve has at most 128
    points, the tree a few hundred samples near it)."""
    motion_point, _rot, motion_pairs = _motion_point_kernel()  # (it takes the lock itself)
    with _LOCK:
        if _COMPILED_MOTION:
            return _COMPILED_MOTION
        jit = _jit

        @jit
        def motion_solve(c, Y0, centroid, nbr, radius, focal, pp, start, prev, Lambda0, Lt, sigma_px, huber_px,
                         gate_px, inlier_px, crop_px, fit_correlation_mm, iterations, step_tol_mm, step_tol_rad):
            n = c.shape[0]
            K = Y0.shape[0]
            delta = start.copy()
            # the rotation of delta (Rodrigues, as geometry.so3_exp: _rot)
            R = np.empty((3, 3))

            def _move(k, R, delta, out):
                p0 = Y0[k, 0] - centroid[0]
                p1 = Y0[k, 1] - centroid[1]
                p2 = Y0[k, 2] - centroid[2]
                for q in range(3):
                    out[q] = p0 * R[q, 0] + p1 * R[q, 1] + p2 * R[q, 2] + centroid[q] + delta[q]

            y = np.empty(3)
            _rot(delta[3:], R)
            # the tree samples that can matter: projected (at the start pose) near the curve
            lo0, lo1, hi0, hi1 = np.inf, np.inf, -np.inf, -np.inf
            for i in range(n):
                lo0 = min(lo0, c[i, 0])
                lo1 = min(lo1, c[i, 1])
                hi0 = max(hi0, c[i, 0])
                hi1 = max(hi1, c[i, 1])
            lo0 -= crop_px
            lo1 -= crop_px
            hi0 += crop_px
            hi1 += crop_px
            sel = np.empty(K, np.int64)
            m = 0
            for k in range(K):
                _move(k, R, delta, y)
                u = focal * y[0] / y[2] + pp[0]
                v = focal * y[1] / y[2] + pp[1]
                if u >= lo0 and u <= hi0 and v >= lo1 and v <= hi1:
                    sel[m] = k
                    m += 1
            sel = sel[:m]
            J = np.zeros((n, 6))
            r = np.zeros(n)
            w = np.zeros(n)
            j = np.zeros(n, np.int64)
            lumen = np.zeros(n)
            H = np.eye(6)
            if m < 2:
                return False, np.inf, delta, H, 0, 0.0, np.inf, J, w, j, lumen
            length = 0.0
            for i in range(1, n):
                length += np.sqrt((c[i, 0] - c[i - 1, 0]) ** 2 + (c[i, 1] - c[i - 1, 1]) ** 2)
            length_mm = length * centroid[2] / focal
            pw = min(1.0, max(1.0, length_mm / fit_correlation_mm) / n)
            uvs = np.empty((m, 2))
            yn = np.empty(3)
            it = 0
            last = iterations + 1  # the final pass: new pairs at the solution
            for it_ in range(1, iterations + 2):
                final = it_ == last
                _rot(delta[3:], R)
                if final or it_ % 2 == 1:
                    # correspondences: the nearest projected tree sample (the lower index on a tie); found at
                    # the start and again every other iteration
                    for s in range(m):
                        _move(sel[s], R, delta, y)
                        uvs[s, 0] = focal * y[0] / y[2] + pp[0]
                        uvs[s, 1] = focal * y[1] / y[2] + pp[1]
                    motion_pairs(uvs, c, sel, j)
                for i in range(n):
                    _move(j[i], R, delta, y)
                    _move(nbr[j[i]], R, delta, yn)
                    r[i] = motion_point(c[i, 0], c[i, 1], y, yn, focal, pp, centroid, J, i)
                    a = abs(r[i])
                    w[i] = (1.0 / np.sqrt(1.0 + (a / huber_px) ** 2) if a <= gate_px else 0.0) * (pw / sigma_px ** 2)
                    lumen[i] = focal * radius[j[i]] / y[2]
                if final:
                    break
                it = it_
                # Gauss-Newton step with the priors
                Hn = Lambda0 + Lt
                gr = Lambda0 @ delta + Lt @ (delta - prev)
                for p in range(6):
                    for q in range(6):
                        s_ = 0.0
                        for i in range(n):
                            s_ += J[i, p] * w[i] * J[i, q]
                        Hn[p, q] += s_
                    s_ = 0.0
                    for i in range(n):
                        s_ += J[i, p] * w[i] * r[i]
                    gr[p] += s_
                H = Hn
                step = -np.linalg.solve(H, gr)
                delta = delta + step
                small = True
                for p in range(3):
                    if abs(step[p]) >= step_tol_mm or abs(step[3 + p]) >= step_tol_rad:
                        small = False
                if small:
                    last = it_ + 1
            ninl = 0
            out_sum = 0.0
            rob = 0.0
            h = huber_px / sigma_px
            for i in range(n):
                outside = max(abs(r[i]) - lumen[i], 0.0)
                if outside <= inlier_px:
                    ninl += 1
                    out_sum += outside
                a = min(abs(r[i]), gate_px) / sigma_px
                rob += 2.0 * h * h * (np.sqrt(1.0 + (a / h) ** 2) - 1.0)
            frac = ninl / n
            mean_res = out_sum / ninl if ninl > 0 else np.inf
            dp = delta - prev
            cost = pw * rob + delta @ (Lambda0 @ delta) + dp @ (Lt @ dp)
            return True, cost, delta, H, it, frac, mean_res, J, w, j, lumen

        _COMPILED_MOTION.update(motion_solve=motion_solve)
        return _COMPILED_MOTION


def motion_solve(c, Y0, centroid, nbr, radius, *, focal_px: float, principal_point_px, start, prev, Lambda0, Lt,
                 sigma_px: float, huber_px: float, gate_px: float, inlier_px: float, crop_px: float,
                 fit_correlation_mm: float, iterations: int, step_tol_mm: float, step_tol_rad: float):
    """The tracker's Gauss-Newton solve (``motion.tracking.MotionTracker._solve``, see there for the model).

    Parameters
    ----------
    c : (N, 2) curve points, px; Y0 : (K, 3) tree samples in the initial pose's camera frame, mm;
    centroid : (3,) their centroid; nbr : (K,) int, a neighbour along the tree of each sample (its tangent);
    radius : (K,) mm; start, prev : (6,) delta at the start and the previous frame's; Lambda0, Lt : (6, 6)
    the roadmap and temporal prior precisions.

    Returns
    -------
    ``(found, cost, delta (6,), H (6, 6), iterations, inlier fraction, mean px outside the lumen,
    J (N, 6), w (N,), pairs (N,) int, lumen px (N,))``; ``found`` is False when fewer than two tree samples
    project within ``crop_px`` of the curve's bounding box (at the start pose).
    """
    f = _compile_motion()["motion_solve"]
    return f(_in(c, np.float64), _in(Y0, np.float64), _in(centroid, np.float64), _in(nbr, np.int64),
             _in(radius, np.float64), float(focal_px), _in(principal_point_px, np.float64), _in(start, np.float64),
             _in(prev, np.float64), _in(Lambda0, np.float64), _in(Lt, np.float64), float(sigma_px), float(huber_px),
             float(gate_px), float(inlier_px), float(crop_px), float(fit_correlation_mm), int(iterations),
             float(step_tol_mm), float(step_tol_rad))


def motion_acquire_costs(points_uv_px, c, step_uv_px, shifts, *, gate_px: float) -> np.ndarray:
    """For each shift ``s`` (M,), ``sum_i min(d_i, gate_px)^2`` with ``d_i`` the distance of the curve point
    ``c[i] - s * step_uv_px`` to the nearest of ``points_uv_px`` (K, 2): the tracker's cranio-caudal search."""
    c = np.asarray(c, np.float64).reshape(-1, 2)
    shifts = np.asarray(shifts, np.float64).reshape(-1)
    moved = c[None, :, :] - shifts[:, None, None] * np.asarray(step_uv_px, np.float64).reshape(1, 1, 2)
    # every shifted curve point at once, against one grid of the tree's points (exact within the gate)
    d2 = nearest_sq_dist(moved.reshape(-1, 2), points_uv_px, float(gate_px))
    return np.minimum(d2, float(gate_px) ** 2).reshape(len(shifts), len(c)).sum(axis=1)


def warm_up_motion() -> None:
    """Compile (or load from the disk cache) the tracker's kernels on tiny inputs."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        Y0 = np.array([[0.0, 0.0, 700.0], [1.0, 0.0, 700.0], [2.0, 0.5, 700.0]])
        c = np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 1.0]])
        motion_solve(c, Y0, Y0.mean(axis=0), np.array([1, 0, 1]), np.ones(3), focal_px=1000.0,
                     principal_point_px=np.zeros(2), start=np.zeros(6), prev=np.zeros(6), Lambda0=np.eye(6),
                     Lt=np.zeros((6, 6)), sigma_px=1.5, huber_px=3.0, gate_px=40.0, inlier_px=3.0, crop_px=70.0,
                     fit_correlation_mm=3.0, iterations=2, step_tol_mm=0.01, step_tol_rad=1e-5)
        motion_acquire_costs(c, c, np.ones(2), np.arange(3.0), gate_px=40.0)


# --- biplane motion tracking (guidewire3d.motion.tracking.BiplaneMotionTracker) -------------------------------------
__all__ += ["motion_linearize"]
_COMPILED_MOTION_VIEWS: dict = {}


def _compile_motion_views():
    """One view's residuals and Jacobian at a pose (the inner loop of ``motion_solve``, without its Gauss-Newton
    step): the biplane tracker sums two views' normal equations in one solve."""
    motion_point, _rot, motion_pairs = _motion_point_kernel()  # (it takes the lock itself)
    with _LOCK:
        if _COMPILED_MOTION_VIEWS:
            return _COMPILED_MOTION_VIEWS
        jit = _jit

        @jit
        def motion_linearize(c, Y0, centroid, nbr, radius, focal, pp, delta, sel, pairs, find_pairs, sigma_px,
                             huber_px, gate_px, pw, slack):
            n = c.shape[0]
            m = sel.shape[0]
            R = np.empty((3, 3))
            _rot(delta[3:], R)
            y = np.empty(3)
            yn = np.empty(3)

            def _move(k, out):
                p0 = Y0[k, 0] - centroid[0]
                p1 = Y0[k, 1] - centroid[1]
                p2 = Y0[k, 2] - centroid[2]
                for q in range(3):
                    out[q] = p0 * R[q, 0] + p1 * R[q, 1] + p2 * R[q, 2] + centroid[q] + delta[q]

            j = pairs.copy()
            if find_pairs:
                uvs = np.empty((m, 2))
                for s in range(m):
                    _move(sel[s], y)
                    uvs[s, 0] = focal * y[0] / y[2] + pp[0]
                    uvs[s, 1] = focal * y[1] / y[2] + pp[1]
                motion_pairs(uvs, c, sel, j)
            J = np.zeros((n, 6))
            r = np.zeros(n)
            w = np.zeros(n)
            lumen = np.zeros(n)
            for i in range(n):
                _move(j[i], y)
                _move(nbr[j[i]], yn)
                r[i] = motion_point(c[i, 0], c[i, 1], y, yn, focal, pp, centroid, J, i)
                a = abs(r[i])
                lumen[i] = focal * radius[j[i]] / y[2]
                w[i] = (1.0 / np.sqrt(1.0 + (a / huber_px) ** 2) if a <= gate_px else 0.0) * (pw / sigma_px ** 2)
                if slack > 0.0:  # the curve anywhere within ``slack`` projected radii of the centerline fits
                    inside = slack * lumen[i]
                    if a <= inside:
                        r[i] = 0.0
                        w[i] = 0.0
                    elif a <= gate_px:
                        r[i] = r[i] - inside if r[i] > 0 else r[i] + inside
                        a = abs(r[i])
                        w[i] = (1.0 / np.sqrt(1.0 + (a / huber_px) ** 2)) * (pw / sigma_px ** 2)
            return r, J, w, j, lumen

        _COMPILED_MOTION_VIEWS.update(motion_linearize=motion_linearize)
        return _COMPILED_MOTION_VIEWS


def motion_linearize(c, Y0, centroid, nbr, radius, *, focal_px: float, principal_point_px, delta, sel, pairs,
                     find_pairs: bool, sigma_px: float, huber_px: float, gate_px: float, point_weight: float,
                     lumen_slack: float = 0.0):
    """One view's point-to-tangent residuals of the tracker at ``delta`` (``motion_solve``'s inner loop).

    Parameters
    ----------
    c : (N, 2) curve points, px; Y0 : (K, 3) tree samples in the view's camera frame at the initial pose, mm;
    centroid : (3,); nbr : (K,) int; radius : (K,) mm (as ``motion_solve``); delta : (6,) the view's delta;
    sel : (M,) int, M >= 1, the tree samples a curve point may pair with; pairs : (N,) int, the pairs to use when
    ``find_pairs`` is False (else each curve point's nearest projected sample among ``sel``, the lower index on a
    tie); point_weight : each point's weight in the fit (one point per ``fit_correlation_mm``); lumen_slack : a
    point within this many projected radii of the centerline has no residual (weight 0), one beyond it the
    distance beyond (0: the distance to the centerline, as ``motion_solve``).

    Returns
    -------
    ``(r (N,) px, J (N, 6) px per delta unit, w (N,) robust weights / sigma^2, pairs (N,) int, lumen px (N,))``
    """
    f = _compile_motion_views()["motion_linearize"]
    return f(_in(c, np.float64), _in(Y0, np.float64), _in(centroid, np.float64), _in(nbr, np.int64),
             _in(radius, np.float64), float(focal_px), _in(principal_point_px, np.float64), _in(delta, np.float64),
             _in(sel, np.int64), _in(pairs, np.int64), bool(find_pairs), float(sigma_px), float(huber_px),
             float(gate_px), float(point_weight), float(lumen_slack))


def warm_up_motion_views() -> None:
    """Compile (or load from the disk cache) the biplane tracker's kernel on tiny inputs."""
    Y0 = np.array([[0.0, 0.0, 700.0], [1.0, 0.0, 700.0], [2.0, 0.5, 700.0]])
    c = np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 1.0]])
    for find in (True, False):
        motion_linearize(c, Y0, Y0.mean(axis=0), np.array([1, 0, 1]), np.ones(3), focal_px=1000.0,
                         principal_point_px=np.zeros(2), delta=np.zeros(6), sel=np.arange(3), pairs=np.zeros(3, np.int64),
                         find_pairs=find, sigma_px=1.5, huber_px=3.0, gate_px=40.0, point_weight=1.0)
