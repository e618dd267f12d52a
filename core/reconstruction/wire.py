"""3D guidewire reconstruction from one X-ray view, a registered pose and the CTA vessel tree.

One view gives no depth. The depth comes from the vessel prior: the wire is inside the lumen.

Default method (``ReconMethod.VESSEL``)
    1. Per pose, a :class:`ReconstructionContext` is built once and cached: the vessel tree is
       densified (about 3 px between projected points), projected (pixel, depth, projected
       radius), indexed by a 2D KD-tree, and its branch structure is turned into tables that give
       the lowest common ancestor, and so the geodesic distance, of any two points in O(1).
    2. Anchors every ``dp_step_px`` along the ordered 2D wire. Candidates of an anchor: the tree
       points whose projection lies within the projected lumen radius (+ a margin) of it.
    3. Viterbi over the anchors: the unary cost is how far the anchor lies outside the projected
       lumen; the pairwise cost asks the tree move between consecutive choices to be *connected*
       (geodesic ~ Euclidean distance, so no jump to an overlapping vessel or across a crossing
       of the wire with itself), to reproduce the 2D step (which makes foreshortening consistent)
       and to be distal (retreats towards the root are penalised). A small start cost prefers the
       proximal candidate. In tracking mode (``previous``) an extra unary cost keeps the choices
       on the previous frame's root -> tip path: advancing beyond the old tip or retracting is
       free, entering a side branch costs in proportion to the distance into it. A path that
       ends nearer the root than it starts triggers a try on the reversed 2D wire (the output is
       always proximal -> distal).
    4. The chosen nodes are joined along the tree into one path. Each 2D wire point's ray is
       intersected with the nearby path segments (ray-segment closest approach, preferring the
       path position interpolated between the anchors). The feasible depths are the chord of the
       ray through the tube the wire's centre can occupy (radius minus ``wire_clearance_mm``).
       Inside that chord the point is put at the depth of the expected wire position: the
       centerline moved towards the outer side of bends (``outer_bend_prior``; a wire pushed
       through a curved vessel rides its outer wall), i.e. the chord's middle on straight parts.
    5. A penalised cubic B-spline (P-spline, the paper's smoothness weight lambda = 0.1) smooths
       the 3D points; lambda is halved until the projection stays within ``max_projection_px`` of
       the input wire (mean) and 2.5x that (max).
    6. Uncertainty per point: a 3x3 covariance ``Sigma`` of the point's error *across the wire*
       (its distance to the true wire; a slide along the wire is not an error of the wire's
       shape), reported as ``uncertainty_mm = sqrt(trace Sigma)``, the RMS 3D distance to the
       true wire it predicts. The point is on its pixel's ray and inside the CTA lumen, so an
       error source only counts through the part the lumen does not absorb. With ``d`` the ray,
       ``t`` the wire tangent, ``n = d x t / |d x t|`` (normal to ray and vessel) and
       ``q = t x n`` (across the vessel, in the plane of ray and vessel):

       * **Ray shift** ``S``: the paper's ``J+ (sigma_geo^2 I + sigma_img^2 gI gI^T) J+^T``
         (``J+`` the pseudo-inverse of the 2x3 projection Jacobian, ``gI`` the image gradient at
         the pixel when ``image`` is given) plus, if given, the registration covariance pushed
         through the pose (``dX = R^T (-dt + [x]x dphi)`` for a left perturbation): both move the
         ray in CTA coordinates while the vessel stays. It enters as ``A S A^T`` with
         ``A = n n^T + g q m^T`` (``m = n x d``): a shift along ``n`` moves the point across the
         vessel in full; a shift along the ray changes nothing; a shift along ``m`` makes the ray
         meet the vessel further along, i.e. the point *slides along the vessel*, except for the
         fraction ``g = cos / (cos^2 + k^2 sin^2)`` (angle between ray and vessel,
         ``k = _ALONG_MM / _DIST_MM``) that the weighted closest approach of step 4 leaves
         across it when the vessel runs along the beam (exact for that quadratic choice).
       * **Lumen**: the wire's offset from its expected position in the cross-section, along
         ``q``, std ``lumen_spread * w`` with ``w = sqrt(rho^2 - dist^2)`` the half width of the
         room the wire's centre has where the ray crosses (``rho`` = radius minus clearance;
         uniform over a diameter would be 0.58, the default 0.3 is calibrated on the simulator's
         wires, which ride the outer side of bends and wander 0.2-0.6 ``rho`` elsewhere), plus
         the CTA centerline error ``sigma_centerline_mm`` along ``q``.
       * **Off the lumen**: a ray that misses the path's tube by ``miss`` adds ``miss^2`` in both
         directions across the wire.
       * **Branch ambiguity** (the hard case a local model misses: a wrong branch at the tip, an
         overlap): from the Viterbi min-marginals, each anchor's other candidates weighted by
         ``exp(-extra path cost / ambiguity_scale)``; the weighted second moment of their
         positions about the chosen point (candidates on the same straight stretch of vessel
         excluded: they are a slide), across the wire.

       Calibration (``scripts/bench_reconstruction.py``, 30 held-out simulator sequences): on
       oracle, realistic and really registered inputs the pooled RMS(error) / RMS(sigma) is
       0.8-1.1 and 95-98 % of the points are within 2 sigma. The former model (chord / sqrt(12)
       along the ray and the full ray shift) was ~2x too large (ratio 0.45-0.55, 99.5-99.8 %
       within 2 sigma): the lumen absorbs the depth part of the pose error and the along-vessel
       part of both the pose and the image error. Limits: a wrong branch with no competing
       candidate under the 2D wire (e.g. chosen because of a registration error) is not seen by
       the ambiguity term (those frames: ~91 % within 2 sigma, RMS ratio ~2.4), and the position
       *along* the wire (the tip's advance) is not part of ``uncertainty_mm``.
    The unconstrained methods (``PAPER``, ``BSPLINE``) keep the full propagation: the depth
    interval along the ray (``chord / sqrt(12)``), the full ray shift ``S`` and an isotropic term
    for a distance outside the projected lumen.

``ReconMethod.PAPER`` applies the paper's closed-form depth literally (it is a two-view
triangulation formula; with one view and the registration's R, t it gives an arbitrary depth),
``ReconMethod.BSPLINE`` is the B-spline baseline: a 2D B-spline fit lifted to the depth of the
nearest projected centerline point, without connectivity.
"""
from __future__ import annotations

