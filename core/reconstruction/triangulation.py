"""The guidewire in 3D from two views (biplane, issue 23): epipolar matching and triangulation.

Both planes share the patient pose, so their projection matrices ``P_A``, ``P_B`` (LPS mm -> px)
fix the epipolar geometry: a point of plane A's wire lies, in plane B, on its epipolar line
``l = F a`` (``F`` the fundamental matrix of the pair). :func:`triangulate_wire`:

1. Plane A's ordered wire (proximal -> distal) is resampled every ``step_px``; plane B's densely.
2. **Candidates**: for each A point, the places where its epipolar line crosses B's wire (sign
   changes of the signed distance along B, interpolated), plus the places where B's wire touches
   the line without crossing it (``touch_px``): where the wire runs along an epipolar line the
   crossings are ill-conditioned or many. Each candidate pair is triangulated (linear least
   squares over both views, DLT).
3. **Choice** (Viterbi over the A points): unary, the vessel prior: how far the triangulated
   point lies outside the CTA lumen (``sigma_lumen_mm``); pairwise, the 3D step between
   consecutive points against the step along A (connectivity) and a monotone walk along B (the
   same wire, so B's arclength moves one way only; both directions are tried, as the two planes'
   2D orders are independent); a *skip* state (cost ``skip_cost``) for A points with no
   acceptable partner (the part of the wire one plane does not see). The prior breaks the ties
   where the wire runs along an epipolar line.
4. **Smoothing**: a cubic smoothing spline per coordinate over A's arclength, each point weighted
   by how well the two views condition it (``sin^2`` of the angle between B's wire and the
   epipolar line: a point where the wire runs along the epipolar line is left to its neighbours).
5. **Uncertainty** per point, from both views: the information of each view's measurement across
   its 2D wire (``sigma_2d_px``), summed, inverted across the 3D wire (a slide along the wire is
   not an error of its shape), plus the registration covariance pushed through the pose (it moves
   both rays together). ``uncertainty_mm = sqrt(trace)``, as the single-view reconstruction.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from guidewire3d import kernels
from guidewire3d.errors import InputError
from guidewire3d.geometry import CArm, Pose
from guidewire3d.reconstruction.single_view import Wire3D
from guidewire3d.reconstruction.smoothing import arclength, curvature, pspline_system, tangents
from guidewire3d.reconstruction.uncertainty import pose_jacobian
from scipy.spatial import cKDTree

__all__ = ["TwoViewOptions", "TwoViewWire", "TwoViewContext", "fundamental_matrix", "triangulate_points",
           "triangulate_wire", "extend_distal", "projection_error_px"]


@dataclass(frozen=True)
class TwoViewOptions:
    """Tuning of :func:`triangulate_wire`."""

    step_px: float = 3.0  #: spacing of the master plane's samples (each plane is the master in turn)
    dense_px: float = 1.0  #: spacing of the other plane's wire for the crossings (linear in between)
    touch_px: float = 0.7  #: B's wire within this of an epipolar line without crossing it is a candidate
    max_candidates: int = 6  #: per A point, the most plausible (vessel prior) are kept
    sigma_lumen_mm: float = 0.5  #: unary: distance outside the CTA lumen
    centerline_weight: float = 1.0  #: unary: (distance to the centerline / radius)^2 inside it, times this
    step_tolerance_mm: float = 0.2  #: pairwise: a 3D step may disagree with its projections by this much freely
    sigma_step_mm: float = 0.3  #: pairwise: cost per this much beyond it
    back_px: float = 1.0  #: pairwise: B's arclength may move back this much (noise)
    skip_cost: float = 8.0  #: a master sample left unmatched (the other pass may match it)
    max_gap: int = 4  #: at most this many consecutive master samples unmatched inside a chain
    outlier_mm: float = 0.5  #: a match this far (and 4 robust sigmas) from the smooth curve is dropped
    min_matched: float = 0.5  #: fraction of plane A's wire that must be matched
    min_points: int = 5
    smoothing_lambda: float = 0.05  #: P-spline smoothness weight (as ``ReconOptions.smoothing_lambda``)
    knot_px: float = 6.0  #: knot spacing along the merged position (arclength in A + in B, px)
    sigma_2d_px: float = 0.5  #: 2D wire error across the wire (px)
    max_reprojection_px: float = 3.0  #: a result whose mean reprojection error in a plane exceeds this fails
    extend_min_px: float = 8.0  #: a plane's 2D wire this far beyond the two-view tip is appended (extend_distal)

    def __post_init__(self):
        for name in ("step_px", "dense_px", "touch_px", "sigma_lumen_mm", "step_tolerance_mm", "sigma_step_mm",
                     "skip_cost", "outlier_mm", "min_matched", "smoothing_lambda", "knot_px", "sigma_2d_px", "max_reprojection_px", "extend_min_px"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"TwoViewOptions.{name} must be a finite positive number, got {v!r}")


@dataclass(frozen=True, eq=False)
class TwoViewWire:
    """A two-view wire: ``wire3d`` (a ``reconstruction.Wire3D``, method ``biplane``) and how it fits
    each plane."""

    wire3d: object  # reconstruction.Wire3D (falsy when it failed)
    projection_error_px: tuple[float, float]  # mean distance of the projected 3D wire to plane A's / B's 2D wire
    matched_fraction: float  # of plane A's wire samples
    b_reversed: bool  # plane B's 2D order ran the other way (distal -> proximal relative to A)
    distal_gap_px: tuple[float, float] = (float("nan"), float("nan"))  # each plane's 2D wire beyond the two-view tip
    single_view_distal_mm: float = 0.0  # length of the distal part appended from one plane (extend_distal)
    #: that plane (0: A, 1: B; -1 when none), its single-view reconstruction the distal part was taken from and its
    #: 2D wire in plane A's order: the frame verdict holds the distal part to what that one view can promise
    distal_plane: int = -1
    distal_source: object = None  # reconstruction.Wire3D
    distal_uv_px: object = None  # (M, 2) ndarray

    def __bool__(self) -> bool:
        return bool(self.wire3d)


def fundamental_matrix(P_a, P_b) -> np.ndarray:
    """``F`` (3, 3) with ``x_b^T F x_a = 0`` for homogeneous pixels of the same 3D point.

    ``F = [e_b]_x P_b P_a^+`` with ``e_b = P_b C_a`` (``C_a``: plane A's source, the null vector of
    ``P_a``). Normalised to unit Frobenius norm."""
    P_a, P_b = np.asarray(P_a, float), np.asarray(P_b, float)
    _, _, vt = np.linalg.svd(P_a)
    C = vt[-1]
    e = P_b @ C
    ex = np.array([[0, -e[2], e[1]], [e[2], 0, -e[0]], [-e[1], e[0], 0]])
    F = ex @ P_b @ np.linalg.pinv(P_a)
    return F / np.linalg.norm(F)


def triangulate_points(uv_a_px, uv_b_px, P_a, P_b) -> np.ndarray:
    """(N, 3) points (LPS mm) from corresponding pixels of two views: linear least squares (DLT: the
    rows ``u P[2] - P[0]``, ``v P[2] - P[1]`` of both views, each scaled to unit norm over its first
    three columns; the normal equations solved per point, compiled: ``kernels.triangulate_dlt``)."""
    return kernels.triangulate_dlt(uv_a_px, uv_b_px, P_a, P_b)


def _resample(uv: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """``uv`` resampled every ~``step`` along its arclength, and the arclengths (compiled)."""
    return kernels.resample_polyline(uv, step)


class TwoViewContext:
    """What does not change from frame to frame: both projections, ``F``, the lumen lookup."""

    def __init__(self, tree, carms: tuple[CArm, CArm], pose: Pose, *, registration_covariance=None,
                 options: TwoViewOptions | None = None):
        self.tree, self.carms, self.pose = tree, tuple(carms), pose
        self.options = options or TwoViewOptions()
        self.P = tuple(c.projection_matrix(pose) for c in self.carms)
        self.F = fundamental_matrix(*self.P)
        dense, orig = tree.densified(0.5)
        self.dense_pts = dense.points_lps_mm
        self.dense_rad = dense.radius_mm
        self.dense_orig = orig
        self.kd = kernels.NearestGrid(self.dense_pts, 4.0)  # the nearest dense tree point (exact)
        self.s_root = tree.arclength_from_root_mm
        self.cov = None if registration_covariance is None else np.asarray(registration_covariance, float)
        # each plane's camera: R_c (rows e_u, e_v, d) and t_c of x_cam = R_c X + t_c (camera frame, mm)
        self.cams = []
        for c in self.carms:
            A = c.axes
            Rc = A @ pose.R
            tc = A @ (pose.t - c.source_room_mm)
            self.cams.append((Rc, tc, c.focal_px, c.principal_point_px))
        self.pixel_at_iso_mm = float(np.mean([c.pixel_at_iso_mm for c in self.carms]))
        # a 3D step of length L projects to lengths whose squares sum to at least L^2 sin^2(angle
        # between the beams): the bound of the pairwise term
        cos_sep = abs(float(self.carms[0].beam_direction @ self.carms[1].beam_direction))
        self.spread = 1.0 / max(np.sqrt(1.0 - cos_sep**2), 0.2)

    def project(self, k: int, X) -> np.ndarray:
        Rc, tc, f, c = self.cams[k]
        xc = X @ Rc.T + tc
        return f * xc[:, :2] / xc[:, 2:3] + c

    def jacobian(self, k: int, X) -> np.ndarray:
        """(N, 2, 3) d(u, v)/dX in plane k."""
        Rc, tc, f, _ = self.cams[k]
        xc = X @ Rc.T + tc
        z = xc[:, 2]
        J = np.zeros((len(X), 2, 3))
        J[:, 0, 0] = J[:, 1, 1] = f / z
        J[:, 0, 2] = -f * xc[:, 0] / z**2
        J[:, 1, 2] = -f * xc[:, 1] / z**2
        return J @ Rc

    def outside_lumen_mm(self, X) -> np.ndarray:
        d, i = self.kd.query(X)
        return np.maximum(d - self.dense_rad[i], 0.0)

    def vessel_cost(self, X) -> np.ndarray:
        """The vessel prior's unary cost of points ``X``: outside the lumen (``sigma_lumen_mm``), and,
        weakly, off the centerline relative to the radius (``centerline_weight``): it breaks the
        ties between matches that are all inside the lumen."""
        opt = self.options
        d, i = self.kd.query(X)
        r = np.maximum(self.dense_rad[i], 0.3)
        return (np.maximum(d - r, 0.0) / opt.sigma_lumen_mm) ** 2 + opt.centerline_weight * np.minimum(d / r, 1.0) ** 2


def _candidates(F: np.ndarray, a: np.ndarray, b: np.ndarray, opt: TwoViewOptions):
    """Per master sample ``a_i``: the positions along the other plane's wire ``b`` (fractional
    sample index) where its epipolar line ``F a_i`` crosses or touches it, and ``|sin|`` of the
    angle between ``b`` and the line there. Returns flat arrays ``(i, j, sin)``: the crossings (sign
    changes of the signed distance along ``b``, interpolated), then the touches (local minima of
    ``|d|`` below ``touch_px`` without a crossing beside them), compiled (``kernels.epipolar_candidates``)."""
    return kernels.epipolar_candidates(F, a, b, touch_px=opt.touch_px)


def _interp(b: np.ndarray, j: np.ndarray) -> np.ndarray:
    j0 = np.clip(np.floor(j).astype(int), 0, len(b) - 1)
    j1 = np.minimum(j0 + 1, len(b) - 1)
    f = (j - j0)[:, None]
    return (1 - f) * b[j0] + f * b[j1]



def _viterbi(n: int, ia, jb, X, unary, step_mm: float, direction: int, opt: TwoViewOptions, *,
             px_other_mm: float, spread: float):
    """One candidate per master sample on one chain, minimising unary + pairwise costs.

    The chain may start late and end early (``skip_cost`` per master sample left out) and jump
    over up to ``max_gap`` samples inside (the same cost each): a gap keeps the continuity with
    the last matched sample (its pairwise term spans the gap), so a wrong stretch cannot hide
    behind one.

    The pairwise cost from sample ``i - g`` to ``i`` (a gap of ``g - 1``): a 3D step and its two
    projections must agree: the step along the other plane's wire cannot exceed the 3D step (a
    jump to another part of that wire does), and the 3D step cannot exceed what both projections
    allow (steps in mm at the isocentre, times ``spread``); beyond ``step_tolerance_mm`` it costs
    ``(excess / sigma_step_mm)^2``; moving back along the other wire by more than ``back_px`` is
    forbidden. Per sample the ``max_candidates`` lowest unary costs compete. Compiled
    (``kernels.two_view_viterbi``).

    Returns ``(chosen, cost)``: the candidate index per sample (-1: left out) and the chain's cost."""
    return kernels.two_view_viterbi(n, ia, jb, X, unary, step_mm=step_mm, direction=direction,
                                    max_candidates=opt.max_candidates, max_gap=opt.max_gap, dense_px=opt.dense_px,
                                    step_tolerance_mm=opt.step_tolerance_mm, sigma_step_mm=opt.sigma_step_mm,
                                    back_px=opt.back_px, skip_cost=opt.skip_cost, px_other_mm=px_other_mm,
                                    spread=spread)


