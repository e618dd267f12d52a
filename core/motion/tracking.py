"""Motion: the patient pose followed frame by frame from what each live frame shows.

Breathing moves the liver, kidneys and heart 5-20 mm, mostly cranio-caudally; one pose from the
roadmap lets the overlay drift off and places the 3D wire in the wrong vessel position. Each live
frame shows a curve that lies inside the vessels (the guidewire, or a catheter); its 2D fit to the
projected tree updates the pose.

What one frame can tell: a curve pins the tree's projection across the curve well, along it
less, and the depth along the beam and the rotations out of the image plane hardly at all. So
the update is a maximum a posteriori estimate of a small rigid motion ``delta`` of the tree,
written in the C-arm's camera axes about the tree's centroid
``(t_u, t_v, t_depth, r_u, r_v, r_beam)`` (mm, rad), with

* the curve's robust (pseudo-Huber) point-to-projected-tree distances, px, one point per
  ``fit_correlation_mm`` of the curve (neighbouring points err together: the wire's offset in
  the lumen);
* the roadmap's prior ``delta ~ N(0, diag(sigma_roadmap^2))``: tight in depth and out-of-plane
  rotation, loose in the image plane (``MotionOptions``), plus the registration's own covariance
  when it is given;
* a temporal prior ``delta_t ~ N(delta_{t-1}, diag(sigma_step^2))``: motion is smooth.

Gauss-Newton with correspondences found again at each iteration (the nearest projected tree
sample and its local 2D tangent), a few iterations per frame. Each frame gets its pose, residual
and verdict as a ``registration.RegistrationResult``, with a pose covariance (``covariance_6x6``,
in the registration's convention; ``pose_std_mm``) that describes what one frame does not see
rather than the estimate's own Hessian (``MotionOptions.cov_*``; ``live.Session`` puts it in
each point's uncertainty), and a second opinion every few frames: the frame solved alone, as
if it had no predecessor. Where that puts the wire's vessels elsewhere, the curve lies in the
lumen in two poses and the tracked one is not settled (``MotionOptions.settle_every``); so too
where two fits almost as good (``settle_rival_cost``) part, the first frame's own starts included.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from guidewire3d import kernels
from guidewire3d.errors import InputError
from guidewire3d.geometry import CArm, Pose, hat, so3_exp
from guidewire3d.registration import RegistrationResult
from guidewire3d.vesseltree import VesselTree

__all__ = ["MotionOptions", "MotionTracker", "track_poses", "curve_to_tree_distance_px"]

#: below this image-plane fraction of the patient's axis (a beam nearly along it) the in-plane
#: prior is isotropic and the acquisition search is skipped
MIN_CC_IN_PLANE = 0.3

#: a frame without a fitted predecessor is solved from the roadmap pose and from this many
#: cranio-caudal shifts (the best local minima of the search)
ACQUIRE_STARTS = 3
#: the curve is thinned to at most this many evenly spaced points (cost per frame)
MAX_CURVE_POINTS = 128
#: the second opinion (``MotionOptions.settle_every``) solves with at most this many curve points
#: (it is compared with a limit of millimetres) from this many of the best cranio-caudal shifts
SETTLE_CURVE_POINTS = 32
SETTLE_STARTS = 2
SETTLE_ITERATIONS = 4
#: Gauss-Newton stops when a step moves less than this (mm, rad): 0.01 mm is 0.05 px at the isocentre
STEP_TOL_MM = 0.01
STEP_TOL_RAD = 1e-5
#: tree samples projected farther than the gate plus this outside the curve's bounding box are
#: not looked at in a frame (a frame moves the tree by a few px)
CROP_MARGIN_PX = 30.0


@dataclass(frozen=True)
class MotionOptions:
    """Priors and robust kernel of the per-frame pose update."""

    #: roadmap prior, 1 sigma: image-plane translation along the patient's cranio-caudal axis as
    #: projected (breathing moves the organs mostly so) and across it (mm), depth (mm),
    #: out-of-plane rotation (deg), rotation about the beam (deg)
    sigma_cc_mm: float = 20.0
    sigma_across_mm: float = 4.0
    sigma_depth_mm: float = 0.3
    sigma_tilt_deg: float = 0.5
    sigma_spin_deg: float = 1.0
    #: temporal prior, 1 sigma per frame on the image-plane translation (mm); depth and rotations
    #: are held by the roadmap prior alone (no random walk)
    sigma_step_inplane_mm: float = 2.0
    #: a frame with no fitted predecessor first searches the cranio-caudal shift (mm) in this range
    acquire_range_mm: float = 25.0
    #: 2D residuals: noise (px), pseudo-Huber cutoff (px), gate beyond which a point is ignored (px)
    sigma_px: float = 1.5
    huber_px: float = 3.0
    gate_px: float = 40.0
    #: tree samples at most this far apart (mm) for the nearest-point correspondence
    sample_mm: float = 1.0
    iterations: int = 4
    #: verdict: a curve point is an inlier within the projected lumen plus ``inlier_px``; the curve
    #: fits when its inliers lie on average within ``max_mean_residual_px`` of the lumen and they are
    #: at least ``min_inlier_fraction`` of it (a catheter or wire rides anywhere inside the lumen,
    #: not on the centerline)
    inlier_px: float = 3.0
    max_mean_residual_px: float = 1.5
    min_inlier_fraction: float = 0.5
    #: a fitted frame whose depth moved more than this from the roadmap's is UNCERTAIN
    max_depth_shift_mm: float = 5.0
    #: the reported pose covariance (``covariance_6x6``, ``pose_std_mm``): not the estimate's own
    #: inverse Hessian, which counts every curve point as an independent 1.5 px measurement and
    #: trusts the priors above (tuned to regularise, not to describe the motion). A curve point
    #: tells where the lumen is to ``cov_lumen_spread`` times the projected radius (the wire rides
    #: anywhere inside it) plus ``sigma_px``; neighbouring points err together, so the curve counts
    #: as one measurement per ``cov_correlation_mm`` of its length; what one frame does not see
    #: (depth, tilt out of the image plane, rotation about the beam) is known to the 1 sigma below
    #: (the simulator's breathing: up to 17 deg off the patient's axis, 0.1 deg/mm of rotation)
    cov_lumen_spread: float = 0.5
    cov_correlation_mm: float = 10.0
    cov_sigma_depth_mm: float = 2.0
    cov_sigma_tilt_deg: float = 1.5
    cov_sigma_spin_deg: float = 2.0
    #: second opinion: every ``settle_every`` frames (and every frame while it disagrees), the
    #: frame is also solved alone, as a frame with no predecessor is (from the roadmap pose and the
    #: best cranio-caudal shifts, no temporal prior). A curve that lies in the lumen in two poses
    #: does not tell which: where the alone solution moves the wire's tree samples more than
    #: ``max_unsettled_mm`` from the tracked one, the tracked pose is not settled (UNCERTAIN).
    #: A check costs about three frames' tracking; 0 turns it off
    settle_every: int = 5
    max_unsettled_mm: float = 3.0
    #: ... and the alone solutions count when their cost is within ``settle_rival_cost`` of the best
    #: one (the fit's units: squared residuals in ``sigma_px``, one point per
    #: ``fit_correlation_mm``), as do the first frame's own starts: two fits almost as good that put
    #: the wire's vessels apart do not say which is right. 0: the best alone solution only. On
    #: bench_motion's simulator 10 turns 12 ok frames with the tip or wire off uncertain and keeps the
    #: right ok ones (a first frame acquired in a neighbouring vessel stays uncertain until the
    #: rival fits part)
    settle_rival_cost: float = 10.0
    #: in the fit, neighbouring curve points err together (the wire's offset inside the lumen varies
    #: slowly along it): the curve counts as one point per ``fit_correlation_mm`` of its length (at
    #: most one per point). Counted as independent, a short curve's offset in the lumen tilts and
    #: spins the tree past what the priors allow (1-1.6 deg RMS of error on bench_motion's
    #: simulator, 2.4 mm pose error); with 3 mm the rotations stay near the priors (2.1 mm) and the
    #: real catheter is followed as before. The reported covariance has its own count
    #: (``cov_correlation_mm``); 10 mm here holds the simulator's pose a little better (1.9 mm) but
    #: follows the real catheter less (4.3 px against 4.1)
    fit_correlation_mm: float = 3.0

    def __post_init__(self):
        for name in ("sigma_cc_mm", "sigma_across_mm", "sigma_depth_mm", "sigma_tilt_deg", "sigma_spin_deg",
                     "sigma_step_inplane_mm", "acquire_range_mm", "sigma_px", "huber_px",
                     "gate_px", "sample_mm", "inlier_px", "max_mean_residual_px", "max_depth_shift_mm",
                     "cov_lumen_spread", "cov_correlation_mm", "cov_sigma_depth_mm", "cov_sigma_tilt_deg",
                     "cov_sigma_spin_deg", "max_unsettled_mm", "fit_correlation_mm"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"MotionOptions.{name}: expected a positive number, got {v!r}")
        if int(self.iterations) < 1:
            raise InputError(f"MotionOptions.iterations: expected >= 1, got {self.iterations!r}")
        if not (np.isfinite(self.settle_rival_cost) and self.settle_rival_cost >= 0):
            raise InputError(f"MotionOptions.settle_rival_cost: expected a number >= 0, got {self.settle_rival_cost!r}")
        if int(self.settle_every) < 0:
            raise InputError(f"MotionOptions.settle_every: expected >= 0 (0: no second opinion), got "
                             f"{self.settle_every!r}")


def _samples(tree: VesselTree, step_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tree samples (K, 3) at most ``step_mm`` apart, their radii (K,) and for each a neighbour
    along the tree (K,) that gives the local tangent (its parent; the root's first child)."""
    dense, _ = tree.densified(step_mm)
    nbr = dense.parent.copy()
    kids = dense.children[dense.root]
    nbr[dense.root] = kids[0] if kids else dense.root
    return dense.points_lps_mm, dense.radius_mm, nbr


