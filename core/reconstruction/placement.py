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
from guidewire3d import kernels

__all__ = ["place_on_path", "DIST_SCALE_MM", "ALONG_SCALE_MM"]

#: place_on_path's segment choice: ray-axis distance and distance along the path from the
#: position interpolated between the anchors, each in units of (mm)
DIST_SCALE_MM = 0.25
ALONG_SCALE_MM = 1.5


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
    if len(P) < 2:
        P = np.r_[P, P]
    # nearest segment to the ray, preferring the path position interpolated between the anchors
    # (this decides the depth where the vessel runs along the beam and many segments touch the ray):
    # the cost (dist / DIST_SCALE_MM)^2 + (along / ALONG_SCALE_MM)^2 at the ray-segment closest
    # approach, minimised over each ray's window (the segments lo .. min(hi, lo + W) - 1); within
    # the chord, the depth of the expected wire position (outer side of bends); one compiled loop
    return kernels.place_on_path(ctx.source, ctx.rays(uv), P, ctx.points, ctx.radius_eff, ctx.outer_offset, lo,
                                 np.minimum(hi, lo + W), W, p, dist_scale_mm=DIST_SCALE_MM,
                                 along_scale_mm=ALONG_SCALE_MM)
