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
from guidewire3d.geometry import CArm, Pose, fine_pixel_factor, hat, so3_exp, options_in_mm
from guidewire3d.registration import RegistrationResult
from guidewire3d.vesseltree import VesselTree

__all__ = ["MotionOptions", "MotionTracker", "track_poses", "curve_to_tree_distance_px", "BiplaneMotionTracker",
           "track_poses_biplane", "biplane_update_planes", "MOTION_PIXEL_OPTIONS"]

#: how a ``BiplaneMotionTracker`` result's message says which planes updated the pose (:func:`biplane_update_planes`
#: reads it back: the two are kept together here)
BOTH_PLANES_MESSAGE = "tracked from both planes"
ONE_PLANE_MESSAGE = "plane {} alone (one-view priors)"

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
#: a first frame's search also looks across the patient's axis (mm, each side; 0: off), at
#: ``ACROSS_STEP_MM`` steps, for rival fits only: its best ``ACROSS_STARTS`` 2D local minima off the
#: axis are solved and count as the frame's rivals (``MotionOptions.settle_rival_cost``), never as its
#: pose. Breathing with a cardiac contraction moves a wire's vessel across the axis too; the axis
#: search alone then kept the roadmap pose, where a short wire lay in another vessel's projected
#: lumen 12 mm from its own (bench_stress wide seed 5213: tips 12-15 mm off, reported ok). Adopting
#: those minima as the pose was tried and dropped (bench_motion's simulator: 3D wire 0.87 -> 1.23 mm)
ACROSS_RANGE_MM = 8.0
ACROSS_STEP_MM = 4.0
ACROSS_STARTS = 2
#: ... on a grid of this step along the axis (mm), with at most ``SETTLE_CURVE_POINTS`` of the curve
#: (the starts are solved with the whole curve): 0.4 ms of CPU per search instead of 13 ms at 1 and
#: 2 mm steps with 128 points
ACROSS_ALONG_STEP_MM = 2.0
SETTLE_ITERATIONS = 4
#: Gauss-Newton stops when a step moves less than this (mm, rad): 0.01 mm is 0.05 px at the isocentre
STEP_TOL_MM = 0.01
STEP_TOL_RAD = 1e-5
#: tree samples projected farther than the gate plus this outside the curve's bounding box are
#: not looked at in a frame (a frame moves the tree by a few px)
CROP_MARGIN_PX = 30.0
#: the options in pixels widened on a view finer than ``geometry.REFERENCE_PIXEL_AT_ISO_MM`` to their size
#: in mm there (``geometry.fine_pixel_factor``; the biplane tracker per view), with ``CROP_MARGIN_PX``: the
#: gate, a reach (at 1024 px, 40 px was a 3.6 mm gate against breathing of 20 mm). A view at the reference
#: or coarser: exactly as before. The noise model and the verdict's "in the lumen" (``sigma_px``,
#: ``huber_px``, ``inlier_px``, ``max_mean_residual_px``) stay in px: widened too, the fit's costs shrink
#: against ``settle_rival_cost`` and ``bench_motion --only sim`` lost 9 right ``ok`` frames ("not settled",
#: views at 0.11-0.14 mm) and caught no wrong one
MOTION_PIXEL_OPTIONS = ("gate_px",)


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
    #: biplane (``BiplaneMotionTracker``), a frame with a curve in both planes: the depth along plane
    #: A's beam is seen by plane B, so the roadmap prior on it is loose (1 sigma, mm, in every
    #: direction across the patient's axis; along it ``sigma_cc_mm`` as in one view; no tie of depth to
    #: the cranio-caudal shift), and the temporal prior holds all three translations
    #: (``sigma_step_inplane_mm``). The rotations keep a prior (1 sigma, deg, about each axis): a wire is
    #: a curve, and no number of views sees a rotation about its own axis; on the simulator's breathing
    #: (true curves, seeds 1-3) 2 deg let the tree turn 2-4 deg off (pose 1.1-1.3 mm), 0.5 deg
    #: held it (0.6-1.1 mm), about as the one-view prior (0.5 deg tilt, 1 deg spin); translation 1 or
    #: 4 mm instead of 2 changed the pose by 0.1 mm at most
    biplane_sigma_mm: float = 2.0
    biplane_sigma_rotation_deg: float = 0.5
    #: biplane, in the Gauss-Newton steps of a two-view fit: a curve point within this many projected
    #: radii of the centerline has no residual, one beyond it the distance beyond (the wire rides
    #: anywhere inside the lumen); the scoring and the verdict use the distance to the centerline as in
    #: one view. 0 (default): the centerline objective. On true 2D wires (simulator, breathing 15 mm and
    #: cardiac 2 mm, seeds 1-5 x 30 frames, pose mTRE mean over the five; plane A alone 1.48 mm) 0.96 mm
    #: with 0, 0.89 mm with 0.3, 0.97 mm with 0.5, and 0.8 lost a sequence (5 mm off): mixed seed by
    #: seed, so not the default
    biplane_lumen_slack: float = 0.0

    def __post_init__(self):
        for name in ("sigma_cc_mm", "sigma_across_mm", "sigma_depth_mm", "sigma_tilt_deg", "sigma_spin_deg",
                     "sigma_step_inplane_mm", "acquire_range_mm", "sigma_px", "huber_px",
                     "gate_px", "sample_mm", "inlier_px", "max_mean_residual_px", "max_depth_shift_mm",
                     "cov_lumen_spread", "cov_correlation_mm", "cov_sigma_depth_mm", "cov_sigma_tilt_deg",
                     "cov_sigma_spin_deg", "max_unsettled_mm", "fit_correlation_mm", "biplane_sigma_mm",
                     "biplane_sigma_rotation_deg"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"MotionOptions.{name}: expected a positive number, got {v!r}")
        if int(self.iterations) < 1:
            raise InputError(f"MotionOptions.iterations: expected >= 1, got {self.iterations!r}")
        if not (np.isfinite(self.biplane_lumen_slack) and self.biplane_lumen_slack >= 0):
            raise InputError(f"MotionOptions.biplane_lumen_slack: expected a number >= 0, got {self.biplane_lumen_slack!r}")
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