class MotionTracker:
    """Per-frame pose tracking against one registration (the roadmap's pose and covariance).

    Parameters
    ----------
    tree : VesselTree
        The CTA (or 3DRA) centerline tree, LPS mm.
    carm : CArm
        The live frames' view.
    initial_pose : Pose
        The roadmap registration ``T_iso_from_lps``: the prior's centre.
    covariance : (6, 6) ndarray, optional
        The registration's covariance (left-perturbation tangent ``(t mm, phi rad)`` about the
        isocentre origin); added to the roadmap prior.
    options : MotionOptions, optional
    """

    def __init__(self, tree: VesselTree, carm: CArm, initial_pose: Pose, *, covariance=None,
                 options: MotionOptions | None = None):
        self.tree, self.carm, self.initial_pose = tree, carm, initial_pose
        self.options = opt = options or MotionOptions()
        pts, self._radius_mm, self._nbr = _samples(tree, opt.sample_mm)
        # tree samples in the camera frame of the initial pose: x_cam = Rc x + tc (z: depth)
        Rc, tc = carm.extrinsics(initial_pose)
        self._Rc_room = carm.axes  # camera axes in the room frame (rows)
        self._Y0 = pts @ Rc.T + tc
        self._c = self._Y0.mean(axis=0)
        p = self._Y0 - self._c
        self._M2 = p.T @ p / len(p)
        self._r2 = float(np.trace(self._M2))
        self._f = carm.focal_px
        self._pp = carm.principal_point_px
        deg = np.pi / 180.0
        # the patient's superior axis (LPS +z) in camera axes; its image-plane part is the
        # breathing direction
        # breathing direction: the patient's superior axis (LPS +z) in camera axes (3D: a
        # cranio-caudal shift seen in the image implies its depth component too)
        self.cc_cam = self._Rc_room @ (initial_pose.R @ np.array([0.0, 0.0, 1.0]))
        a = self.cc_cam
        P0 = np.zeros((6, 6))
        P0[:3, :3] = np.diag([opt.sigma_across_mm**2, opt.sigma_across_mm**2, opt.sigma_depth_mm**2])
        # (with a cranio-caudal axis in the image, depth is also tied to it below)
        if np.linalg.norm(a[:2]) > MIN_CC_IN_PLANE:
            P0[:3, :3] += opt.sigma_cc_mm**2 * np.outer(a, a)
        else:  # the beam runs along the patient's axis: no preferred direction in the image
            P0[:2, :2] = opt.sigma_cc_mm**2 * np.eye(2)
        P0[3:, 3:] = np.diag(np.array([opt.sigma_tilt_deg * deg, opt.sigma_tilt_deg * deg,
                                       opt.sigma_spin_deg * deg]) ** 2)
        # the reported covariance's prior: the same structure with what one frame does not see
        P_cal = P0.copy()
        P_cal[:3, :3] += np.diag([0.0, 0.0, opt.cov_sigma_depth_mm**2 - opt.sigma_depth_mm**2])
        P_cal[3:, 3:] = np.diag(np.array([opt.cov_sigma_tilt_deg * deg, opt.cov_sigma_tilt_deg * deg,
                                          opt.cov_sigma_spin_deg * deg]) ** 2)
        self._A = self._tangent_to_delta
        self._A_inv = np.linalg.inv(self._A)
        if covariance is not None:
            C_cam = self._camera_covariance(covariance)
            P0, P_cal = P0 + C_cam, P_cal + C_cam
        self._Lambda0 = np.linalg.inv(P0)
        self._Lambda_cal = np.linalg.inv(P_cal)
        # depth is not seen in one view, and an image-plane scaling (the heart contracting, a
        # vessel straightened by the wire) would pass for it: the depth may differ from what the
        # cranio-caudal shift implies by ``sigma_depth_mm`` only
        if np.linalg.norm(a[:2]) > MIN_CC_IN_PLANE:
            k = a[2] * a[:2] / float(a[:2] @ a[:2])
            wz = np.array([-k[0], -k[1], 1.0, 0.0, 0.0, 0.0])
            self._Lambda0 += np.outer(wz, wz) / opt.sigma_depth_mm**2
            self._Lambda_cal += np.outer(wz, wz) / opt.cov_sigma_depth_mm**2
        self._Lambda_t = np.zeros((6, 6))
        self._Lambda_t[:3, :3] = np.eye(3) / opt.sigma_step_inplane_mm**2
        self._source_room_mm = carm.source_room_mm  # (pose_of, per frame)
        # the compiled solve's inputs, read-only once here (kernels._in then passes them as they are)
        for name in ("_Y0", "_c", "_nbr", "_radius_mm", "_pp", "_Lambda0", "_Lambda_t"):
            a = np.ascontiguousarray(getattr(self, name), np.int64 if name == "_nbr" else np.float64)
            a.flags.writeable = False
            setattr(self, name, a)
        self._no_Lt = np.zeros((6, 6))
        self._no_Lt.flags.writeable = False
        kernels.warm_up_motion()  # compiled (or loaded from numba's disk cache) before the first frame
        self.reset()

    def reset(self) -> None:
        """Back to the roadmap pose, no temporal history."""
        self.delta = np.zeros(6)
        self._has_previous = False
        self._since_check = 0
        self.unsettled_mm = 0.0  # the last second opinion's disagreement (see ``MotionOptions.settle_every``)

    def _camera_covariance(self, covariance) -> np.ndarray:
        """The registration covariance (about the iso origin, room axes) in this tracker's
        parametrisation (about the tree centroid, camera axes)."""
        C = np.asarray(covariance, float)
        if C.shape != (6, 6) or not np.all(np.isfinite(C)):
            raise InputError(f"covariance: expected a finite (6, 6) matrix, got shape {C.shape}")
        return self._A @ C @ self._A.T

    @property
    def _tangent_to_delta(self) -> np.ndarray:
        """(6, 6) ``d delta / d xi``: a left perturbation ``xi = (t, phi)`` of the pose (room axes,
        about the iso origin, ``T' = exp(xi) T``) as this tracker's ``delta`` (camera axes, about the
        tree centroid). A room point moves by ``t + phi x x``, so the centroid ``c`` by
        ``t + phi x c``; the camera axes are left-handed (det -1), so a rotation ``phi`` in the
        room is ``-Rc phi`` in them."""
        Rc = self._Rc_room
        c_room = Rc.T @ self._c + self.carm.source_room_mm
        A = np.zeros((6, 6))
        A[:3, :3] = Rc
        A[:3, 3:] = -Rc @ hat(c_room)
        A[3:, 3:] = float(np.linalg.det(Rc)) * Rc
        return A

    # --- pose <-> delta ------------------------------------------------------------------------
    def pose_of(self, delta) -> Pose:
        """``T_iso_from_lps`` of the tree moved by ``delta`` (camera axes, about the centroid)."""
        d = np.asarray(delta, float)
        Rd = so3_exp(d[3:])
        Rc, S = self._Rc_room, self._source_room_mm
        T0 = self.initial_pose
        # x_cam' = Rd (x_cam - c) + c + t,  x_cam = Rc (T0 x - S),  T x = Rc^T x_cam' + S
        R = Rc.T @ Rd @ Rc @ T0.R
        t = Rc.T @ (Rd @ (Rc @ (T0.t - S) - self._c) + self._c + d[:3]) + S
        return Pose(R, t)

    def _moved(self, delta) -> np.ndarray:
        return self._moved_subset(delta, slice(None))

    def _moved_subset(self, delta, idx) -> np.ndarray:
        Rd = so3_exp(delta[3:])
        return (self._Y0[idx] - self._c) @ Rd.T + self._c + delta[:3]

    def _project(self, Y) -> np.ndarray:
        return self._f * Y[:, :2] / Y[:, 2:3] + self._pp

    # --- one frame -----------------------------------------------------------------------------
    def update(self, curve_uv_px):
        """Update the pose from one frame's curve (``(N, 2)`` px); returns a ``RegistrationResult``.

        An empty or unusable curve keeps the previous frame's pose (verdict FAILED, with why).
        """
        t0 = time.perf_counter()
        opt = self.options
        c = np.asarray(curve_uv_px, float).reshape(-1, 2) if curve_uv_px is not None else np.zeros((0, 2))
        c = c[np.all(np.isfinite(c), axis=1)]
        if len(c) > MAX_CURVE_POINTS:  # a 1-px ordered wire has hundreds: evenly spaced ones suffice
            c = c[np.linspace(0, len(c) - 1, MAX_CURVE_POINTS).round().astype(int)]
        prev = self.delta.copy()
        if len(c) < 3:
            pose = self.pose_of(prev)
            return RegistrationResult(pose, self.carm.projection_matrix(pose), False,
                                      "no curve in the frame: pose held from the previous frame",
                                      float("nan"), 0.0, 0, time.perf_counter() - t0)
        tracked = self._has_previous
        Lt = self._Lambda_t if tracked else self._no_Lt
        starts = [prev] if tracked else self._acquire(c, prev)
        best = None
        sols = []
        for start in starts:
            sol = self._solve(c, start, prev, Lt)
            if sol is not None:
                sols.append(sol)
                if best is None or sol[0] < best[0]:
                    best, fit = sol, self._last_fit
        if best is None:
            pose = self.pose_of(prev)
            return RegistrationResult(pose, self.carm.projection_matrix(pose), False,
                                      "the curve lies away from the projected tree: pose held from the previous "
                                      "frame", float("inf"), 0.0, 0, time.perf_counter() - t0)
        _, delta, _, it, frac, mean_res = best
        fits = frac >= opt.min_inlier_fraction and mean_res <= opt.max_mean_residual_px
        depth_shift = float(delta[2])
        pose = self.pose_of(delta)
        cov = self._reported_covariance(*fit[:4])
        std_mm = self._tree_std_mm(cov)
        if fits:
            self.delta = delta
            self._has_previous = True
            ok = abs(depth_shift) <= opt.max_depth_shift_mm
            msg = (f"tracked: {100 * frac:.0f}% of the curve in the projected lumen ({mean_res:.2f} px outside on "
                   f"average); moved "
                   f"{np.linalg.norm(delta[:2]):.1f} mm in the image plane, {depth_shift:+.1f} mm in depth")
            if not ok:
                msg += f" (depth moved more than {opt.max_depth_shift_mm:g} mm from the roadmap's)"
            if tracked and opt.settle_every > 0:
                self._since_check += 1
                if self._since_check >= int(opt.settle_every) or self.unsettled_mm > opt.max_unsettled_mm:
                    self._since_check = 0
                    self.unsettled_mm = self._second_opinion_mm(c, delta, fit[4])
                if self.unsettled_mm > opt.max_unsettled_mm:
                    ok = False
                    msg += (f"; tracked pose not settled: this frame's curve alone puts the wire's vessels "
                            f"{self.unsettled_mm:.1f} mm elsewhere (limit {opt.max_unsettled_mm:g} mm)")
            elif opt.settle_every > 0:
                # a first frame: its other starts' fits are the second opinion
                self._since_check = 0
                self.unsettled_mm = self._rivals_mm(sols, delta, fit[4])
                if self.unsettled_mm > opt.max_unsettled_mm:
                    ok = False
                    msg += (f"; acquired pose not settled: another fit almost as good puts the wire's vessels "
                            f"{self.unsettled_mm:.1f} mm elsewhere (limit {opt.max_unsettled_mm:g} mm)")
            else:
                self.unsettled_mm = 0.0
        else:
            # keep the previous estimate: a curve that does not lie on the tree does not move it
            pose = self.pose_of(prev)
            ok = False
            msg = (f"the curve does not fit the projected tree ({100 * frac:.0f}% within {opt.inlier_px:g} px of the "
                   f"lumen, {mean_res:.2f} px outside on average): pose held from the previous frame")
        if not fits:
            cov = self._reported_covariance(None, None, None, None)
            std_mm = self._tree_std_mm(cov)
        return RegistrationResult(pose, self.carm.projection_matrix(pose), bool(ok), msg, mean_res, frac, it,
                                  time.perf_counter() - t0, covariance_6x6=self._A_inv @ cov @ self._A_inv.T,
                                  pose_std_mm=std_mm,
                                  fits_2d=bool(fits))

    def _second_opinion_mm(self, c, delta, j) -> float:
        """How far (mm, the largest over the curve's tree samples ``j``) the frame solved alone
        (from the ``SETTLE_STARTS`` best cranio-caudal shifts of the roadmap pose, no temporal prior;
        the best fit and those within ``settle_rival_cost`` of it) puts the tree from where
        ``delta`` puts it."""
        zero = np.zeros(6)
        if len(c) > SETTLE_CURVE_POINTS:  # a coarse answer suffices (it is compared with a limit of mm)
            c = c[np.linspace(0, len(c) - 1, SETTLE_CURVE_POINTS).round().astype(int)]
        starts = self._acquire(c, zero)
        sols = [self._solve(c, start, zero, self._no_Lt, iterations=SETTLE_ITERATIONS)
                for start in (starts[1:1 + SETTLE_STARTS] if len(starts) > 1 else starts)]
        return self._rivals_mm([s for s in sols if s is not None], delta, j)

    def _rivals_mm(self, sols, delta, j) -> float:
        """The largest distance (mm, over the tree samples ``j``) between where ``delta`` puts the
        tree and where the fits ``sols`` (``_solve`` results) do, of those whose cost is within
        ``settle_rival_cost`` of the best; 0 without any."""
        if not sols:
            return 0.0
        limit = min(s[0] for s in sols) + self.options.settle_rival_cost
        idx = np.unique(j)
        here = self._moved_subset(delta, idx)
        return max(float(np.max(np.linalg.norm(self._moved_subset(s[1], idx) - here, axis=1)))
                   for s in sols if s[0] <= limit)

    def _reported_covariance(self, c, J, w, lumen_px) -> np.ndarray:
        """(6, 6) covariance of ``delta`` (see ``MotionOptions.cov_*``): the curve's points inside
        the gate tell where the lumen is to ``sigma_px`` plus ``cov_lumen_spread`` projected radii,
        counted once per ``cov_correlation_mm`` of the curve's length, on top of what the roadmap
        tells (``cov_sigma_*``); no curve (``J`` None): the roadmap's alone."""
        opt = self.options
        L = self._Lambda_cal
        if J is not None:
            inl = w > 0
            n = int(inl.sum())
            if n:
                wi = inl / (opt.sigma_px**2 + (opt.cov_lumen_spread * lumen_px) ** 2)
                length_mm = float(np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1))) * self._c[2] / self._f
                kappa = min(1.0, max(1.0, length_mm / opt.cov_correlation_mm) / n)
                L = L + kappa * (J.T @ (J * wi[:, None]))
        return np.linalg.inv(L)

    def _tree_std_mm(self, cov) -> float:
        """RMS over the tree of the 1-sigma displacement implied by ``cov`` (of ``delta``), mm:
        ``tr C_t + tr C_r mean|p|^2 - tr(C_r mean p p^T)`` with ``p`` about the centroid."""
        return float(np.sqrt(max(np.trace(cov[:3, :3]) + np.trace(cov[3:, 3:]) * self._r2
                                 - np.trace(cov[3:, 3:] @ self._M2), 0.0)))

    def _solve(self, c, start, prev, Lt, *, iterations: int | None = None):
        """Gauss-Newton from ``start``: ``(robust cost, delta, H, iterations, inlier fraction,
        mean px outside the lumen)``, or None when no tree sample projects near the curve.

        Only the tree samples projected (at the start) within the gate plus ``CROP_MARGIN_PX`` of
        the curve's bounding box are looked at. Correspondences (each curve point's nearest
        projected sample and its tangent) are found at the start and again every other iteration (a
        frame's motion is a few px, so point-to-line steps with fixed pairs converge in between),
        and once more at the solution, which is scored: the MAP objective (pseudo-Huber of the
        gated distances, one point per ``fit_correlation_mm`` of the curve, plus the priors), the
        fraction of the curve within ``inlier_px`` of the projected lumen and how far outside it.
        One compiled call (``kernels.motion_solve``; tests/test_motion.py holds the numpy code it
        replaced, and checks that they agree)."""
        opt = self.options
        found, cost, delta, H, it, frac, mean_res, J, w, j, lumen_px = kernels.motion_solve(
            c, self._Y0, self._c, self._nbr, self._radius_mm, focal_px=self._f, principal_point_px=self._pp,
            start=start, prev=prev, Lambda0=self._Lambda0, Lt=Lt, sigma_px=opt.sigma_px, huber_px=opt.huber_px,
            gate_px=opt.gate_px, inlier_px=opt.inlier_px, crop_px=opt.gate_px + CROP_MARGIN_PX,
            fit_correlation_mm=opt.fit_correlation_mm,
            iterations=int(opt.iterations if iterations is None else iterations), step_tol_mm=STEP_TOL_MM,
            step_tol_rad=STEP_TOL_RAD)
        if not found:
            return None
        self._last_fit = (c, J, w, lumen_px, j)
        return float(cost), delta, H, int(it), float(frac), float(mean_res)

    def _acquire(self, c, delta) -> list:
        """Starts for a frame without a fitted predecessor: ``delta`` and the cranio-caudal shifts
        (1 mm steps within ``acquire_range_mm``) at the best local minima of how far the curve lies
        from the projected tree (a wire can fit a neighbouring vessel too: each start is solved
        and the best fit kept)."""
        opt = self.options
        a = self.cc_cam
        if np.linalg.norm(a[:2]) <= MIN_CC_IN_PLANE:
            return [delta]
        uv = self._project(self._moved(delta))
        step_px = self._f / self._c[2] * a[:2]  # image shift of 1 mm along the axis, at the centroid
        shifts = np.arange(-opt.acquire_range_mm, opt.acquire_range_mm + 0.5, 1.0)
        # per shift, sum over the curve of min(distance to the projected tree samples, gate)^2
        cost = kernels.motion_acquire_costs(uv, c, step_px, shifts, gate_px=opt.gate_px)
        interior = (cost[1:-1] <= cost[:-2]) & (cost[1:-1] <= cost[2:])
        minima = np.r_[cost[0] <= cost[1], interior, cost[-1] <= cost[-2]]
        order = [k for k in np.argsort(cost) if minima[k]][:ACQUIRE_STARTS]
        starts = [delta]
        for k in order:
            out = delta.copy()
            out[:3] += shifts[k] * a
            starts.append(out)
        return starts