def _weighted_pspline(x, Y, w, lam: float, knot: float, camera) -> np.ndarray:
    """The single-view reconstruction's P-spline (``smoothing.fit_pspline``) with weights ``w``:
    the fitted values of ``Y (M, 3)`` at ``x (M,)``, in two compiled calls (the system, then
    ``kernels.penalised_fit``'s banded Cholesky solve; its projection error into ``camera``, one
    plane's ``(Rc, tc, focal_px, principal_point_px)``, is not used)."""
    _, D, first, ab, BtY = pspline_system(x, Y, knot=knot, weights=w)
    Rc, tc, f, c = camera
    Xs, _, _ = kernels.penalised_fit(D, first, ab, BtY, lam=lam, uv_px=np.zeros((len(x), 2)), Rc=Rc, tc=tc,
                                     focal_px=f, principal_point_px=c)
    return Xs


def _polyline_distance_px(uv: np.ndarray, curve: np.ndarray) -> np.ndarray:
    dense, _ = _resample(curve, 0.25) if len(curve) > 1 else (curve, None)
    return kernels.NearestGrid(dense, 2.0).query(uv)[0]


def projection_error_px(ctx: "TwoViewContext", k: int, points_lps_mm, wire_uv_px) -> float:
    """Mean distance (px) of the 3D wire ``points_lps_mm (N, 3)`` projected into plane ``k`` (0: A,
    1: B) to that plane's 2D wire ``wire_uv_px (M, 2)``: the measure of ``TwoViewWire.projection_error_px``.
    NaN when either is empty."""
    X = np.asarray(points_lps_mm, float).reshape(-1, 3)
    uv = np.asarray(wire_uv_px, float).reshape(-1, 2)
    if len(X) == 0 or len(uv) == 0:
        return float("nan")
    return float(_polyline_distance_px(ctx.project(int(k), X), uv).mean())


