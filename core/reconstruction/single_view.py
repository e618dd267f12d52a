"""3D guidewire reconstruction from one X-ray view, a registered pose and the CTA vessel tree.

One view gives no depth. The depth comes from the vessel prior: the wire is inside the lumen.

Default method (``ReconMethod.VESSEL``), one module of this package per step:

    1. ``context``: per pose, a :class:`ReconstructionContext` is built once and cached: the vessel
       tree is densified (about 3 px between projected points), projected (pixel, depth, projected
       radius), indexed by a 2D KD-tree, and its branch structure is turned into tables that give
       the lowest common ancestor, and so the geodesic distance, of any two points in O(1).
    2. ``candidates``: anchors every ``dp_step_px`` along the ordered 2D wire. Candidates of an
       anchor: the tree points whose projection lies within the projected lumen radius (+ a margin)
       of it.
    3. ``path``: Viterbi over the anchors: the unary cost is how far the anchor lies outside the
       projected lumen; the pairwise cost asks the tree move between consecutive choices to be
       *connected* (geodesic ~ Euclidean distance, so no jump to an overlapping vessel or across a
       crossing of the wire with itself), to reproduce the 2D step (which makes foreshortening
       consistent) and to be distal (retreats towards the root are penalised). A small start cost
       prefers the proximal candidate. In tracking mode (``previous``) an extra unary cost keeps
       the choices on the previous frame's root -> tip path: advancing beyond the old tip or
       retracting is free, entering a side branch costs in proportion to the distance into it. A
       path that ends nearer the root than it starts triggers a try on the reversed 2D wire (the
       output is always proximal -> distal). Path-level checks on the result: in tracking mode the
       Viterbi also runs without the prior, and the prior is dropped when that path explains the
       wire much better (``track_override_cost``: the previous frame's path was a wrong branch, or
       the wire went elsewhere) along one connected route (``track_override_max_step``: a path that
       jumps between vessels is no evidence); how far the path walks back towards the root along the
       wire (``Wire3D.tree_retreat_mm``: a 2D trace that took the wrong way at a crossing); and the best
       rival path that avoids a branch the path entered (``Wire3D.branch_extra_cost``,
       ``branch_tip_shift_mm``); and whether the path reaches its tip's vessel by a skip, a step whose
       projected tree route is many px longer than the wire's (``Wire3D.tip_skip_px``). The frame verdict
       (``live.frame_verdict``) reads the last three.
    4. ``placement``: the chosen nodes are joined along the tree into one path. Each 2D wire
       point's ray is intersected with the nearby path segments (ray-segment closest approach,
       preferring the path position interpolated between the anchors). The feasible depths are the
       chord of the ray through the tube the wire's centre can occupy (radius minus
       ``wire_clearance_mm``). Inside that chord the point is put at the depth of the expected wire
       position: the centerline moved towards the outer side of bends (``outer_bend_prior``; a wire
       pushed through a curved vessel rides its outer wall), i.e. the chord's middle on straight
       parts.
    5. ``smoothing``: a penalised cubic B-spline (P-spline, the paper's smoothness weight
       lambda = 0.1) smooths the 3D points; lambda is halved until the projection stays within
       ``max_projection_px`` of the input wire (mean) and 2.5x that (max).
    6. ``uncertainty``: per point, a 3x3 covariance of the point's error *across the wire*,
       reported as ``uncertainty_mm = sqrt(trace Sigma)``: the ray shift (the paper's image term,
       the registration covariance) through the part the lumen does not absorb, where the wire sits
       in the lumen, a ray that misses it, and the branch ambiguity of the Viterbi min-marginals.
       Calibrated on 30 held-out simulator sequences (the module has the model, the numbers and its
       limits).

``ReconMethod.PAPER`` and ``ReconMethod.BSPLINE`` (``baselines``) put the points elsewhere and share
steps 5 and 6, with the unconstrained uncertainty. This module joins the steps:
:func:`reconstruct_wire` (one frame), :class:`WireTracker` (frame by frame) and their result
:class:`Wire3D`, which the two-view ``triangulation`` returns too.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from guidewire3d.errors import InputError
from guidewire3d.geometry import CArm, Pose
from guidewire3d.methods import ReconMethod
from guidewire3d.reconstruction.baselines import bspline_points, paper_points
from guidewire3d.reconstruction.candidates import anchor_indices, tree_candidates
from guidewire3d.reconstruction.context import ReconOptions, build_context, options_at_pixel, options_for_tree
from guidewire3d.reconstruction.path import (
    ambiguity_mm2,
    branch_alternative,
    lost_lumen_stretch,
    path_retreat_mm,
    path_step_costs,
    tip_skip_px,
    tracking_tip,
    viterbi_costs,
    viterbi_path,
)
from guidewire3d.reconstruction.placement import place_on_path
from guidewire3d.reconstruction.smoothing import arclength, curvature, smooth_wire, tangents
from guidewire3d.reconstruction.uncertainty import beyond_path_mm2, covariance_lumen, covariance_unconstrained
from guidewire3d.vesseltree import VesselTree

__all__ = ["Wire3D", "reconstruct_wire", "WireTracker"]

#: ``Wire3D.tree_retreat_mm``: a move through the tree between consecutive anchors longer than this
#: many anchor steps (``dp_step_px`` at the tree's depth) is a jump, not a walk along the vessels
RETREAT_STEP_ANCHORS = 4.0


def _ro(a, dtype=float) -> np.ndarray:
    a = np.array(a, dtype=dtype, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Wire3D:
    """A reconstructed 3D wire; falsy when reconstruction failed (then the arrays are empty).

    Attributes
    ----------
    points_lps_mm : (N, 3) ndarray, proximal -> distal, LPS mm.
    uncertainty_mm : (N,) ndarray, ``sqrt(trace(Sigma))`` of each point's 3x3 covariance
        (the predicted RMS 3D distance to the true wire, mm; see ``reconstruction.uncertainty``).
    length_mm : float, arc length of the polyline.
    projection_error_px : float, mean distance between the projected points and the input 2D wire
        (point to corresponding point).
    tree_point_ids : (N,) int, the vessel-tree point chosen for each point (-1 where none).
    arclength_mm, curvature_per_mm : (N,) ndarray.
    covariance_mm2 : (N, 3, 3) ndarray, the covariance behind ``uncertainty_mm`` (of the error
        across the wire: for the vessel method it has no component along the wire).
    reversed_input : bool, the vessel method reversed the given 2D order (its path through the
        tree ran towards the root, and the reversed one explained the wire better).
    tree_rise_mm : float, vessel method: arclength from the tree's root gained from the first to
        the last tree point of the path (positive: the output runs away from the root, as a wire
        advanced from the root does); NaN for the other methods.
    tree_retreat_mm : float, vessel method: how far the path through the tree runs back towards
        the root along the wire (``path.path_retreat_mm``; a wire advanced from the root does not,
        a 2D trace that took the wrong way at a crossing does); NaN for the other methods.
    branch_extra_cost, branch_tip_shift_mm : float, vessel method: the best path that avoids a
        branch the chosen one entered (``path.branch_alternative``): its extra cost (0: as good;
        inf: none) and how far its end lies from the chosen path's, mm; NaN for the other methods.
    past_path_mm : float, vessel method: the length of the 2D wire past the last anchor the path
        through the tree explains (in mm at the tree's depth; its depth is extrapolated, and spread
        by ``uncertainty.BEYOND_PATH_DEPTH_PER_MM``); 0 when the path explains the wire to its tip.
    prior_dropped : bool, vessel method: the previous frame's path (the tracking prior) was dropped,
        the wire fitting another path through the tree much better (``ReconOptions.track_override_cost``).
    lumen_miss_mm : (N,) ndarray, vessel method: how far each point's ray passes outside the lumen of its
        tree point (distance from the ray to the centerline minus the radius, mm at the vessel; 0 inside).
        Empty for the other methods. A stretch of the wire far outside the path's lumen is not in that
        vessel: the tree lacks the one it is in, or the pose is off there (``live.session.OFF_LUMEN_MAX_MM``).
    lost_lumen_stretch_mm, lost_lumen_shift_mm : float, vessel method: how much of the wire (mm) also projects
        onto segmented lumen the tree does not follow (``path.lost_lumen_stretch``: two vessels fused in the
        CTA, the tree kept one), and how far that lumen lies from the wire (median, mm); 0 and NaN when none,
        NaN for the other methods.
    tip_skip_px, tip_skip_from_tip_px : float, vessel method: the largest skip of the path near the tip
        (``path.tip_skip_px``: how many px more the projected tree route of one step covers than the 2D wire's
        step, within ``path.TIP_SKIP_NEAR_PX`` of the tip; px at the reference pixel) and how far from the tip it
        lies; 0 and NaN when none, NaN for the other methods.
    """

    points_lps_mm: np.ndarray
    uncertainty_mm: np.ndarray
    length_mm: float
    projection_error_px: float
    success: bool
    message: str
    tree_point_ids: np.ndarray
    arclength_mm: np.ndarray
    curvature_per_mm: np.ndarray
    seconds: float = 0.0
    method: str = ReconMethod.VESSEL.value
    covariance_mm2: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    reversed_input: bool = False
    tree_rise_mm: float = float("nan")
    tree_retreat_mm: float = float("nan")
    branch_extra_cost: float = float("nan")
    branch_tip_shift_mm: float = float("nan")
    past_path_mm: float = 0.0
    prior_dropped: bool = False
    lumen_miss_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    lost_lumen_stretch_mm: float = float("nan")
    lost_lumen_shift_mm: float = float("nan")
    tip_skip_px: float = float("nan")
    tip_skip_from_tip_px: float = float("nan")

    def __post_init__(self):
        object.__setattr__(self, "points_lps_mm", _ro(np.reshape(self.points_lps_mm, (-1, 3))))
        for name in ("uncertainty_mm", "arclength_mm", "curvature_per_mm", "lumen_miss_mm"):
            object.__setattr__(self, name, _ro(np.reshape(getattr(self, name), -1)))
        object.__setattr__(self, "tree_point_ids", _ro(np.reshape(self.tree_point_ids, -1), np.int64))
        object.__setattr__(self, "covariance_mm2", _ro(np.reshape(self.covariance_mm2, (-1, 3, 3))))

    def __bool__(self) -> bool:
        return bool(self.success)

    @property
    def n_points(self) -> int:
        return len(self.points_lps_mm)

    @classmethod
    def failed(cls, message: str, *, seconds: float = 0.0, method: str = ReconMethod.VESSEL.value) -> "Wire3D":
        z = np.zeros(0)
        return cls(np.zeros((0, 3)), z, 0.0, float("nan"), False, str(message), np.zeros(0, np.int64),
                   z, z, float(seconds), method)

    def to_dict(self) -> dict:
        def f(x):
            return None if not np.isfinite(x) else round(float(x), 5)

        return {
            "success": bool(self.success),
            "message": str(self.message),
            "method": str(self.method),
            "points_lps_mm": np.round(self.points_lps_mm, 4).tolist(),
            "uncertainty_mm": np.round(self.uncertainty_mm, 4).tolist(),
            "length_mm": f(self.length_mm),
            "projection_error_px": f(self.projection_error_px),
            "tree_point_ids": self.tree_point_ids.astype(int).tolist(),
            "arclength_mm": np.round(self.arclength_mm, 4).tolist(),
            "curvature_per_mm": np.round(self.curvature_per_mm, 5).tolist(),
            "seconds": f(self.seconds),
            "reversed_input": bool(self.reversed_input),
            "tree_rise_mm": f(self.tree_rise_mm),
            "tree_retreat_mm": f(self.tree_retreat_mm),
            "branch_extra_cost": f(self.branch_extra_cost),
            "branch_tip_shift_mm": f(self.branch_tip_shift_mm),
            "past_path_mm": f(self.past_path_mm),
            "prior_dropped": bool(self.prior_dropped),
            "lumen_miss_mm": np.round(self.lumen_miss_mm, 3).tolist(),
            "lost_lumen_stretch_mm": f(self.lost_lumen_stretch_mm),
            "lost_lumen_shift_mm": f(self.lost_lumen_shift_mm),
            "tip_skip_px": f(self.tip_skip_px),
            "tip_skip_from_tip_px": f(self.tip_skip_from_tip_px),
        }


def _validate_uv(wire_uv_px) -> np.ndarray:
    try:
        uv = np.array(wire_uv_px, dtype=float, copy=True)
    except (TypeError, ValueError):
        raise InputError("reconstruction: wire_uv_px must be an (M, 2) array of pixels") from None
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise InputError(f"reconstruction: wire_uv_px must be (M, 2), got shape {uv.shape}")
    if not np.all(np.isfinite(uv)):
        raise InputError("reconstruction: wire_uv_px has non-finite entries")
    return uv


def _finish(ctx, X, uv, tid, depth_std, extra, *, image, registration_covariance, opt, method, t0, message,
            lumen=None, reversed_input=False, tree_rise_mm=float("nan"), path_checks=(float("nan"),) * 3):
    Xs, lam = smooth_wire(ctx, X, uv, lam=opt.smoothing_lambda, opt=opt)
    proj = ctx.project(Xs)
    perr = float(np.linalg.norm(proj - uv, axis=1).mean())
    if lumen is None:
        cov = covariance_unconstrained(ctx, Xs, uv, depth_std_mm=depth_std, extra_iso_mm2=extra, image=image,
                                       registration_covariance=registration_covariance, opt=opt)
    else:
        half_width, miss, amb = lumen
        cov = covariance_lumen(ctx, Xs, uv, tangent=tangents(Xs), half_width_mm=half_width, miss_mm=miss,
                               ambiguity_mm2=amb, image=image, registration_covariance=registration_covariance,
                               opt=opt)
    unc = np.sqrt(np.clip(np.trace(cov, axis1=1, axis2=2), 0.0, None))
    arc = arclength(Xs)
    ok = bool(np.isfinite(perr) and perr <= opt.fail_projection_px and np.all(np.isfinite(Xs)))
    msg = message if ok else f"projection error {perr:.2f} px exceeds {opt.fail_projection_px} px"
    if lam < opt.smoothing_lambda:
        msg += f"; smoothing lambda reduced to {lam:.3g} to keep the projection"
    tree_ids = np.where(tid >= 0, ctx.orig_id[np.maximum(tid, 0)], -1)
    return Wire3D(Xs, unc, float(arc[-1]), perr, ok, msg, tree_ids, arc, curvature(Xs), time.perf_counter() - t0,
                  method.value, cov, reversed_input, tree_rise_mm, *path_checks)


def _reconstruct_vessel(ctx, uv, *, track_tip, image, registration_covariance, opt, t0):
    aidx = anchor_indices(uv, opt.dp_step_px)
    cand, outside = tree_candidates(ctx, uv[aidx], opt)
    has = (cand >= 0).any(axis=1)
    coverage = float(has.mean())
    if coverage < opt.min_coverage or has.sum() < 2:
        return Wire3D.failed(
            f"the 2D wire misses the projected vessel tree ({100 * coverage:.0f}% of anchors inside, "
            f"need {100 * opt.min_coverage:.0f}%)", seconds=time.perf_counter() - t0)
    aidx, cand, outside = aidx[has], cand[has], outside[has]
    costs = viterbi_costs(ctx, uv[aidx], cand, outside, opt, track_tip)
    nodes, total, marg = viterbi_path(ctx, uv[aidx], cand, outside, opt, track_tip, costs=costs)
    prior_note = ""
    if costs.U_untracked is not None:
        # the tracking prior may only settle what the 2D wire leaves open: when the best path
        # without it explains the wire much better, the previous frame's path is not this one's
        # (its distal part was a wrong branch, or the wire was pulled back and went elsewhere).
        # That path must be one route along the vessels: when it jumps between vessels that only
        # project onto the wire (a step costing more than track_override_max_step), the tree does
        # not fit the wire at this pose (a pose off by a few mm, a non-rigid motion), neither path
        # is evidence against the other, and the prior, the last path that did fit, is kept
        free = costs.untracked()
        f_nodes, f_total, f_marg = viterbi_path(ctx, uv[aidx], cand, outside, opt, None, costs=free)
        if (total - f_total > opt.track_override_cost and len(f_nodes) >= 2
                and path_step_costs(free, f_nodes).max() <= opt.track_override_max_step):
            prior_note = (f"; the previous frame's path dropped as a prior (the wire fits another path better by "
                          f"{total - f_total:.0f})")
            nodes, total, marg, costs, track_tip = f_nodes, f_total, f_marg, free, None
    n_skipped = len(aidx) - len(nodes)
    aidx_all, aidx = aidx, aidx[: len(nodes)]
    if not np.isfinite(total) or len(nodes) < 2:
        return Wire3D.failed("no connected path through the vessel tree explains the 2D wire",
                             seconds=time.perf_counter() - t0)
    reversed_note = ""
    if ctx.s[nodes[-1]] < ctx.s[nodes[0]] - opt.reverse_mm:
        # the path runs towards the root: the 2D wire was probably given distal -> proximal. The
        # retry runs over every anchor with a candidate (the forward path may have ended early)
        r_aidx = len(uv) - 1 - aidx_all[::-1]
        r_costs = viterbi_costs(ctx, uv[::-1][r_aidx], cand[::-1], outside[::-1], opt, track_tip)
        r_nodes, r_total, r_marg = viterbi_path(ctx, uv[::-1][r_aidx], cand[::-1], outside[::-1], opt, track_tip,
                                                costs=r_costs)
        if r_total < total and len(r_nodes) >= 2:
            uv, aidx, nodes, total, marg = uv[::-1].copy(), r_aidx[: len(r_nodes)], r_nodes, r_total, r_marg
            costs = r_costs
            n_skipped = len(r_aidx) - len(r_nodes)
            reversed_note = "; the 2D wire looked distal -> proximal: output reversed to proximal -> distal"
    X, tid, half, dist, r = place_on_path(ctx, uv, aidx, nodes)
    miss = np.maximum(dist - r, 0.0)
    depth_std = 2.0 * half / np.sqrt(12.0) + miss
    half_width = np.sqrt(np.maximum(r * r - dist * dist, 0.0))
    amb = None
    if opt.ambiguity_scale > 0:
        # each wire point takes the ambiguity of its nearest anchor (beyond the path's end: the last)
        k = np.clip(np.searchsorted(aidx, np.arange(len(uv))), 0, len(aidx) - 1)
        km = np.clip(k - 1, 0, len(aidx) - 1)
        k = np.where(np.abs(aidx[km] - np.arange(len(uv))) < np.abs(aidx[k] - np.arange(len(uv))), km, k)
        amb = ambiguity_mm2(ctx, nodes, marg, opt)[k]
    past_mm = 0.0
    if n_skipped:
        # the wire past the path's last anchor fits no lumen: its depth is extrapolated, as uncertain as it is long
        past, past_mm = beyond_path_mm2(ctx, uv, int(aidx[-1]))
        amb = past if amb is None else amb + past
    msg = (f"ok: {len(uv)} points, {100 * coverage:.0f}% of anchors on the tree, path cost {total:.1f}" + reversed_note
           + prior_note)
    if coverage < 1.0:
        msg += " (gaps bridged)"
    if n_skipped:
        msg += f"; the last {n_skipped} anchors fit no lumen (placed beyond the path's end)"
    # segmented lumen the tree lost along these rays (two vessels fused in the CTA): a second hypothesis for the
    # point's depth, as likely as the chosen one (second moment about the chosen point: half the squared shift)
    lost_mm, lost_shift_mm, lost_delta = lost_lumen_stretch(ctx, X)
    alt = np.isfinite(lost_delta[:, 0])
    if alt.any():
        extra = np.zeros((len(X), 3, 3))
        extra[alt] = 0.5 * lost_delta[alt, :, None] * lost_delta[alt, None, :]
        amb = extra if amb is None else amb + extra
    ids = np.where(miss > 0, -1, tid)
    arc_px = np.r_[0.0, np.cumsum(np.sqrt((np.diff(uv, axis=0) ** 2).sum(axis=1)))]
    skip_px, skip_from_tip_px = tip_skip_px(ctx, nodes, arc_px[aidx], float(arc_px[-1]))
    retreat_mm = path_retreat_mm(ctx, nodes, max_step_mm=RETREAT_STEP_ANCHORS * opt.dp_step_px * ctx.px_mm)
    w = _finish(ctx, X, uv, ids, depth_std, miss**2, image=image, registration_covariance=registration_covariance,
                opt=opt, method=ReconMethod.VESSEL, t0=t0, message=msg, lumen=(half_width, miss, amb),
                reversed_input=bool(reversed_note), tree_rise_mm=float(ctx.s[nodes[-1]] - ctx.s[nodes[0]]),
                path_checks=(retreat_mm, *branch_alternative(ctx, costs, nodes, total, opt)))
    return replace(w, past_path_mm=past_mm, prior_dropped=bool(prior_note), lumen_miss_mm=miss,
                   lost_lumen_stretch_mm=lost_mm, lost_lumen_shift_mm=lost_shift_mm, tip_skip_px=skip_px,
                   tip_skip_from_tip_px=skip_from_tip_px)


def _reconstruct_paper(ctx, uv, *, image, registration_covariance, opt, t0):
    X = paper_points(ctx, uv)
    if X is None:
        return Wire3D.failed("paper closed-form depth is undefined (zero denominator) for this pose",
                             seconds=time.perf_counter() - t0, method=ReconMethod.PAPER.value)
    zero = np.zeros(len(uv))
    return _finish(ctx, X, uv, -np.ones(len(uv), np.int64), zero, zero, image=image,
                   registration_covariance=registration_covariance, opt=opt, method=ReconMethod.PAPER, t0=t0,
                   message="paper closed-form depth (single-view: not constrained by the anatomy)")


def _reconstruct_bspline(ctx, uv, *, image, registration_covariance, opt, t0):
    placed = bspline_points(ctx, uv, opt)
    if placed is None:
        return Wire3D.failed("the 2D wire misses the projected vessel tree", seconds=time.perf_counter() - t0,
                             method=ReconMethod.BSPLINE.value)
    X, tid, depth_std, extra = placed
    return _finish(ctx, X, uv, tid, depth_std, extra, image=image,
                   registration_covariance=registration_covariance, opt=opt, method=ReconMethod.BSPLINE, t0=t0,
                   message="2D B-spline lifted to the nearest centerline depth")


def reconstruct_wire(wire_uv_px, pose: Pose, carm: CArm, tree: VesselTree, *, previous: Wire3D | None = None,
                     method="vessel", registration_covariance=None, image=None,
                     options: ReconOptions | None = None) -> Wire3D:
    """Reconstruct the 3D wire of one frame.

    Parameters
    ----------
    wire_uv_px : (M, 2) ndarray of float
        The ordered 2D wire (pixels ``(u, v)``, proximal -> distal, about 1 px apart).
    pose : Pose
        The registered ``T_iso_from_lps`` (any pose: e.g. an EPnP one for the baseline).
    carm : CArm
        The view of the frame.
    tree : VesselTree
        The CTA vessel centerline graph (LPS mm).
    previous : Wire3D, optional
        The previous frame's result: its root-to-tip path becomes a prior (tracking).
    method : ReconMethod or str
        ``"vessel"`` (default), ``"paper"`` or ``"bspline"``.
    registration_covariance : (6, 6) ndarray, optional
        Pose covariance in the left-perturbation tangent ``(tx, ty, tz, rx, ry, rz)`` (mm, rad).
    image : (rows, cols) ndarray, optional
        The frame; its gradient (intensities min-max normalised to [0, 1], per px) enters the
        paper's uncertainty term ``sigma_img^2 gI gI^T``.

    Returns
    -------
    Wire3D
        Falsy with a message when the wire cannot be reconstructed (e.g. it misses the tree).
    """
    t0 = time.perf_counter()
    try:
        method = ReconMethod(method.value if isinstance(method, ReconMethod) else str(method).lower())
    except ValueError:
        raise InputError(f"reconstruction: unknown method {method!r}; choose one of "
                         f"{[m.value for m in ReconMethod]}") from None
    uv = _validate_uv(wire_uv_px)
    if len(uv) < 2:
        return Wire3D.failed("the 2D wire has fewer than 2 points", method=method.value)
    opt = options_for_tree(options_at_pixel(options or ReconOptions(), carm.pixel_at_iso_mm), tree)
    ctx = build_context(pose, carm, tree, options=opt)
    kw = dict(image=image, registration_covariance=registration_covariance, opt=opt, t0=t0)
    if method is ReconMethod.PAPER:
        return _reconstruct_paper(ctx, uv, **kw)
    if method is ReconMethod.BSPLINE:
        return _reconstruct_bspline(ctx, uv, **kw)
    return _reconstruct_vessel(ctx, uv, track_tip=tracking_tip(ctx, previous), **kw)


class WireTracker:
    """Frame-by-frame reconstruction that keeps the previous frame's path as a prior.

    A frame that cannot be reconstructed is returned as a falsy ``Wire3D`` (flagged in
    ``failed_frames``) and does not replace the prior.
    """

    def __init__(self, pose: Pose, carm: CArm, tree: VesselTree, *, method="vessel", registration_covariance=None,
                 options: ReconOptions | None = None):
        self.pose, self.carm, self.tree = pose, carm, tree
        self.method = method
        self.registration_covariance = registration_covariance
        self.options = options or ReconOptions()
        self.context = build_context(pose, carm, tree,
                                     options=options_for_tree(options_at_pixel(self.options, carm.pixel_at_iso_mm), tree))
        self.previous: Wire3D | None = None
        self.n_frames = 0
        self.failed_frames: list[int] = []

    def update(self, wire_uv_px, *, image=None) -> Wire3D:
        w = reconstruct_wire(wire_uv_px, self.pose, self.carm, self.tree, previous=self.previous,
                             method=self.method, registration_covariance=self.registration_covariance,
                             image=image, options=self.options)
        if w.success:
            self.previous = w
        else:
            self.failed_frames.append(self.n_frames)
        self.n_frames += 1
        return w
