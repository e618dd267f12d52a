"""The path through the vessel tree (step 3 of ``single_view``): Viterbi over the anchors.

The unary cost is how far the anchor lies outside the projected lumen; the pairwise cost asks the
tree move between consecutive choices to be connected (geodesic ~ Euclidean distance), to
reproduce the 2D step and to be distal. In tracking mode an extra unary cost keeps the choices on
the previous frame's root -> tip path. The recursions run compiled (``guidewire3d.kernels``); the
min-marginals give the branch ambiguity that enters the uncertainty.
"""
from __future__ import annotations

import numpy as np
from guidewire3d import kernels

__all__ = ["viterbi_path", "ambiguity_mm2", "tracking_tip"]


def viterbi_path(ctx, uv_a, cand, outside, opt, track_tip):
    """The chosen tree point per anchor (A',), the path's total cost and its min-marginals.

    ``cand``, ``outside`` (A, K): the candidates of the anchors ``uv_a`` (A, 2) and their distance
    outside the projected lumen (``candidates.tree_candidates``); ``track_tip``: the tracking prior
    (:func:`tracking_tip`, a dense tree point) or None. The path may end before the last anchor.

    The min-marginals are ``(cand, excess)``, each (A', K): the candidates of the anchors on the
    path and, for each, how much more the best path through it costs (0 for the chosen one).
    """
    # keep only the columns that hold a candidate somewhere (the KD query pads with misses)
    keep = (cand >= 0).any(axis=0)
    cand, outside = cand[:, keep], outside[:, keep]
    valid = cand >= 0
    safe = np.maximum(cand, 0)
    U = (outside / opt.sigma_outside_px) ** 2
    if track_tip is not None:
        # distance off the previous frame's root -> tip path into a side branch; advancing beyond
        # the previous tip (into its subtree) or retracting along the path is free
        lca = ctx.lca_s(safe, track_tip)
        off = np.where(lca >= ctx.s[track_tip] - 1e-9, 0.0, ctx.s[safe] - lca)
        U = U + np.maximum(off - opt.track_tolerance_mm, 0.0) / opt.sigma_track_mm
    U = np.where(valid, U, np.inf)
    # pairwise costs for all steps at once: (A-1, K, K), compiled (kernels.viterbi_pairwise):
    # C[t, i, j] = 2 (sqrt(1 + m2 / sigma_step_px^2) - 1) + max(geo - e3, 0) / sigma_jump_mm + up / sigma_retreat_mm
    # with e3 = |X_j - X_i|, m2 = |(uv_j - uv_i) - (w_t - w_t-1)|^2 and geo, up the tree move through
    # the lowest common ancestor (up: its part towards the root). The pseudo-Huber on the 2D step
    # mismatch is quadratic up to sigma_step_px, then linear (a wire cutting the corner of a
    # bifurcation leaves the centerline's candidates for a few anchors)
    C = kernels.viterbi_pairwise(safe, ctx.s, ctx.point_branch, ctx.branch_lca_s, ctx.points, ctx.uv, uv_a,
                                 sigma_step_px=opt.sigma_step_px, sigma_jump_mm=opt.sigma_jump_mm,
                                 sigma_retreat_mm=opt.sigma_retreat_mm)
    acc = U[0] + opt.start_cost_per_mm * ctx.s[safe[0]]
    # the path may end before the last anchor, paying skip_cost per anchor left unexplained (a
    # distal part outside every lumen, e.g. a missing or mis-registered end branch, is then not
    # forced onto a far branch by a long jump); the recursions run compiled (kernels)
    alpha, back, end_t, end_k, end_cost = kernels.viterbi_forward(acc, U, C, opt.skip_cost)
    end_t, end_k, end_cost = int(end_t), int(end_k), float(end_cost)
    best = np.empty(end_t + 1, np.int64)
    best[-1] = end_k
    for t in range(end_t - 1, -1, -1):
        best[t] = back[t, best[t + 1]]
    # min-marginals of the path ending at end_t: forward + backward min-sum costs
    beta = kernels.viterbi_backward(C, U, end_t)
    with np.errstate(invalid="ignore"):
        excess = alpha[: end_t + 1] + beta - (alpha[end_t, end_k])
    excess = np.where(np.isfinite(excess), np.maximum(excess, 0.0), np.inf)
    return cand[np.arange(end_t + 1), best], end_cost, (cand[: end_t + 1], excess)


def ambiguity_mm2(ctx, nodes, marginals, opt) -> np.ndarray:
    """(A', 3, 3) second moment of the tree point about the chosen one, per anchor.

    The candidates of an anchor weighted by ``exp(-excess / ambiguity_scale)`` (normalised; the
    excess is the extra path cost of going through the candidate, in the squared-residual units
    of the Viterbi costs, so a scale of 2 reads it as a Gaussian log-likelihood): a second branch
    that explains the 2D wire almost as well (overlap, a bifurcation near the tip) at another
    depth. Candidates joined to the chosen point by a straight stretch of tree (geodesic minus
    Euclidean distance below ``sigma_jump_mm``) are the same hypothesis moved along the vessel
    and count with no displacement.
    """
    cand, excess = marginals
    return kernels.branch_ambiguity(cand, excess, nodes, ctx.points, ctx.s, ctx.point_branch, ctx.branch_lca_s,
                                    scale=opt.ambiguity_scale, sigma_jump_mm=opt.sigma_jump_mm)


def tracking_tip(ctx, previous):
    """The tracking prior of :func:`viterbi_path`: a dense tree point on the root -> tip path of the
    ``previous`` frame's ``Wire3D``, or None (no previous frame, or it failed)."""
    if previous is None or not previous.success:
        return None
    ids = previous.tree_point_ids
    ids = ids[ids >= 0]
    if len(ids) == 0 or ids.max() >= ctx.tree.n_points:
        return None
    # the most distal chosen point (largest arclength from the root), moved back by
    # track_confirm_mm: a branch entered in the last few mm of the previous frame is not locked in
    tip = int(ids[np.argmax(ctx.s[ids])])
    rp = ctx.root_path(tip)
    k = int(np.searchsorted(ctx.s[rp], ctx.s[tip] - ctx.options.track_confirm_mm, side="right")) - 1
    return int(rp[max(k, 0)])