def _direction(ia: np.ndarray, jb: np.ndarray) -> int:
    """+1 / -1 when the samples with a single candidate walk the other wire clearly forwards /
    backwards (rank correlation above ``0.8``), else 0 (try both)."""
    counts = np.bincount(ia)
    single = counts[ia] == 1
    if single.sum() < 8:
        return 0
    x, y = ia[single], jb[single]
    rx, ry = np.argsort(np.argsort(x)), np.argsort(np.argsort(y))
    r = float(np.corrcoef(rx, ry)[0, 1])
    return 1 if r > 0.8 else -1 if r < -0.8 else 0


def _one_way(ctx: TwoViewContext, master: int, m_uv, o_uv, direction_hint=None):
    """Match the master plane's samples to the other plane's wire; returns per match the master
    and other arclengths (px), the 3D point, the conditioning ``|sin|``; and the Viterbi's
    direction and cost."""
    opt = ctx.options
    m, sm = _resample(m_uv, opt.step_px)
    o, so = _resample(o_uv, opt.dense_px)
    F = ctx.F if master == 0 else ctx.F.T
    ia, jb, sin_ang = _candidates(F, m, o, opt)
    if len(ia) == 0:
        return None
    uo = _interp(o, jb)
    X = triangulate_points(m[ia], uo, *ctx.P) if master == 0 else triangulate_points(uo, m[ia], *ctx.P)
    unary = ctx.vessel_cost(X)
    step_mm = opt.step_px * ctx.carms[master].pixel_at_iso_mm
    px_other_mm = ctx.carms[1 - master].pixel_at_iso_mm
    best = None
    if direction_hint is None:
        direction_hint = _direction(ia, jb)
    for direction in ((1, -1) if direction_hint == 0 else (direction_hint,)):
        chosen, cost = _viterbi(len(m), ia, jb, X, unary, step_mm, direction, opt, px_other_mm=px_other_mm,
                                spread=ctx.spread)
        if best is None or cost < best[1]:
            best = (chosen, cost, direction)
    chosen, cost, direction = best
    keep = chosen >= 0
    c = chosen[keep]
    s_other = np.interp(jb[c], np.arange(len(so)), so)
    return dict(s_master=sm[keep], s_other=s_other, X=X[c], sin=sin_ang[c], frac=float(keep.mean()),
                direction=direction, cost=cost, L_master=float(sm[-1]), L_other=float(so[-1]))