import copy
import time
from collections import OrderedDict
from dataclasses import dataclass, field, fields, replace

import numpy as np
from guidewire3d import kernels
from guidewire3d.errors import InputError, ReconstructionError
from guidewire3d.geometry import CArm, Pose
from guidewire3d.methods import ReconMethod
from guidewire3d.vesseltree import VesselTree
from scipy.interpolate import BSpline
from scipy.linalg import solveh_banded
from scipy.spatial import cKDTree

__all__ = [
    "ReconMethod",
    "ReconOptions",
    "Wire3D",
    "ReconstructionContext",
    "build_context",
    "reconstruct_wire",
    "paper_depth_mm",
    "WireTracker",
]




@dataclass(frozen=True)
class ReconOptions:
    """Tuning of the reconstruction (defaults are the ones benchmarked)."""

    densify_px: float = 3.0  #: target projected spacing of the (densified) tree points
    densify_radius: float = 0.4  #: ... but at least this fraction of the vessel radius
    dp_step_px: float = 5.0  #: spacing of the Viterbi anchors along the 2D wire
    candidates: int = 16  #: at most this many tree points per anchor
    margin_px: float = 5.0  #: candidates may lie this far outside the projected lumen
    sigma_outside_px: float = 1.5  #: unary: distance outside the projected lumen
    sigma_step_px: float = 3.0  #: pairwise: 2D step of the tree point vs of the wire
    sigma_jump_mm: float = 0.5  #: pairwise: geodesic minus Euclidean distance (connectivity)
    sigma_retreat_mm: float = 1.0  #: pairwise: distance moved towards the root
    skip_cost: float = 15.0  #: cost per distal anchor left unexplained when the path ends early
    start_cost_per_mm: float = 0.002  #: prefers the proximal candidate at the first anchor
    reverse_mm: float = 5.0  #: a chosen path ending this much nearer the root triggers a reversed try
    min_coverage: float = 0.6  #: fraction of anchors that must have a candidate
    track_tolerance_mm: float = 1.0  #: tracking: free distance off the previous root->tip path
    track_confirm_mm: float = 10.0  #: tracking: the last this-many mm of the previous path are not a prior
    sigma_track_mm: float = 2.0  #: tracking: cost per this many mm further off it
    outer_bend_prior: bool = True  #: place the depth towards the outer side of bends (wire rides it)
    outer_bend_mm: float = 20.0  #: full hug where the radius of curvature is below this
    outer_bend_fraction: float = 0.7  #: ... of this fraction of the room the wire has
    chord_clearance: bool = True  #: the depth interval is the chord of radius - wire_clearance_mm
    bend_scale_mm: float = 5.0  #: centerline smoothing for its curvature
    wire_clearance_mm: float = 0.35  #: wire radius + margin kept from the wall (chord and prior)
    smoothing_lambda: float = 0.1  #: paper's smoothness weight (P-spline, see module doc)
    knot_px: float = 5.0  #: spline knot spacing along the 2D wire
    max_projection_px: float = 1.0  #: the smoothed wire stays within this (mean) of the 2D wire
    fail_projection_px: float = 3.0  #: a result worse than this (mean) is a failure
    sigma_geo_px: float = 2.0  #: paper's geometric uncertainty
    sigma_img: float = 0.1  #: paper's image uncertainty (scales the image gradient)
    lumen_spread: float = 0.3  #: std of the wire's offset from its expected lumen position / the room it has
    sigma_centerline_mm: float = 0.2  #: CTA centerline error across the vessel (per axis)
    ambiguity_scale: float = 2.0  #: weight exp(-extra path cost / this) of other candidates (0: off)

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool):
                continue
            if not np.isfinite(v) or v < 0 or (v == 0 and f.name not in _MAY_BE_ZERO):
                raise InputError(f"ReconOptions.{f.name} must be a finite positive number, got {v!r}")
        if int(self.candidates) != self.candidates or self.candidates < 1:
            raise InputError(f"ReconOptions.candidates must be a positive integer, got {self.candidates!r}")


_MAY_BE_ZERO = {"start_cost_per_mm", "track_tolerance_mm", "track_confirm_mm",
                "margin_px", "wire_clearance_mm", "sigma_img", "min_coverage", "ambiguity_scale",
                "lumen_spread", "sigma_centerline_mm"}


# --------------------------------------------------------------------------------------------
# result
# --------------------------------------------------------------------------------------------
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
        (the predicted RMS 3D distance to the true wire, mm; see the module doc, step 6).
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

    def __post_init__(self):
        object.__setattr__(self, "points_lps_mm", _ro(np.reshape(self.points_lps_mm, (-1, 3))))
        for name in ("uncertainty_mm", "arclength_mm", "curvature_per_mm"):
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
        }