def track_poses(tree: VesselTree, curves_uv_px, carm: CArm, initial_pose: Pose, *, covariance=None,
                options: MotionOptions | None = None) -> list:
    """Follow the pose through a sequence of frames.

    Parameters
    ----------
    tree : VesselTree
        The vessel centerline tree, LPS mm.
    curves_uv_px : sequence of (N_k, 2) ndarray
        Per frame, the 2D wire or catheter (proximal -> distal, px); an empty one holds the pose.
    carm : CArm
        The frames' view.
    initial_pose : Pose
        The roadmap registration (the prior's centre and the first frame's start).
    covariance : (6, 6) ndarray, optional
        The roadmap registration's covariance.

    Returns
    -------
    list of registration.RegistrationResult
        One per frame: ``pose``, ``mean_residual_px``, ``inlier_fraction``, ``verdict``, ``message``.
    """
    tracker = MotionTracker(tree, carm, initial_pose, covariance=covariance, options=options)
    return [tracker.update(c) for c in curves_uv_px]


def curve_to_tree_distance_px(curve_uv_px, tree: VesselTree, carm: CArm, pose: Pose) -> np.ndarray:
    """Distance (px) of each curve point to the nearest segment of the projected tree (N,)."""
    c = np.asarray(curve_uv_px, float).reshape(-1, 2)
    uv = carm.project(tree.points_lps_mm, pose)
    e = np.flatnonzero(tree.parent >= 0)
    A, B = uv[e], uv[tree.parent[e]]
    out = np.empty(len(c))
    AB = B - A
    L2 = np.maximum(np.einsum("ij,ij->i", AB, AB), 1e-12)
    for k0 in range(0, len(c), 256):
        P = c[k0:k0 + 256, None, :]
        s = np.clip(np.einsum("mij,ij->mi", P - A[None], AB) / L2, 0.0, 1.0)
        Q = A[None] + s[..., None] * AB[None]
        out[k0:k0 + 256] = np.sqrt(np.min(np.sum((P - Q) ** 2, axis=2), axis=1))
    return out