def triangulate_wire(wire_a_uv_px, wire_b_uv_px, ctx: TwoViewContext) -> TwoViewWire:
    """The 3D wire from plane A's and plane B's ordered 2D wires (see the module docstring).

    Both planes in turn are the master (each sample of its wire is matched on the other's wire),
    so a stretch foreshortened in one plane is sampled by the other. Every match has an arclength
    along both 2D wires; their sum (B's taken in A's direction) orders the merged matches along
    the wire.

    Parameters
    ----------
    wire_a_uv_px, wire_b_uv_px : (N, 2), (M, 2) ndarray of float
        Ordered 2D wires (px); plane A's order (proximal -> distal) is the output's.
    ctx : TwoViewContext
        Both planes at the registered pose, and the vessel tree.

    Returns
    -------
    TwoViewWire
        ``wire3d`` falsy (with the reason) when too little of the wire could be matched.
    """
    t0 = time.perf_counter()
    opt = ctx.options
    ua = np.asarray(wire_a_uv_px, float).reshape(-1, 2)
    ub = np.asarray(wire_b_uv_px, float).reshape(-1, 2)
    if len(ua) < 2 or len(ub) < 2 or not (np.all(np.isfinite(ua)) and np.all(np.isfinite(ub))):
        raise InputError("triangulate_wire: each plane's wire must have >= 2 finite (u, v) points")

    def failed(msg, frac=0.0):
        return TwoViewWire(Wire3D.failed(msg, seconds=time.perf_counter() - t0, method="biplane"),
                           (float("nan"), float("nan")), frac, False)

    ra = _one_way(ctx, 0, ua, ub)
    if ra is None:
        return failed("no epipolar correspondence between the planes' wires")
    direction = ra["direction"]
    rb = _one_way(ctx, 1, ub, ua, direction_hint=direction)
    frac = ra["frac"]
    if len(ra["X"]) < opt.min_points or frac < opt.min_matched:
        return failed(f"only {100 * frac:.0f}% of plane A's wire has an epipolar partner on plane B's wire "
                      f"(need {100 * opt.min_matched:.0f}%)", frac)
    # merge: position along the wire = arclength in A + arclength in B (in A's direction)
    s_a = [ra["s_master"]]
    s_b = [ra["s_other"]]
    X = [ra["X"]]
    sin = [ra["sin"]]
    if rb is not None and len(rb["X"]):
        s_a.append(rb["s_other"])
        s_b.append(rb["s_master"])
        X.append(rb["X"])
        sin.append(rb["sin"])
    s_a, s_b, X, sin = (np.concatenate(v) for v in (s_a, s_b, X, sin))
    L_a, L_b = ra["L_master"], ra["L_other"]
    s_b = s_b if direction > 0 else L_b - s_b  # B's arclength in A's direction
    key = s_a + s_b
    order = np.argsort(key, kind="stable")
    key, X, sin, s_a, s_b = key[order], X[order], sin[order], s_a[order], s_b[order]
    # drop exact duplicates of the key (a spline needs increasing x)
    keep = np.r_[True, np.diff(key) > 1e-6]
    key, X, sin, s_a, s_b = key[keep], X[keep], sin[keep], s_a[keep], s_b[keep]
    w = np.clip(sin, 0.05, 1.0) ** 2
    n_outliers = 0
    if len(key) >= 5 and key[-1] - key[0] > 4 * opt.knot_px:
        lam = opt.smoothing_lambda
        Xs = _weighted_pspline(key, X, w, lam, opt.knot_px, ctx.cams[0])
        # one robust pass: matches far from the smooth curve (a wrong crossing that the Viterbi's
        # skip did not catch) are dropped and the curve fitted again
        r = np.linalg.norm(X - Xs, axis=1)
        out = r > max(opt.outlier_mm, 4.0 * 1.4826 * float(np.median(r)))
        n_outliers = int(out.sum())
        if 0 < n_outliers <= 0.3 * len(key) and len(key) - n_outliers >= 5:
            key, X, w, s_a, s_b = key[~out], X[~out], w[~out], s_a[~out], s_b[~out]
            Xs = _weighted_pspline(key, X, w, lam, opt.knot_px, ctx.cams[0])
    else:
        Xs = X.copy()
    # resample the output along the 3D arclength (~ step_px at the isocentre)
    arc = arclength(Xs)
    step = opt.step_px * ctx.pixel_at_iso_mm
    if arc[-1] > step:
        n_out = max(int(np.ceil(arc[-1] / step)) + 1, 2)
        sa = np.linspace(0.0, arc[-1], n_out)
        Xs = np.column_stack([np.interp(sa, arc, Xs[:, d]) for d in range(3)])
    tan3 = tangents(Xs)
    # uncertainty: both views' information across their 2D wires, summed; inverted across the 3D wire
    # (plus the registration covariance through the pose), compiled
    G = pose_jacobian(ctx.pose, Xs) if ctx.cov is not None else None
    cov, unc = kernels.two_view_covariance(Xs, tan3, ctx.cams, sigma_2d_px=opt.sigma_2d_px, pose_jacobians=G,
                                           registration_covariance=ctx.cov)
    perr = tuple(projection_error_px(ctx, k, Xs, u) for k, u in ((0, ua), (1, ub)))
    arc = arclength(Xs)
    _, i = ctx.kd.query(Xs)
    tree_ids = ctx.dense_orig[i]
    rise = float(ctx.s_root[tree_ids[-1]] - ctx.s_root[tree_ids[0]])
    ok = bool(max(perr) <= opt.max_reprojection_px and np.all(np.isfinite(Xs)))
    msg = (f"two views: {100 * frac:.0f}% of plane A's wire matched on plane B's"
           + ("" if direction > 0 else " (plane B's 2D order reversed)"))
    if not ok:
        msg = f"two views: projection error {max(perr):.2f} px exceeds {opt.max_reprojection_px} px"
    w3 = Wire3D(Xs, unc, float(arc[-1]), float(np.mean(perr)), ok, msg, tree_ids, arc, curvature(Xs),
                time.perf_counter() - t0, "biplane", cov, False, rise)
    gaps = (float(L_a - s_a.max()), float(L_b - s_b.max()))
    return TwoViewWire(w3, perr, frac, direction < 0, gaps)