# --------------------------------------------------------------------------------------------
# per-pose context
# --------------------------------------------------------------------------------------------
class ReconstructionContext:
    """Everything that depends only on (tree, C-arm, pose), computed once.

    Build it with :func:`build_context` (cached) and reuse it for every frame.
    """

    def __init__(self, pose: Pose, carm: CArm, tree: VesselTree, *, options: ReconOptions | None = None):
        if not isinstance(tree, VesselTree):
            raise InputError(f"reconstruction: tree must be a VesselTree, got {type(tree).__name__}")
        if not isinstance(pose, Pose) or not isinstance(carm, CArm):
            raise InputError("reconstruction: pose must be a Pose and carm a CArm")
        self.pose, self.carm, self.tree = pose, carm, tree
        self.options = opt = options or ReconOptions()
        # candidate spacing: ~densify_px in the image, coarser in wide vessels (0.4 radius)
        step_mm = np.maximum(max(opt.densify_px * carm.pixel_at_iso_mm, 0.05), opt.densify_radius * tree.radius_mm)
        dense, self.orig_id = tree.densified(step_mm)
        self.dense = dense
        self.points = dense.points_lps_mm
        self.radius = dense.radius_mm
        self.s = dense.arclength_from_root_mm
        self.focal = carm.focal_px
        # Viterbi candidates: a thinned subset (one per step_mm of arclength, plus every node)
        step_d = np.maximum(max(opt.densify_px * carm.pixel_at_iso_mm, 0.05), opt.densify_radius * self.radius)
        par = dense.parent
        q = np.floor(self.s / step_d)
        qp = np.floor(self.s[np.maximum(par, 0)] / step_d)
        self.cand_ids = np.flatnonzero((par < 0) | (q != qp) | (dense.degree != 2))
        self._project(pose)
        # --- branch tables: O(1) lowest common ancestor of two points ---------------------
        br = dense.branches
        B = len(br)
        self.point_branch = dense.point_branch
        bpar = np.array([b.parent for b in br], dtype=np.int64)
        end_s = np.array([self.s[b.point_ids[-1]] for b in br])
        chains = []
        for b in range(B):
            c = [b]
            while bpar[c[-1]] >= 0:
                c.append(int(bpar[c[-1]]))
            chains.append(c)  # b, parent, ..., root-level branch
        anc = np.zeros((B, B), bool)  # anc[a, b]: a is a strict ancestor branch of b
        lca_s = np.zeros((B, B))
        sets = [set(c) for c in chains]
        for b in range(B):
            anc[chains[b][1:], b] = True
        for a in range(B):
            for b in range(B):
                if a == b or anc[a, b] or anc[b, a]:
                    continue
                common = [c for c in chains[a] if c in sets[b]]
                lca_s[a, b] = end_s[common[0]] if common else 0.0
        # for branches on one root path the LCA is the more proximal of the two points: +inf here
        lca_s[anc | anc.T] = np.inf
        np.fill_diagonal(lca_s, np.inf)
        self.branch_lca_s = lca_s
        # root paths per branch, index-aligned by depth
        self.rootpath = []
        for b in range(B):
            ids = br[b].point_ids
            self.rootpath.append(ids.copy() if bpar[b] < 0 else np.r_[self.rootpath[bpar[b]], ids[1:]])
        self.pos_in_branch = np.zeros(dense.n_points, np.int64)
        for b in br:
            self.pos_in_branch[b.point_ids[1:]] = np.arange(1, len(b.point_ids))
        self.pos_in_branch[dense.root] = 0
        self._branch_len = np.array([len(b.point_ids) for b in br])
        self.radius_eff = (np.maximum(self.radius - opt.wire_clearance_mm, 0.5 * self.radius)
                           if opt.chord_clearance else self.radius)
        self.outer_offset = self._outer_bend_offset(opt) if opt.outer_bend_prior else np.zeros_like(self.points)
        self._scratch = -np.ones(dense.n_points, np.int64)

    def _project(self, pose: Pose) -> None:
        """The attributes that depend on the pose: the tree in the image and the source."""
        self.pose = pose
        uv, z = self.carm.project(self.points, pose, return_depth=True)
        if np.any(z <= 0):
            raise ReconstructionError("reconstruction: part of the vessel tree lies behind the X-ray source")
        self.uv, self.depth = uv, z
        self.r_px = self.radius * self.focal / z
        self.kd2 = cKDTree(uv[self.cand_ids])
        self.r_px_max = float(self.r_px.max())
        Rc, tc = self.carm.extrinsics(pose)
        self.Rc, self.tc = Rc, tc
        self.source = -Rc.T @ tc
        self.px_mm = float(np.median(z)) / self.focal  # mm per px at the tree's depth

    def with_pose(self, pose: Pose) -> "ReconstructionContext":
        """The same tree tables (smoothing, densification, branches, bend offsets: none depends on
        the pose) seen at another pose; what a moving patient changes per frame."""
        ctx = copy.copy(self)
        ctx._project(pose)
        ctx._scratch = -np.ones(len(self.points), np.int64)
        return ctx

    def _outer_bend_offset(self, opt: ReconOptions) -> np.ndarray:
        """(N, 3) expected wire offset from the centerline: towards the outer side of bends.

        ``-n * rho * min(1, kappa * outer_bend_mm)`` with ``n`` the principal normal (towards the
        inner side), ``kappa`` the curvature of the centerline smoothed over ``bend_scale_mm`` and
        ``rho = radius - wire_clearance_mm`` the room the wire has.
        """
        from scipy.ndimage import gaussian_filter1d

        k = np.zeros_like(self.points)
        for b, ids in enumerate(self.rootpath):
            own = self._branch_len[b]
            take = ids[-min(len(ids), own + 40):]  # the branch plus some of its parents for context
            P = self.points[take]
            if len(P) < 5:
                continue
            s = _arclength(P)
            step = max(float(s[-1]) / (len(P) - 1), 1e-6)
            Ps = gaussian_filter1d(P, opt.bend_scale_mm / step, axis=0, mode="nearest")
            T = np.gradient(Ps, s, axis=0)
            T /= np.maximum(np.linalg.norm(T, axis=1, keepdims=True), 1e-12)
            kv = np.gradient(T, s, axis=0)
            kv -= np.sum(kv * T, axis=1, keepdims=True) * T
            k[take[-own:]] = kv[-own:]
        kappa = np.linalg.norm(k, axis=1)
        n = k / np.maximum(kappa, 1e-12)[:, None]
        rho = np.maximum(self.radius - opt.wire_clearance_mm, 0.0)
        return -n * (opt.outer_bend_fraction * rho * np.clip(kappa * opt.outer_bend_mm, 0.0, 1.0))[:, None]

    # --- tree queries ------------------------------------------------------------------------
    def lca_s(self, i, j) -> np.ndarray:
        """Arclength from the root of the lowest common ancestor of points ``i`` and ``j`` (broadcast)."""
        # on one root path: the more proximal point; else the end of the common ancestor branch
        lca = self.branch_lca_s[self.point_branch[i], self.point_branch[j]]
        return np.minimum(np.minimum(self.s[i], self.s[j]), lca)

    def root_path(self, i: int) -> np.ndarray:
        b = self.point_branch[i]
        rp = self.rootpath[b]
        return rp[: len(rp) - self._branch_len[b] + self.pos_in_branch[i] + 1]

    def path(self, i: int, j: int) -> np.ndarray:
        """Dense point ids along the tree from ``i`` to ``j`` (inclusive)."""
        a, b = self.root_path(i), self.root_path(j)
        n = min(len(a), len(b))
        diff = np.flatnonzero(a[:n] != b[:n])
        k = int(diff[0]) if len(diff) else n
        return np.concatenate([a[k - 1 :][::-1], b[k:]])

    # --- geometry --------------------------------------------------------------------------
    def rays(self, uv_px) -> np.ndarray:
        """Unit ray directions (M, 3) in LPS for pixels (M, 2); all rays start at ``self.source``."""
        ray_cam = np.column_stack([(uv_px - self.carm.principal_point_px) / self.focal, np.ones(len(uv_px))])
        d = ray_cam @ self.Rc
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def project(self, X) -> np.ndarray:
        xc = X @ self.Rc.T + self.tc
        return self.focal * xc[:, :2] / xc[:, 2:3] + self.carm.principal_point_px