def _settle(trk, opt: MotionOptions, tracked: bool, second_opinion, rivals, alone: str) -> str:
    """The second opinion's schedule (``MotionOptions.settle_every``) for a tracker ``trk`` (its
    ``_since_check`` and ``unsettled_mm`` updated): a tracked frame is solved alone every
    ``settle_every`` frames, and every frame while that disagrees (``second_opinion()``, mm); a first
    frame's other starts are its second opinion (``rivals()``, mm). Returns the verdict message's
    suffix when the pose is not settled (the frame is then not ``ok``), else ""."""
    if opt.settle_every <= 0:
        trk.unsettled_mm = 0.0
        return ""
    if tracked:
        trk._since_check += 1
        if trk._since_check >= int(opt.settle_every) or trk.unsettled_mm > opt.max_unsettled_mm:
            trk._since_check = 0
            trk.unsettled_mm = second_opinion()
        what = f"tracked pose not settled: {alone} the wire's vessels"
    else:
        trk._since_check = 0
        trk.unsettled_mm = rivals()
        what = "acquired pose not settled: another fit almost as good puts the wire's vessels"
    if trk.unsettled_mm > opt.max_unsettled_mm:
        return f"; {what} {trk.unsettled_mm:.1f} mm elsewhere (limit {opt.max_unsettled_mm:g} mm)"
    return ""


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
        Its lengths in pixels (``MOTION_PIXEL_OPTIONS``) hold at ``geometry.REFERENCE_PIXEL_AT_ISO_MM``;
        ``self.options`` has them widened on a finer ``carm`` (``geometry.options_in_mm``).
    """

    def __init__(self, tree: VesselTree, carm: CArm, initial_pose: Pose, *, covariance=None,
                 options: MotionOptions | None = None):
        self.tree, self.carm, self.initial_pose = tree, carm, initial_pose
        self.options = opt = options_in_mm(options or MotionOptions(), MOTION_PIXEL_OPTIONS, carm.pixel_at_iso_mm)
        self._crop_margin_px = CROP_MARGIN_PX * fine_pixel_factor(carm.pixel_at_iso_mm)
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
        c = _prepare_curve(curve_uv_px)
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
        rivals = list(sols)
        if not tracked:  # rivals across the patient's axis (never the pose: ACROSS_RANGE_MM)
            for start in self._across_starts(c, prev):
                sol = self._solve(c, start, prev, Lt)
                if sol is not None:
                    rivals.append(sol)
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
            unsettled = _settle(self, opt, tracked, lambda: self._second_opinion_mm(c, delta, fit[4]),
                                lambda: self._rivals_mm(rivals, delta, fit[4]), "this frame's curve alone puts")
            ok = ok and not unsettled
            msg += unsettled
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
        (from the ``SETTLE_STARTS`` best cranio-caudal shifts of the roadmap pose and the best shifts
        across the axis, ``_across_starts``, no temporal prior;
        the best fit and those within ``settle_rival_cost`` of it) puts the tree from where
        ``delta`` puts it."""
        zero = np.zeros(6)
        c = _evenly(c, SETTLE_CURVE_POINTS)  # a coarse answer suffices (it is compared with a limit of mm)
        starts = self._acquire(c, zero)
        starts = (starts[1:1 + SETTLE_STARTS] if len(starts) > 1 else starts) + self._across_starts(c, zero)
        sols = [self._solve(c, start, zero, self._no_Lt, iterations=SETTLE_ITERATIONS) for start in starts]
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
        L = self._Lambda_cal
        if J is not None:
            L = L + self._curve_information(c, J, w, lumen_px)
        return np.linalg.inv(L)

    def _curve_information(self, c, J, w, lumen_px) -> np.ndarray:
        """(6, 6) what the curve tells about ``delta`` in the reported covariance (``MotionOptions.cov_*``):
        its points inside the gate (``w > 0``) place the lumen to ``sigma_px`` plus ``cov_lumen_spread``
        projected radii, counted once per ``cov_correlation_mm`` of the curve's length."""
        opt = self.options
        inl = w > 0
        n = int(inl.sum())
        if not n:
            return np.zeros((6, 6))
        wi = inl / (opt.sigma_px**2 + (opt.cov_lumen_spread * lumen_px) ** 2)
        length_mm = float(np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1))) * self._c[2] / self._f
        kappa = min(1.0, max(1.0, length_mm / opt.cov_correlation_mm) / n)
        return kappa * (J.T @ (J * wi[:, None]))

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
            gate_px=opt.gate_px, inlier_px=opt.inlier_px, crop_px=opt.gate_px + self._crop_margin_px,
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
        shifts = _acquire_shifts(self.options)
        # per shift, sum over the curve of min(distance to the projected tree samples, gate)^2
        cost = self._acquire_costs(c, delta, shifts)
        if cost is None:
            return [delta]
        return _starts_from_costs(delta, self.cc_cam, shifts, cost)

    def _across_starts(self, c, delta) -> list:
        """Starts off the patient's axis for a first frame's rival fits: ``delta`` shifted by the
        (along, across) offsets at the ``ACROSS_STARTS`` best local minima (3 x 3 neighbourhoods) of how
        far the curve lies from the projected tree, over ``ACROSS_ALONG_STEP_MM`` steps along (the
        axis search's range) and ``ACROSS_STEP_MM`` steps within ``ACROSS_RANGE_MM`` across (the
        axis itself excluded: its
        minima are the frame's own starts). Empty when the axis is nearly along the beam."""
        from scipy import ndimage as ndi

        a = self.cc_cam
        n_in = float(np.linalg.norm(a[:2]))
        if ACROSS_RANGE_MM <= 0 or n_in <= MIN_CC_IN_PLANE:
            return []
        across = np.array([-a[1], a[0], 0.0]) / n_in  # in the image plane, normal to the axis's image
        rng = self.options.acquire_range_mm
        shifts = np.arange(-rng, rng + 1e-9, ACROSS_ALONG_STEP_MM)
        c = _evenly(c, SETTLE_CURVE_POINTS)
        offsets = np.arange(-ACROSS_RANGE_MM, ACROSS_RANGE_MM + 1e-9, ACROSS_STEP_MM)
        uv = self._project(self._moved(delta))
        px_per_mm = self._f / self._c[2]
        grid = np.array([kernels.motion_acquire_costs(uv + o * px_per_mm * across[:2], c, px_per_mm * a[:2], shifts,
                                                      gate_px=self.options.gate_px) for o in offsets])
        minima = grid <= ndi.minimum_filter(grid, size=3, mode="nearest")
        minima[np.abs(offsets) < 1e-9, :] = False
        cand = np.argwhere(minima)
        cand = cand[np.argsort(grid[minima], kind="stable")][:ACROSS_STARTS]
        starts = []
        for i, k in cand:
            out = np.array(delta, float).copy()
            out[:3] += shifts[k] * a + offsets[i] * across
            starts.append(out)
        return starts

    # --- pieces of the solve that the biplane tracker runs per view (``BiplaneMotionTracker``) -------
    def _crop(self, c, delta) -> np.ndarray:
        """The tree samples (indices) projected at ``delta`` within the gate plus ``CROP_MARGIN_PX`` of
        the curve's bounding box (as ``kernels.motion_solve`` selects them)."""
        crop = self.options.gate_px + self._crop_margin_px
        uv = self._project(self._moved(delta))
        lo, hi = c.min(axis=0) - crop, c.max(axis=0) + crop
        return np.flatnonzero(np.all((uv >= lo) & (uv <= hi), axis=1))

    def _point_weight(self, c) -> float:
        """Each curve point's weight in the fit: one point per ``fit_correlation_mm`` of the curve's
        length at the centroid's depth, at most one per point (as ``kernels.motion_solve``)."""
        length_mm = float(np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1))) * self._c[2] / self._f
        return min(1.0, max(1.0, length_mm / self.options.fit_correlation_mm) / len(c))

    def _acquire_costs(self, c, delta, shifts):
        """For each cranio-caudal shift (mm, (M,)), how far the curve lies from the projected tree
        (``kernels.motion_acquire_costs``); None when the patient's axis is nearly along the beam."""
        a = self.cc_cam
        if np.linalg.norm(a[:2]) <= MIN_CC_IN_PLANE:
            return None
        uv = self._project(self._moved(delta))
        step_px = self._f / self._c[2] * a[:2]
        return kernels.motion_acquire_costs(uv, c, step_px, shifts, gate_px=self.options.gate_px)


