"""Candidates (step 2 of ``single_view``): anchors along the 2D wire and, for each, the vessel-tree
points whose projected lumen contains it (within a margin)."""
from __future__ import annotations

import numpy as np
from guidewire3d.reconstruction.smoothing import arclength

__all__ = ["anchor_indices", "tree_candidates"]


def anchor_indices(uv, step_px) -> np.ndarray:
    """Indices of the anchors along the ordered 2D wire ``uv`` (M, 2): about every ``step_px`` of its
    arclength, the first and the last point included."""
    s = arclength(uv)
    n = max(int(np.ceil(s[-1] / step_px)), 1)
    idx = np.searchsorted(s, np.linspace(0.0, s[-1], n + 1))
    idx = np.clip(idx, 0, len(uv) - 1)
    idx = idx[np.r_[True, idx[1:] != idx[:-1]]]  # np.unique of the (sorted) indices
    if idx[-1] != len(uv) - 1:
        idx = np.r_[idx, len(uv) - 1]
    return idx


def tree_candidates(ctx, uv_a, opt):
    """The candidates of the anchors ``uv_a`` (A, 2): the tree points (``ctx.cand_ids``) whose
    projection lies within their projected lumen radius + ``opt.margin_px`` of the anchor, at most
    ``opt.candidates`` each.

    Returns (A, K) candidate ids (dense tree points, -1 none) and (A, K) 2D distance outside the
    projected lumen (px, inf for none)."""
    K = opt.candidates
    dist, ids = ctx.kd2.query(uv_a, k=K, distance_upper_bound=ctx.r_px_max + opt.margin_px)
    ids = np.where(np.isfinite(dist), ctx.cand_ids[np.minimum(ids, len(ctx.cand_ids) - 1)], -1)
    safe = np.maximum(ids, 0)
    outside = np.where(ids >= 0, np.maximum(dist - ctx.r_px[safe], 0.0), np.inf)
    ok = (ids >= 0) & (outside <= opt.margin_px)
    return np.where(ok, ids, -1), np.where(ok, outside, np.inf)