_CACHE: OrderedDict = OrderedDict()
_CACHE_SIZE = 12  # the benchmark alternates ~8 (pose, tree, options) per frame


def build_context(pose: Pose, carm: CArm, tree: VesselTree, *,
                  options: ReconOptions | None = None) -> ReconstructionContext:
    """The cached :class:`ReconstructionContext` of (pose, carm, tree, options).

    The cache holds the objects themselves (so their ids stay valid) for the last few calls.
    """
    options = options or ReconOptions()
    key = (id(pose), id(carm), id(tree), options)
    hit = _CACHE.get(key)
    if hit is not None and hit.pose is pose and hit.carm is carm and hit.tree is tree:
        _CACHE.move_to_end(key)
        return hit
    # a context of the same tree and view at another pose (a tracked patient) lends its tree tables
    base = next((c for c in reversed(_CACHE.values()) if c.carm is carm and c.tree is tree and c.options == options),
                None)
    ctx = base.with_pose(pose) if base is not None else ReconstructionContext(pose, carm, tree, options=options)
    _CACHE[key] = ctx
    while len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return ctx


# --------------------------------------------------------------------------------------------
# pieces
# --------------------------------------------------------------------------------------------
def _arclength(p) -> np.ndarray:
    return np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]


def _pspline(x, Y, lam: float, knot: float, *, weights=None):
    """Penalised cubic B-spline fit of ``Y (M, D)`` over ``x (M,)``: ``(BSpline, design matrix)``.

    Objective: ``mean_m |Y_m - f(x_m)|^2 + lam * mean_k |second difference of coefficients_k|^2``
    (Eilers & Marx P-spline), solved as a banded (bandwidth 3) symmetric system. With ``weights``
    (M,) the mean over m is the weighted one.
    """
    x0, x1 = float(x[0]), float(x[-1])
    nint = max(int(round((x1 - x0) / knot)), 1)
    t = np.r_[[x0] * 3, np.linspace(x0, x1, nint + 1), [x1] * 3]
    Bm = BSpline.design_matrix(np.clip(x, x0, x1), t, 3)
    nb = Bm.shape[1]
    M = len(x)
    # the data weights, summing to 1 (uniform 1/M without weights)
    wn = np.full(M, 1.0 / M) if weights is None else np.asarray(weights, float) / float(np.sum(weights))
    ab = np.zeros((4, nb))  # upper banded form: ab[3 + i - j, j] = A[i, j]
    rows4 = Bm.nnz == 4 * M and np.all(np.diff(Bm.indptr) == 4)
    if rows4:
        D, J = Bm.data.reshape(M, 4), Bm.indices.reshape(M, 4)
        rows4 = bool(np.all(np.diff(J, axis=1) == 1))
    if rows4:
        # B^T W B straight into the banded form (each row of B holds 4 consecutive basis functions)
        for a in range(4):
            for b in range(a, 4):
                ab[3 - (b - a)] += np.bincount(J[:, b], weights=wn * D[:, a] * D[:, b], minlength=nb)[:nb]
        BtY = np.column_stack([np.bincount(J.ravel(), weights=(wn[:, None] * D * Y[:, [d]]).ravel(), minlength=nb)[:nb]
                               for d in range(Y.shape[1])])
    else:
        Bw = Bm.multiply(wn[:, None]).tocsr()
        BtB = (Bm.T @ Bw).tocsr()
        for k in range(4):
            ab[3 - k, k:] = BtB.diagonal(k)
        BtY = np.asarray(Bw.T @ Y)
    w = lam / max(nb - 2, 1)
    # D^T D of the second-difference operator, by diagonals
    p0 = np.full(nb, 6.0)
    p0[[0, -1]] = 1.0
    if nb > 2:
        p0[[1, -2]] = 5.0
    p1 = np.full(nb - 1, -4.0)
    p1[[0, -1]] = -2.0
    if nb >= 3:
        ab[3] += w * p0
        ab[2, 1:] += w * p1
        ab[1, 2:] += w * 1.0
    ab[3] += 1e-12
    coef = solveh_banded(ab, BtY)
    return BSpline(t, coef, 3, extrapolate=True), Bm


def _smooth(ctx: ReconstructionContext, X, uv, *, lam: float, opt: ReconOptions):
    """Smooth 3D points ``X`` (M, 3) keeping their projection near ``uv`` (M, 2)."""
    x = _arclength(uv)
    if len(X) < 5 or x[-1] < 2 * opt.knot_px:
        return X.copy(), lam
    for _ in range(8):
        spl, Bm = _pspline(x, X, lam, opt.knot_px)
        Xs = Bm @ spl.c
        err = np.linalg.norm(ctx.project(Xs) - uv, axis=1)
        if err.mean() <= opt.max_projection_px and err.max() <= 2.5 * opt.max_projection_px:
            return Xs, lam
        lam *= 0.5
    return Xs, lam