def _acquire_shifts(opt: MotionOptions) -> np.ndarray:
    """The cranio-caudal shifts (mm) a frame without a fitted predecessor searches: 1 mm steps."""
    return np.arange(-opt.acquire_range_mm, opt.acquire_range_mm + 0.5, 1.0)


def _starts_from_costs(delta, a, shifts, cost) -> list:
    """``delta`` and ``delta`` shifted along ``a`` (the patient's axis, camera axes) by the shifts at the
    ``ACQUIRE_STARTS`` best local minima of ``cost``."""
    interior = (cost[1:-1] <= cost[:-2]) & (cost[1:-1] <= cost[2:])
    minima = np.r_[cost[0] <= cost[1], interior, cost[-1] <= cost[-2]]
    order = [k for k in np.argsort(cost) if minima[k]][:ACQUIRE_STARTS]
    starts = [delta]
    for k in order:
        out = delta.copy()
        out[:3] += shifts[k] * a
        starts.append(out)
    return starts


def _evenly(c: np.ndarray, n: int) -> np.ndarray:
    """At most ``n`` evenly spaced points of the curve ``c`` (``c`` itself when it has no more)."""
    return c[np.linspace(0, len(c) - 1, n).round().astype(int)] if len(c) > n else c


def _prepare_curve(curve_uv_px) -> np.ndarray:
    """A frame's curve as the tracker uses it: (N, 2) finite px, at most ``MAX_CURVE_POINTS`` evenly
    spaced points (a 1-px ordered wire has hundreds); empty for None."""
    c = np.asarray(curve_uv_px, float).reshape(-1, 2) if curve_uv_px is not None else np.zeros((0, 2))
    c = c[np.all(np.isfinite(c), axis=1)]
    c = _evenly(c, MAX_CURVE_POINTS)
    return c


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


