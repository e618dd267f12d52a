"""The points on their rays (step 4 of ``single_view``): each 2D wire point's ray meets the chosen
path through the tree.

The chosen tree points are joined along the tree into one path. Each ray is intersected with the
nearby path segments (ray-segment closest approach, preferring the path position interpolated
between the anchors). The feasible depths are the chord of the ray through the tube the wire's
centre can occupy (radius minus ``wire_clearance_mm``): inside it the point is put at the depth of
the expected wire position (the centerline moved towards the outer side of bends).
"""
from __future__ import annotations

import numpy as np

__all__ = ["place_on_path", "DIST_SCALE_MM", "ALONG_SCALE_MM"]

#: place_on_path's segment choice: ray-axis distance and distance along the path from the
#: position interpolated between the anchors, each in units of (mm)
DIST_SCALE_MM = 0.25
ALONG_SCALE_MM = 1.5


def _ray_segments(o, d, A, B, rA, rB, seg):
    """Closest approach of rays ``o + s d`` (d: (M, 3) unit) to the segments ``A[seg] -> B[seg]``.

    ``A, B`` are (S, 3) segment ends with radii ``rA, rB`` (S,); ``seg`` (M, W) picks the segments
    tried for each ray. Returns, each (M, W): depth along the ray ``s``, ray-axis distance, segment
    parameter ``u``, half-chord of the ray through the tube of radius ``r(u)``, and ``r(u)``.
    """
    e = B - A
    w0 = A - o
    c = np.einsum("sk,sk->s", e, e)[seg]
    q = np.einsum("sk,sk->s", e, w0)[seg]
    w2 = np.einsum("sk,sk->s", w0, w0)[seg]
    b = np.einsum("mwk,mk->mw", e[seg], d)
    p = np.einsum("mwk,mk->mw", w0[seg], d)
    den = c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(den > 1e-12, (p * b - q) / den, 0.5)
    u = np.clip(u, 0.0, 1.0)
    s = p + u * b
    # |s d - u e - w0|^2 expanded (d is unit)
    dist = np.sqrt(np.maximum(s * s - 2 * s * u * b - 2 * s * p + u * u * c + 2 * u * q + w2, 0.0))
    r = rA[seg] + u * (rB - rA)[seg]
    sin2 = np.clip(1.0 - b * b / np.maximum(c, 1e-24), 1e-6, 1.0)
    half = np.sqrt(np.clip(r * r - dist * dist, 0.0, None) / sin2)
    half = np.minimum(half, 0.5 * np.abs(b) + r)  # a ray along the vessel: bounded by the segment
    return s, dist, u, half, r


def place_on_path(ctx, uv, anchor_idx, nodes):
    """3D points on the rays of every wire point, near the tree path through ``nodes``.

    ``uv`` (M, 2): the 2D wire; ``anchor_idx`` (A',): the indices of the anchors in it that
    ``nodes`` (A',), the dense tree points of :func:`~guidewire3d.reconstruction.path.viterbi_path`,
    were chosen for. Returns, each per wire point: the 3D point (M, 3) LPS mm, the nearer end of
    the path segment it was placed on (M,), the half chord of its ray through the segment's tube of
    radius ``ctx.radius_eff`` (M,) mm, the ray's distance to the segment's axis (M,) mm and that
    radius (M,) mm.
    """
    P = ctx.path(int(nodes[0]), int(nodes[-1]))
    scratch = ctx._scratch
    scratch[P] = np.arange(len(P))
    pos = scratch[nodes].astype(float)
    scratch[P] = -1
    on = pos >= 0
    if not on.any():
        pos = np.zeros(len(nodes))
        on = np.ones(len(nodes), bool)
    M = len(uv)
    m = np.arange(M)
    p = np.interp(m, anchor_idx[on], pos[on])
    # window of path segments around each point: between the bracketing anchors, with slack
    k = np.clip(np.searchsorted(anchor_idx[on], m, side="right") - 1, 0, on.sum() - 1)
    pa = pos[on][k]
    pb = pos[on][np.minimum(k + 1, on.sum() - 1)]
    slack = 4
    lo = np.clip(np.floor(np.minimum(np.minimum(pa, pb), p)).astype(int) - slack, 0, max(len(P) - 2, 0))
    hi = np.clip(np.ceil(np.maximum(np.maximum(pa, pb), p)).astype(int) + slack, 1, len(P) - 1)
    W = int(min(max((hi - lo).max(), 1), 400))
    seg = lo[:, None] + np.arange(W)[None, :]
    segok = seg < np.minimum(hi, lo + W)[:, None]
    seg = np.minimum(seg, len(P) - 2) if len(P) >= 2 else np.zeros_like(seg)
    if len(P) < 2:
        P = np.r_[P, P]
    d = ctx.rays(uv)
    pa_ids, pb_ids = P[:-1], P[1:]
    rad = ctx.radius_eff
    s, dist, u, half, r = _ray_segments(ctx.source, d, ctx.points[pa_ids], ctx.points[pb_ids],
                                        rad[pa_ids], rad[pb_ids], seg)
    # nearest segment to the ray, preferring the path position interpolated between the anchors
    # (this decides the depth where the vessel runs along the beam and many segments touch the ray)
    seg_len = np.linalg.norm(ctx.points[pb_ids] - ctx.points[pa_ids], axis=1)[seg]
    along = (seg + u - p[:, None]) * seg_len
    cost = np.where(segok, (dist / DIST_SCALE_MM) ** 2 + (along / ALONG_SCALE_MM) ** 2, np.inf)
    w = np.argmin(cost, axis=1)
    s_, d_, u_, h_, r_ = (x[m, w] for x in (s, dist, u, half, r))
    sw = seg[m, w]
    a_ids, b_ids = pa_ids[sw], pb_ids[sw]
    # within the chord, the depth of the expected wire position (outer side of bends)
    off = ctx.outer_offset[a_ids] + u_[:, None] * (ctx.outer_offset[b_ids] - ctx.outer_offset[a_ids])
    Y = ctx.points[a_ids] + u_[:, None] * (ctx.points[b_ids] - ctx.points[a_ids]) + off
    s_ = np.clip(np.einsum("mk,mk->m", Y - ctx.source, d), s_ - h_, s_ + h_)
    X = ctx.source + s_[:, None] * d
    tid = np.where(u_ < 0.5, a_ids, b_ids)
    return X, tid, h_, d_, r_