def _tangent(X) -> np.ndarray:
    """(N, 3) unit tangents of a polyline (central differences)."""
    if len(X) < 2:
        return np.tile([1.0, 0.0, 0.0], (len(X), 1))
    T = np.gradient(X, axis=0)
    return T / np.maximum(np.linalg.norm(T, axis=1, keepdims=True), 1e-12)


def _curvature(X) -> np.ndarray:
    n = len(X)
    if n < 3:
        return np.zeros(n)
    d1 = np.gradient(X, axis=0)
    d2 = np.gradient(d1, axis=0)
    num = np.linalg.norm(np.cross(d1, d2), axis=1)
    den = np.maximum(np.linalg.norm(d1, axis=1) ** 3, 1e-12)
    return num / den


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


def _projection_jacobian(ctx: ReconstructionContext, X) -> np.ndarray:
    """(M, 2, 3) d(u, v)/dX at LPS points X."""
    xc = X @ ctx.Rc.T + ctx.tc
    z = xc[:, 2]
    J = np.zeros((len(X), 2, 3))
    J[:, 0, 0] = J[:, 1, 1] = ctx.focal / z
    J[:, 0, 2] = -ctx.focal * xc[:, 0] / z**2
    J[:, 1, 2] = -ctx.focal * xc[:, 1] / z**2
    return J @ ctx.Rc


def _ray_shift_covariance(ctx, X, uv, *, image, registration_covariance, opt):
    """(M, 3, 3) covariance of the displacement of each point's ray, at the point (mm^2).

    The paper's ``J+ (sigma_geo^2 I + sigma_img^2 gI gI^T) J+^T`` (a pixel error of the 2D wire
    moves the ray sideways) plus, if given, the registration covariance pushed through the pose
    (``dX = R^T (-dt + [x]x dphi)`` for a left perturbation: the pose error moves the ray in CTA
    coordinates).
    """
    M = len(X)
    J = _projection_jacobian(ctx, X)
    JJt = J @ np.transpose(J, (0, 2, 1))
    Jp = np.transpose(J, (0, 2, 1)) @ np.linalg.inv(JJt)  # (M, 3, 2)
    S2 = np.broadcast_to(opt.sigma_geo_px**2 * np.eye(2), (M, 2, 2)).copy()
    if image is not None:
        g = _image_gradient(image, uv)
        S2 += opt.sigma_img**2 * g[:, :, None] * g[:, None, :]
    cov = Jp @ S2 @ np.transpose(Jp, (0, 2, 1))
    if registration_covariance is not None:
        C = _check_registration_covariance(registration_covariance)
        x_room = ctx.pose.apply(X)
        G = np.zeros((M, 3, 6))
        G[:, :, :3] = -np.eye(3)
        # -phi x x = [x]x phi
        G[:, 0, 4], G[:, 0, 5] = -x_room[:, 2], x_room[:, 1]
        G[:, 1, 3], G[:, 1, 5] = x_room[:, 2], -x_room[:, 0]
        G[:, 2, 3], G[:, 2, 4] = -x_room[:, 1], x_room[:, 0]
        G = ctx.pose.R.T[None] @ G
        cov += G @ C @ np.transpose(G, (0, 2, 1))
    return cov


def _check_registration_covariance(registration_covariance) -> np.ndarray:
    C = np.asarray(registration_covariance, dtype=float)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        raise InputError(f"reconstruction: registration_covariance must be a finite 6x6 matrix, got {C.shape}")
    return C


def _cross(a, b) -> np.ndarray:
    """Row-wise cross product of (M, 3) arrays (faster than np.cross for small M)."""
    a, b = np.broadcast_arrays(a, b)
    return np.column_stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]])


def _outer(a, b=None):
    return a[:, :, None] * (a if b is None else b)[:, None, :]


def _covariance(ctx, X, uv, *, depth_std_mm, extra_iso_mm2, image, registration_covariance, opt):
    """(M, 3, 3) unconstrained covariance (no lumen absorption): depth interval along the ray +
    the full ray shift (paper's propagation + registration) + an isotropic extra term.

    Used by the methods without a lumen constraint (``PAPER``, ``BSPLINE``)."""
    cov = _ray_shift_covariance(ctx, X, uv, image=image, registration_covariance=registration_covariance, opt=opt)
    d = ctx.rays(uv)
    cov += (depth_std_mm**2)[:, None, None] * _outer(d)
    cov += extra_iso_mm2[:, None, None] * np.eye(3)
    return cov


def _image_gradient(image, uv) -> np.ndarray:
    """(M, 2) image gradient (intensities min-max normalised to [0, 1], per px) at the pixels ``uv``."""
    img = np.asarray(image)
    if img.dtype.kind not in "fiub":
        img = img.astype(float)
    if img.ndim != 2:
        raise InputError(f"reconstruction: image must be 2D (rows, cols), got shape {img.shape}")
    # central differences at the wire's pixels only (converted to float there, not the whole frame)
    H, Wd = img.shape
    ui = np.clip(np.rint(uv[:, 0]).astype(int), 1, Wd - 2)
    vi = np.clip(np.rint(uv[:, 1]).astype(int), 1, H - 2)

    def at(v, u):
        return img[v, u].astype(float)

    g = 0.5 * np.column_stack([at(vi, ui + 1) - at(vi, ui - 1), at(vi + 1, ui) - at(vi - 1, ui)])
    if img.dtype.kind == "f":
        lo, hi = float(np.nanmin(img)), float(np.nanmax(img))
    else:
        lo, hi = float(img.min()), float(img.max())
    return g / (hi - lo) if hi > lo else np.zeros_like(g)  # intensities normalised to [0, 1] (paper)