#: the two planes' names in messages
PLANES = ("A", "B")


class BiplaneMotionTracker:
    """Per-frame pose tracking from two views at once (biplane: planes A and B about one isocentre).

    One ``MotionTracker`` per plane holds that view's tree samples, projection and one-view priors.
    A frame with a curve in both planes is one MAP solve over both views' residuals: each view's
    point-to-tangent residuals and Jacobian (``kernels.motion_linearize``, the inner loop of the
    one-view solve) are expressed in plane A's ``delta`` (plane B's ``delta`` is the same rigid motion
    in its own camera axes: ``delta_b = blockdiag(M, M) delta_a`` with ``M = R_b R_a^T``, both about the
    tree's centroid) and their normal equations are summed. Plane B sees plane A's depth and the
    rotations out of its image plane, so the roadmap prior on them is loose
    (``MotionOptions.biplane_sigma_mm``, ``biplane_sigma_rotation_deg``) and the temporal prior holds
    all three translations. Schedule as the one-view solve: correspondences at the start and every
    other iteration, the cranio-caudal search of a first frame over both views' costs summed, the
    second opinion every ``settle_every`` frames and the rival fits of a first frame.

    A frame with a curve in one plane only is that plane's one-view update (its priors; the state is
    carried over). Verdict: the frame fits when both curves fit (the one-view rule, per plane); when
    one does not, the frame is tracked from the other plane alone and is UNCERTAIN, its message naming
    the plane whose curve does not fit; when neither does, the pose is held (FAILED). The depth limit
    of the one-view tracker (``max_depth_shift_mm``) does not apply to a two-view fit: depth is seen.

    Parameters
    ----------
    tree : VesselTree
    carm_a, carm_b : CArm
        The two planes' live views.
    initial_pose : Pose
        The (joint) roadmap registration ``T_iso_from_lps``.
    covariance : (6, 6) ndarray, optional
        Its covariance (registration convention).
    options : MotionOptions, optional
    """

    def __init__(self, tree: VesselTree, carm_a: CArm, carm_b: CArm, initial_pose: Pose, *, covariance=None,
                 options: MotionOptions | None = None):
        self.options = opt = options or MotionOptions()
        self.initial_pose = initial_pose
        self.planes = tuple(MotionTracker(tree, c, initial_pose, covariance=covariance, options=opt)
                            for c in (carm_a, carm_b))
        kernels.warm_up_motion_views()
        A = self.planes[0]
        M = carm_b.axes @ carm_a.axes.T
        Tb = np.zeros((6, 6))
        Tb[:3, :3] = Tb[3:, 3:] = M
        #: plane k's delta = ``_to_view[k] @`` plane A's delta
        self._to_view = (np.eye(6), Tb)
        deg = np.pi / 180.0
        a = A.cc_cam
        P = np.zeros((6, 6))
        P[:3, :3] = opt.biplane_sigma_mm**2 * np.eye(3) + opt.sigma_cc_mm**2 * np.outer(a, a)
        P[3:, 3:] = (opt.biplane_sigma_rotation_deg * deg) ** 2 * np.eye(3)
        if covariance is not None:
            P = P + A._camera_covariance(covariance)
        self._Lambda0 = np.linalg.inv(P)
        self._Lambda_t = np.zeros((6, 6))
        self._Lambda_t[:3, :3] = np.eye(3) / opt.sigma_step_inplane_mm**2
        self._no_Lt = np.zeros((6, 6))
        self.reset()

    def reset(self) -> None:
        """Back to the roadmap pose, no temporal history."""
        self.delta = np.zeros(6)
        self._has_previous = False
        self._since_check = 0
        self.unsettled_mm = 0.0
        for p in self.planes:
            p.reset()

    def pose_of(self, delta) -> Pose:
        """``T_iso_from_lps`` of the tree moved by ``delta`` (plane A's camera axes, about the centroid)."""
        return self.planes[0].pose_of(delta)

    # --- one frame pair ------------------------------------------------------------------------
    def update(self, curve_a_uv_px, curve_b_uv_px) -> RegistrationResult:
        """Update the pose from one frame pair's curves (``(N, 2)`` px each, either None or empty when
        that plane shows none); returns a ``RegistrationResult`` (pose, verdict, plane-named message)."""
        t0 = time.perf_counter()
        opt = self.options
        cs = [_prepare_curve(curve_a_uv_px), _prepare_curve(curve_b_uv_px)]
        have = [k for k in range(2) if len(cs[k]) >= 3]
        if len(have) < 2:
            if not have:
                pose = self.pose_of(self.delta)
                return RegistrationResult(pose, self.planes[0].carm.projection_matrix(pose), False,
                                          "no curve in either plane: pose held from the previous frame",
                                          float("nan"), 0.0, 0, time.perf_counter() - t0)
            k = have[0]
            return self._one_view(k, cs[k], f"plane {PLANES[1 - k]} shows no curve", t0)
        prev = self.delta.copy()
        tracked = self._has_previous
        Lt = self._Lambda_t if tracked else self._no_Lt
        starts = [prev] if tracked else self._acquire(cs, prev)
        sols = [s for s in (self._solve(cs, start, prev, Lt) for start in starts) if s is not None]
        if not sols:
            return self._one_view_or_hold(cs, prev, "the curves lie away from the projected tree in both planes", t0,
                                          ())
        best = min(sols, key=lambda s: s[0])
        cost, delta, H, it, per_view, lin = best
        # each plane's px limits are its own (``MotionTracker.options``: widened on a view finer than the reference)
        vo = [p.options for p in self.planes]
        fits = [frac >= opt.min_inlier_fraction and mean_res <= vo[k].max_mean_residual_px
                for k, (frac, mean_res) in enumerate(per_view)]
        if not all(fits):
            why = "; ".join(f"plane {PLANES[k]}'s curve does not fit the projected tree at the two-view pose "
                            f"({100 * per_view[k][0]:.0f}% within {vo[k].inlier_px:g} px of the lumen, "
                            f"{per_view[k][1]:.2f} px outside on average)" for k in range(2) if not fits[k])
            return self._one_view_or_hold(cs, prev, why, t0, [k for k in range(2) if fits[k]])
        self.delta = delta
        self._has_previous = True
        frac = float(np.mean([p[0] for p in per_view]))
        mean_res = float(np.mean([p[1] for p in per_view]))
        msg = (f"{BOTH_PLANES_MESSAGE}: {100 * per_view[0][0]:.0f}% / {100 * per_view[1][0]:.0f}% of the curves "
               f"(A / B) in the projected lumen ({per_view[0][1]:.2f} / {per_view[1][1]:.2f} px outside on average); "
               f"moved {np.linalg.norm(delta[:2]):.1f} mm in plane A's image plane, {delta[2]:+.1f} mm along its beam")
        j = np.unique(np.concatenate([v[4] for v in lin]))
        A = self.planes[0]
        unsettled = _settle(self, opt, tracked, lambda: self._second_opinion_mm(cs, delta, j),
                            lambda: A._rivals_mm(sols, delta, j), "this pair's curves alone put")
        ok = not unsettled
        msg += unsettled
        cov = self._reported_covariance(cs, lin)
        pose = self.pose_of(delta)
        return RegistrationResult(pose, A.carm.projection_matrix(pose), ok, msg, mean_res, frac, it,
                                  time.perf_counter() - t0, covariance_6x6=A._A_inv @ cov @ A._A_inv.T,
                                  pose_std_mm=A._tree_std_mm(cov), fits_2d=True)

    def _one_view(self, k: int, c, why: str, t0: float, *, uncertain: bool = False) -> RegistrationResult:
        """Plane ``k``'s one-view update of this frame (its priors), from the two-view state."""
        import dataclasses

        trk, T = self.planes[k], self._to_view[k]
        trk.delta = T @ self.delta
        trk._has_previous = self._has_previous
        trk._since_check, trk.unsettled_mm = self._since_check, self.unsettled_mm
        res = trk.update(c)
        self.delta = T.T @ trk.delta
        self._has_previous = trk._has_previous
        self._since_check, self.unsettled_mm = trk._since_check, trk.unsettled_mm
        msg = f"{why}: {ONE_PLANE_MESSAGE.format(PLANES[k])}: {res.message}"
        return dataclasses.replace(res, message=msg, success=bool(res.success and not uncertain),
                                   seconds=time.perf_counter() - t0)

    def _one_view_or_hold(self, cs, prev, why: str, t0: float, fitting) -> RegistrationResult:
        """A pair whose two-view fit does not fit both curves: tracked from the plane whose curve fits
        (UNCERTAIN), else the pose held (FAILED)."""
        self.delta = prev
        if fitting:
            k = int(fitting[0])
            return self._one_view(k, cs[k], why, t0, uncertain=True)
        pose = self.pose_of(prev)
        return RegistrationResult(pose, self.planes[0].carm.projection_matrix(pose), False,
                                  f"{why}: pose held from the previous frame", float("inf"), 0.0, 0,
                                  time.perf_counter() - t0)

    # --- the two-view solve --------------------------------------------------------------------
    def _solve(self, cs, start, prev, Lt, *, iterations: int | None = None, views=(0, 1)):
        """Gauss-Newton over the views ``views`` from ``start`` (plane A's delta), the schedule of
        ``MotionTracker._solve``: ``(cost, delta, H, iterations, ((inlier fraction, mean px outside the
        lumen) per view), ((c, J, w, lumen px, pairs) per view))``, or None when a view has fewer than
        two tree samples near its curve."""
        opt = self.options
        n_it = int(opt.iterations if iterations is None else iterations)
        vs = []
        for k in views:
            trk, T, c = self.planes[k], self._to_view[k], cs[k]
            sel = trk._crop(c, T @ start)
            if len(sel) < 2:
                return None
            vs.append((trk, T, c, sel, trk._point_weight(c), np.zeros(len(c), np.int64)))
        delta = np.array(start, float)
        H = np.eye(6)
        it = 0
        last = n_it + 1
        lin = [None] * len(vs)
        for it_ in range(1, n_it + 2):
            final = it_ == last
            for i, (trk, T, c, sel, pw, pairs) in enumerate(vs):
                r, J, w, j, lumen = kernels.motion_linearize(
                    c, trk._Y0, trk._c, trk._nbr, trk._radius_mm, focal_px=trk._f, principal_point_px=trk._pp,
                    delta=T @ delta, sel=sel, pairs=pairs if lin[i] is None else lin[i][4],
                    find_pairs=final or it_ % 2 == 1, sigma_px=trk.options.sigma_px, huber_px=trk.options.huber_px,
                    gate_px=trk.options.gate_px, point_weight=pw, lumen_slack=opt.biplane_lumen_slack if len(vs) > 1 and not final else 0.0)
                lin[i] = (r, J, w, lumen, j)
            if final:
                break
            it = it_
            H = self._Lambda0 + Lt
            g = self._Lambda0 @ delta + Lt @ (delta - prev)
            for (trk, T, *_), (r, J, w, _, _) in zip(vs, lin):
                JT = J @ T
                H = H + JT.T @ (JT * w[:, None])
                g = g + JT.T @ (w * r)
            step = -np.linalg.solve(H, g)
            delta = delta + step
            if np.all(np.abs(step[:3]) < STEP_TOL_MM) and np.all(np.abs(step[3:]) < STEP_TOL_RAD):
                last = it_ + 1
        per_view, fit, rob_sum = [], [], 0.0
        for (trk, T, c, sel, pw, _), (r, J, w, lumen, j) in zip(vs, lin):
            vo = trk.options                     # this view's px options (widened on a fine view)
            h = vo.huber_px / vo.sigma_px
            outside = np.maximum(np.abs(r) - lumen, 0.0)
            inl = outside <= vo.inlier_px
            per_view.append((float(inl.mean()), float(outside[inl].mean()) if inl.any() else float("inf")))
            a = np.minimum(np.abs(r), vo.gate_px) / vo.sigma_px
            rob_sum += pw * float(np.sum(2.0 * h * h * (np.sqrt(1.0 + (a / h) ** 2) - 1.0)))
            fit.append((c, J @ T, w, lumen, j))
        dp = delta - prev
        cost = rob_sum + delta @ self._Lambda0 @ delta + dp @ Lt @ dp
        return float(cost), delta, H, it, tuple(per_view), tuple(fit)

    def _acquire(self, cs, delta) -> list:
        """Starts of a pair without a fitted predecessor: ``delta`` and the cranio-caudal shifts at the
        best minima of both views' search costs summed (the same 3D shift in both)."""
        shifts = _acquire_shifts(self.options)
        costs = [self.planes[k]._acquire_costs(cs[k], self._to_view[k] @ delta, shifts) for k in range(2)]
        costs = [c for c in costs if c is not None]
        if not costs:
            return [delta]
        return _starts_from_costs(delta, self.planes[0].cc_cam, shifts, np.sum(costs, axis=0))

    def _second_opinion_mm(self, cs, delta, j) -> float:
        """As ``MotionTracker._second_opinion_mm``, the pair solved alone from both views."""
        zero = np.zeros(6)
        cs = [_evenly(c, SETTLE_CURVE_POINTS) for c in cs]
        starts = self._acquire(cs, zero)
        sols = [self._solve(cs, start, zero, self._no_Lt, iterations=SETTLE_ITERATIONS)
                for start in (starts[1:1 + SETTLE_STARTS] if len(starts) > 1 else starts)]
        return self.planes[0]._rivals_mm([s for s in sols if s is not None], delta, j)

    def _reported_covariance(self, cs, fit) -> np.ndarray:
        """(6, 6) covariance of plane A's delta: the two-view prior and what each curve tells
        (``MotionTracker._curve_information``, per view, in plane A's delta)."""
        L = self._Lambda0.copy()
        for k, (c, JT, w, lumen, _) in enumerate(fit):
            L = L + self.planes[k]._curve_information(c, JT, w, lumen)
        return np.linalg.inv(L)