def extend_distal(tv: TwoViewWire, wire_a_uv_px, wire_b_uv_px, ctx: TwoViewContext, single_view) -> TwoViewWire:
    """The two-view wire continued beyond its tip where only one plane shows the wire's distal part
    (it leaves the other plane's field of view, or the other plane's 2D wire stops short).

    ``single_view(k, uv)`` is plane k's single-view reconstruction (vessel prior) of its 2D wire
    ``uv`` in plane A's order; its points beyond the two-view tip (along plane k's 2D wire) are
    appended, moved along plane k's rays so that they join the two-view tip (their projection in
    plane k does not change), with their own uncertainty. The message says so. Returns ``tv``
    unchanged when no plane shows more than ``extend_min_px`` beyond the tip."""
    opt = ctx.options
    if not tv or not np.all(np.isfinite(tv.distal_gap_px)):
        return tv
    k = int(np.argmax(tv.distal_gap_px))
    if tv.distal_gap_px[k] < opt.extend_min_px:
        return tv
    uv = np.asarray(wire_a_uv_px if k == 0 else wire_b_uv_px, float).reshape(-1, 2)
    if k == 1 and tv.b_reversed:
        uv = uv[::-1]
    w = single_view(k, uv)
    plane = "AB"[k]
    W = tv.wire3d
    if not w:
        return _with_message(tv, f"{W.message}; the distal {tv.distal_gap_px[k]:.0f} px that only plane {plane} shows "
                                 f"are left out (its single-view reconstruction failed: {w.message})")
    dense, s = _resample(uv, 0.5)
    s_last = float(s[-1]) - tv.distal_gap_px[k]
    proj = ctx.project(k, w.points_lps_mm)
    d, j = cKDTree(dense).query(proj)
    s_w = s[j]
    beyond = np.flatnonzero((s_w > s_last + 1.0) & (d < 2.0))
    if len(beyond) < 2:
        return tv
    beyond = beyond[np.argsort(s_w[beyond], kind="stable")]
    src = ctx.pose.inverse().apply(ctx.carms[k].source_room_mm[None])[0]
    tip = W.points_lps_mm[-1]
    junction = w.points_lps_mm[int(np.argmin(np.abs(s_w - s_last)))]
    ray = (tip - src) / np.linalg.norm(tip - src)
    ext = w.points_lps_mm[beyond] + float((tip - junction) @ ray) * ray
    X = np.vstack([W.points_lps_mm, ext])
    unc = np.r_[W.uncertainty_mm, np.asarray(w.uncertainty_mm)[beyond]]
    cov = np.concatenate([W.covariance_mm2, np.asarray(w.covariance_mm2)[beyond]]) \
        if len(w.covariance_mm2) == len(w.points_lps_mm) else np.zeros((0, 3, 3))
    arc = arclength(X)
    ids = np.r_[W.tree_point_ids, np.asarray(w.tree_point_ids)[beyond]]
    ext_mm = float(arc[-1] - W.arclength_mm[-1])
    rise = float(ctx.s_root[ids[-1]] - ctx.s_root[ids[0]]) if ids[-1] >= 0 and ids[0] >= 0 else W.tree_rise_mm
    msg = (f"{W.message}; the distal {ext_mm:.1f} mm from plane {plane} alone (plane {'BA'[k]} does not show it: "
           "its depth is the vessel prior's)")
    perr = list(tv.projection_error_px)
    w3 = Wire3D(X, unc, float(arc[-1]), W.projection_error_px, W.success, msg, ids, arc, curvature(X),
                W.seconds + w.seconds, "biplane", cov, False, rise)
    return TwoViewWire(w3, tuple(perr), tv.matched_fraction, tv.b_reversed, tv.distal_gap_px, ext_mm, k, w, uv)


def _with_message(tv: TwoViewWire, message: str) -> TwoViewWire:
    from dataclasses import replace

    return replace(tv, wire3d=replace(tv.wire3d, message=message))