def _covariance_lumen(ctx, X, uv, *, tangent, half_width_mm, miss_mm, image, registration_covariance, opt,
                      ambiguity_mm2=None):
    """(M, 3, 3) covariance of points placed in the lumen (``ReconMethod.VESSEL``), see the module doc.

    ``tangent`` (M, 3): unit wire direction at each point; ``half_width_mm`` (M,): half width,
    across the vessel and in the plane of the ray, of the room the wire's centre has
    (``sqrt(rho^2 - dist^2)``); ``miss_mm`` (M,): how far the ray passes outside that room (0 inside).
    ``A S A^T`` is evaluated through the three scalars ``n^T S n``, ``n^T S m``, ``m^T S m``.
    """
    M = len(X)
    d = ctx.rays(uv)
    t = tangent
    n = _cross(d, t)
    sin = np.linalg.norm(n, axis=1)
    # a ray (nearly) along the vessel: any direction normal to the ray
    alt = _cross(d, np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]]))
    along = sin <= 1e-6
    n = np.where(along[:, None], alt, n)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = np.where(along[:, None], _cross(n, d), t)
    cos = np.abs(np.einsum("mk,mk->m", d, t))
    q = _cross(t, n)  # across the vessel, in the plane of the ray and the vessel
    m = _cross(n, d)  # normal to the ray, in the plane of the ray and the vessel
    # a sideways ray shift along m slides the point along the vessel (no error across the wire)
    # as long as the placement can follow it: the weighted closest approach of _place_on_path
    # leaves the fraction cos / (cos^2 + k^2 sin^2) of it across the vessel, k = along / dist scale
    k2 = (_ALONG_MM / _DIST_MM) ** 2
    gain = cos / np.maximum(cos**2 + k2 * sin**2, 1e-12)
    # ray shift S = J+ S2 J+^T (+ G C G^T): v^T S w = (J+^T v)^T S2 (J+^T w) (+ (G^T v)^T C (G^T w))
    J = _projection_jacobian(ctx, X)
    JJt = J @ np.transpose(J, (0, 2, 1))
    det = JJt[:, 0, 0] * JJt[:, 1, 1] - JJt[:, 0, 1] * JJt[:, 1, 0]
    inv = np.stack([np.stack([JJt[:, 1, 1], -JJt[:, 0, 1]], -1), np.stack([-JJt[:, 1, 0], JJt[:, 0, 0]], -1)], 1)
    inv /= det[:, None, None]
    Jn = np.einsum("mij,mjk,mk->mi", inv, J, n)  # J+^T n (M, 2)
    Jm = np.einsum("mij,mjk,mk->mi", inv, J, m)
    s_nn = opt.sigma_geo_px**2 * np.einsum("mi,mi->m", Jn, Jn)
    s_nm = opt.sigma_geo_px**2 * np.einsum("mi,mi->m", Jn, Jm)
    s_mm = opt.sigma_geo_px**2 * np.einsum("mi,mi->m", Jm, Jm)
    if image is not None:
        g = _image_gradient(image, uv)
        gn, gm = np.einsum("mi,mi->m", g, Jn), np.einsum("mi,mi->m", g, Jm)
        s_nn, s_nm, s_mm = s_nn + opt.sigma_img**2 * gn * gn, s_nm + opt.sigma_img**2 * gn * gm, \
            s_mm + opt.sigma_img**2 * gm * gm
    if registration_covariance is not None:
        C = _check_registration_covariance(registration_covariance)
        x_room = ctx.pose.apply(X)
        # G = R^T [-I | [x]x]  =>  G^T v = -(R v, x x R v)
        vn, vm = n @ ctx.pose.R.T, m @ ctx.pose.R.T
        bn = np.hstack([vn, _cross(x_room, vn)])
        bm = np.hstack([vm, _cross(x_room, vm)])
        Cbn, Cbm = bn @ C, bm @ C
        s_nn = s_nn + np.einsum("mi,mi->m", Cbn, bn)
        s_nm = s_nm + np.einsum("mi,mi->m", Cbn, bm)
        s_mm = s_mm + np.einsum("mi,mi->m", Cbm, bm)
    # where the wire sits in the lumen (across the vessel, along q) and the CTA centerline error;
    # off the lumen (a ray that misses the path's tube by miss_mm): that much more across the wire
    miss2 = miss_mm**2
    a = s_nn + miss2
    b = gain * s_nm
    c = gain**2 * s_mm + (opt.lumen_spread * half_width_mm) ** 2 + opt.sigma_centerline_mm**2 + miss2
    if ambiguity_mm2 is not None:  # another branch at another depth: its part across the wire
        Bn = np.einsum("mij,mj->mi", ambiguity_mm2, n)
        a = a + np.einsum("mi,mi->m", Bn, n)
        b = b + np.einsum("mi,mi->m", Bn, q)
        c = c + np.einsum("mi,mj,mij->m", q, q, ambiguity_mm2)
    nq = _outer(n, q)
    cov = a[:, None, None] * _outer(n) + b[:, None, None] * (nq + np.transpose(nq, (0, 2, 1))) \
        + c[:, None, None] * _outer(q)
    return cov.reshape(M, 3, 3)