def biplane_update_planes(result: RegistrationResult) -> str:
    """Which planes' curves updated a pose (``result``: a ``BiplaneMotionTracker.update``'s): ``"AB"`` (the two-view
    fit), ``"A"`` or ``"B"`` (that plane's one-view update: the other showed no curve, or its curve did not fit) or
    ``""`` (none: the pose was held)."""
    msg = str(getattr(result, "message", ""))
    if msg.startswith(BOTH_PLANES_MESSAGE):
        return "AB"
    for p in PLANES:
        if ONE_PLANE_MESSAGE.format(p) in msg:
            return p
    return ""


def track_poses_biplane(tree: VesselTree, curves_a_uv_px, curves_b_uv_px, carm_a: CArm, carm_b: CArm,
                        initial_pose: Pose, *, covariance=None, options: MotionOptions | None = None) -> list:
    """Follow the pose through a sequence of biplane frame pairs (``BiplaneMotionTracker``).

    Parameters
    ----------
    tree : VesselTree
        The vessel centerline tree, LPS mm.
    curves_a_uv_px, curves_b_uv_px : sequences of (N_k, 2) ndarray or None
        Per frame pair, the 2D wire or catheter in plane A and in plane B (proximal -> distal, px);
        None or empty where a plane shows none (that pair is tracked from the other plane alone).
    carm_a, carm_b : CArm
        The two planes' views.
    initial_pose : Pose
        The (joint) roadmap registration.
    covariance : (6, 6) ndarray, optional
        Its covariance.

    Returns
    -------
    list of registration.RegistrationResult
        One per frame pair.
    """
    curves_a, curves_b = list(curves_a_uv_px), list(curves_b_uv_px)
    if len(curves_a) != len(curves_b):
        raise InputError(f"track_poses_biplane: {len(curves_a)} plane-A curves but {len(curves_b)} plane-B curves")
    tracker = BiplaneMotionTracker(tree, carm_a, carm_b, initial_pose, covariance=covariance, options=options)
    return [tracker.update(a, b) for a, b in zip(curves_a, curves_b)]