# --------------------------------------------------------------------------------------------
# the paper's closed form
# --------------------------------------------------------------------------------------------
def paper_depth_mm(wire_uv_px, pose: Pose, carm: CArm) -> np.ndarray:
    """The paper's closed-form depth, applied literally with the registration's R, t.

    ``d_m = |t x R^T k_m| / |(R^T k_m) x k_m|`` with ``k_m = K^-1 [g_m; 1]`` and ``(R, t)`` the
    camera extrinsics of the registered pose. It is a two-view triangulation formula (the second
    ray being ``R^T k_m`` from the camera centre ``t``); with a single view both rays come from the
    same pixel, so the value does not depend on the anatomy at all. Returns (M,) camera depths (mm).
    """
    uv = np.asarray(wire_uv_px, dtype=float)
    R, t = carm.extrinsics(pose)
    k = np.column_stack([(uv - carm.principal_point_px) / carm.focal_px, np.ones(len(uv))])
    Rk = k @ R  # rows R^T k
    num = np.linalg.norm(np.cross(t[None, :], Rk), axis=1)
    den = np.linalg.norm(np.cross(Rk, k), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return num / den


# --------------------------------------------------------------------------------------------
# the methods
# --------------------------------------------------------------------------------------------
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


def _anchors(uv, step_px) -> np.ndarray:
    s = _arclength(uv)
    n = max(int(np.ceil(s[-1] / step_px)), 1)
    idx = np.searchsorted(s, np.linspace(0.0, s[-1], n + 1))
    idx = np.unique(np.clip(idx, 0, len(uv) - 1))
    if idx[-1] != len(uv) - 1:
        idx = np.r_[idx, len(uv) - 1]
    return idx


def _candidates(ctx, uv_a, opt):
    """(A, K) candidate ids (-1 none) and (A, K) 2D distance outside the projected lumen (px)."""
    K = opt.candidates
    dist, ids = ctx.kd2.query(uv_a, k=K, distance_upper_bound=ctx.r_px_max + opt.margin_px)
    ids = np.where(np.isfinite(dist), ctx.cand_ids[np.minimum(ids, len(ctx.cand_ids) - 1)], -1)
    safe = np.maximum(ids, 0)
    outside = np.where(ids >= 0, np.maximum(dist - ctx.r_px[safe], 0.0), np.inf)
    ok = (ids >= 0) & (outside <= opt.margin_px)
    return np.where(ok, ids, -1), np.where(ok, outside, np.inf)


def _viterbi(ctx, uv_a, cand, outside, opt, track_tip):
    """The chosen tree point per anchor (A',), the path's total cost and its min-marginals.

    The min-marginals are ``(cand, excess)``, each (A', K): the candidates of the anchors on the
    path and, for each, how much more the best path through it costs (0 for the chosen one).
    """
    # keep only the columns that hold a candidate somewhere (the KD query pads with misses)
    keep = (cand >= 0).any(axis=0)
    cand, outside = cand[:, keep], outside[:, keep]
    A, K = cand.shape
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
    # pairwise costs for all steps at once: (A-1, K, K)
    i, j = safe[:-1, :, None], safe[1:, None, :]
    slca = ctx.lca_s(i, j)
    up = ctx.s[i] - slca
    geo = up + (ctx.s[j] - slca)
    # |X_j - X_i| and |(uv_j - uv_i) - (w_t - w_t-1)|^2 through batched dot products
    Xc, Uc = ctx.points[safe], ctx.uv[safe]
    n2 = np.einsum("akx,akx->ak", Xc, Xc)
    e3 = np.sqrt(np.maximum(n2[:-1, :, None] + n2[1:, None, :] - 2.0 * Xc[:-1] @ np.transpose(Xc[1:], (0, 2, 1)), 0.0))
    a = Uc[1:] - (uv_a[1:] - uv_a[:-1])[:, None, :]
    m2 = (np.einsum("akx,akx->ak", Uc[:-1], Uc[:-1])[:, :, None] + np.einsum("akx,akx->ak", a, a)[:, None, :]
          - 2.0 * Uc[:-1] @ np.transpose(a, (0, 2, 1)))
    # pseudo-Huber on the 2D step mismatch: quadratic up to sigma_step_px, then linear (a wire
    # cutting the corner of a bifurcation leaves the centerline's candidates for a few anchors)
    C = (
        2.0 * (np.sqrt(1.0 + np.maximum(m2, 0.0) / opt.sigma_step_px**2) - 1.0)
        + np.maximum(geo - e3, 0.0) / opt.sigma_jump_mm
        + up / opt.sigma_retreat_mm
    )
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


def _ambiguity(ctx, nodes, marginals, opt: ReconOptions) -> np.ndarray:
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
    safe = np.maximum(cand, 0)
    w = np.where((cand >= 0) & np.isfinite(excess), np.exp(-excess / opt.ambiguity_scale), 0.0)
    w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    D = ctx.points[safe] - ctx.points[nodes][:, None, :]
    geo = ctx.s[safe] + ctx.s[nodes][:, None] - 2.0 * ctx.lca_s(safe, nodes[:, None])
    other = geo - np.linalg.norm(D, axis=2) > opt.sigma_jump_mm
    return np.einsum("ak,aki,akj->aij", w * other, D, D)


def _place_on_path(ctx, uv, anchor_idx, nodes):
    """3D points on the rays of every wire point, near the tree path through ``nodes``."""
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
    cost = np.where(segok, (dist / _DIST_MM) ** 2 + (along / _ALONG_MM) ** 2, np.inf)
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


#: _place_on_path's segment choice: ray-axis distance and distance along the path from the
#: position interpolated between the anchors, each in units of (mm)
_DIST_MM = 0.25
_ALONG_MM = 1.5


def _finish(ctx, X, uv, tid, depth_std, extra, *, image, registration_covariance, opt, method, t0, message,
            lumen=None):
    Xs, lam = _smooth(ctx, X, uv, lam=opt.smoothing_lambda, opt=opt)
    proj = ctx.project(Xs)
    perr = float(np.linalg.norm(proj - uv, axis=1).mean())
    if lumen is None:
        cov = _covariance(ctx, Xs, uv, depth_std_mm=depth_std, extra_iso_mm2=extra, image=image,
                          registration_covariance=registration_covariance, opt=opt)
    else:
        half_width, miss, amb = lumen
        cov = _covariance_lumen(ctx, Xs, uv, tangent=_tangent(Xs), half_width_mm=half_width, miss_mm=miss,
                                ambiguity_mm2=amb, image=image, registration_covariance=registration_covariance,
                                opt=opt)
    unc = np.sqrt(np.clip(np.trace(cov, axis1=1, axis2=2), 0.0, None))
    arc = _arclength(Xs)
    ok = bool(np.isfinite(perr) and perr <= opt.fail_projection_px and np.all(np.isfinite(Xs)))
    msg = message if ok else f"projection error {perr:.2f} px exceeds {opt.fail_projection_px} px"
    if lam < opt.smoothing_lambda:
        msg += f"; smoothing lambda reduced to {lam:.3g} to keep the projection"
    tree_ids = np.where(tid >= 0, ctx.orig_id[np.maximum(tid, 0)], -1)
    return Wire3D(Xs, unc, float(arc[-1]), perr, ok, msg, tree_ids, arc, _curvature(Xs) if len(Xs) > 2 else
                  np.zeros(len(Xs)), time.perf_counter() - t0, method.value, cov)


def _reconstruct_vessel(ctx, uv, *, track_tip, image, registration_covariance, opt, t0):
    aidx = _anchors(uv, opt.dp_step_px)
    cand, outside = _candidates(ctx, uv[aidx], opt)
    has = (cand >= 0).any(axis=1)
    coverage = float(has.mean())
    if coverage < opt.min_coverage or has.sum() < 2:
        return Wire3D.failed(
            f"the 2D wire misses the projected vessel tree ({100 * coverage:.0f}% of anchors inside, "
            f"need {100 * opt.min_coverage:.0f}%)", seconds=time.perf_counter() - t0)
    aidx, cand, outside = aidx[has], cand[has], outside[has]
    nodes, total, marg = _viterbi(ctx, uv[aidx], cand, outside, opt, track_tip)
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
        r_nodes, r_total, r_marg = _viterbi(ctx, uv[::-1][r_aidx], cand[::-1], outside[::-1], opt, track_tip)
        if r_total < total and len(r_nodes) >= 2:
            uv, aidx, nodes, total, marg = uv[::-1].copy(), r_aidx[: len(r_nodes)], r_nodes, r_total, r_marg
            n_skipped = len(r_aidx) - len(r_nodes)
            reversed_note = "; the 2D wire looked distal -> proximal: output reversed to proximal -> distal"
    X, tid, half, dist, r = _place_on_path(ctx, uv, aidx, nodes)
    miss = np.maximum(dist - r, 0.0)
    depth_std = 2.0 * half / np.sqrt(12.0) + miss
    half_width = np.sqrt(np.maximum(r * r - dist * dist, 0.0))
    amb = None
    if opt.ambiguity_scale > 0:
        # each wire point takes the ambiguity of its nearest anchor (beyond the path's end: the last)
        k = np.clip(np.searchsorted(aidx, np.arange(len(uv))), 0, len(aidx) - 1)
        km = np.clip(k - 1, 0, len(aidx) - 1)
        k = np.where(np.abs(aidx[km] - np.arange(len(uv))) < np.abs(aidx[k] - np.arange(len(uv))), km, k)
        amb = _ambiguity(ctx, nodes, marg, opt)[k]
    msg = f"ok: {len(uv)} points, {100 * coverage:.0f}% of anchors on the tree, path cost {total:.1f}" + reversed_note
    if coverage < 1.0:
        msg += " (gaps bridged)"
    if n_skipped:
        msg += f"; the last {n_skipped} anchors fit no lumen (placed beyond the path's end)"
    ids = np.where(miss > 0, -1, tid)
    w = _finish(ctx, X, uv, ids, depth_std, miss**2, image=image, registration_covariance=registration_covariance,
                opt=opt, method=ReconMethod.VESSEL, t0=t0, message=msg, lumen=(half_width, miss, amb))
    return replace(w, reversed_input=bool(reversed_note), tree_rise_mm=float(ctx.s[nodes[-1]] - ctx.s[nodes[0]]))


def _reconstruct_paper(ctx, uv, *, image, registration_covariance, opt, t0):
    d = paper_depth_mm(uv, ctx.pose, ctx.carm)
    if not np.all(np.isfinite(d)) or np.any(d <= 0):
        return Wire3D.failed("paper closed-form depth is undefined (zero denominator) for this pose",
                             seconds=time.perf_counter() - t0, method=ReconMethod.PAPER.value)
    X = ctx.carm.backproject(uv, d, ctx.pose)
    zero = np.zeros(len(uv))
    return _finish(ctx, X, uv, -np.ones(len(uv), np.int64), zero, zero, image=image,
                   registration_covariance=registration_covariance, opt=opt, method=ReconMethod.PAPER, t0=t0,
                   message="paper closed-form depth (single-view: not constrained by the anatomy)")


def _reconstruct_bspline(ctx, uv, *, image, registration_covariance, opt, t0):
    x = _arclength(uv)
    if len(uv) >= 5 and x[-1] >= 2 * opt.knot_px:
        spl, Bm = _pspline(x, uv, opt.smoothing_lambda, opt.knot_px)
        g = Bm @ spl.c
    else:
        g = uv
    dist, ids = ctx.kd2.query(g)
    ids = ctx.cand_ids[ids]
    outside = np.maximum(dist - ctx.r_px[ids], 0.0)
    if float((outside <= opt.margin_px).mean()) < opt.min_coverage:
        return Wire3D.failed("the 2D wire misses the projected vessel tree", seconds=time.perf_counter() - t0,
                             method=ReconMethod.BSPLINE.value)
    X = ctx.carm.backproject(g, ctx.depth[ids], ctx.pose)
    depth_std = 2.0 * ctx.radius[ids] / np.sqrt(12.0)
    tid = np.where(outside <= opt.margin_px, ids, -1)
    return _finish(ctx, X, uv, tid, depth_std, (outside * ctx.px_mm) ** 2, image=image,
                   registration_covariance=registration_covariance, opt=opt, method=ReconMethod.BSPLINE, t0=t0,
                   message="2D B-spline lifted to the nearest centerline depth")


def _track_tip(ctx, previous: Wire3D | None):
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
    opt = options or ReconOptions()
    ctx = build_context(pose, carm, tree, options=opt)
    kw = dict(image=image, registration_covariance=registration_covariance, opt=opt, t0=t0)
    if method is ReconMethod.PAPER:
        return _reconstruct_paper(ctx, uv, **kw)
    if method is ReconMethod.BSPLINE:
        return _reconstruct_bspline(ctx, uv, **kw)
    return _reconstruct_vessel(ctx, uv, track_tip=_track_tip(ctx, previous), **kw)


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
        self.context = build_context(pose, carm, tree, options=self.options)
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
