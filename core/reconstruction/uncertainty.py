"""The uncertainty of each reconstructed point (step 6 of ``single_view``).

Each point has a 3x3 covariance ``Sigma`` of its error *across the wire* (its distance to the
true wire; a slide along the wire is not an error of the wire's shape), reported as
``uncertainty_mm = sqrt(trace Sigma)``, the RMS 3D distance to the true wire it predicts. The
point is on its pixel's ray and inside the CTA lumen, so an error source only counts through the
part the lumen does not absorb. With ``d`` the ray, ``t`` the wire tangent, ``n = d x t / |d x t|``
(normal to ray and vessel) and ``q = t x n`` (across the vessel, in the plane of ray and vessel):

* **Ray shift** ``S``: the paper's ``J+ (sigma_geo^2 I + sigma_img^2 gI gI^T) J+^T``
  (``J+`` the pseudo-inverse of the 2x3 projection Jacobian, ``gI`` the image gradient at
  the pixel when ``image`` is given) plus, if given, the registration covariance pushed
  through the pose (``dX = R^T (-dt + [x]x dphi)`` for a left perturbation): both move the
  ray in CTA coordinates while the vessel stays. It enters as ``A S A^T`` with
  ``A = n n^T + g q m^T`` (``m = n x d``): a shift along ``n`` moves the point across the
  vessel in full; a shift along the ray changes nothing; a shift along ``m`` makes the ray
  meet the vessel further along, i.e. the point *slides along the vessel*, except for the
  fraction ``g = cos / (cos^2 + k^2 sin^2)`` (angle between ray and vessel,
  ``k = ALONG_SCALE_MM / DIST_SCALE_MM``) that the weighted closest approach of ``placement``
  leaves across it when the vessel runs along the beam (exact for that quadratic choice).
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
"""
from __future__ import annotations

import numpy as np
from guidewire3d import kernels
from guidewire3d.errors import InputError
from guidewire3d.reconstruction.placement import ALONG_SCALE_MM, DIST_SCALE_MM

__all__ = ["covariance_lumen", "covariance_unconstrained", "pose_jacobian"]


def _projection_jacobian(ctx, X) -> np.ndarray:
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
        G = pose_jacobian(ctx.pose, X)
        cov += G @ C @ np.transpose(G, (0, 2, 1))
    return cov


def pose_jacobian(pose, points_lps_mm) -> np.ndarray:
    """(M, 3, 6) how a pose error moves the rays at the points ``points_lps_mm`` (M, 3), in CTA mm.

    For a left perturbation ``(tx, ty, tz, rx, ry, rz)`` (mm, rad) of ``pose``,
    ``dX = R^T (-dt + [x]x dphi)`` with ``x`` the point in room coordinates: the registration
    covariance ``C`` (6, 6) becomes ``G C G^T`` at each point.
    """
    x_room = pose.apply(points_lps_mm)
    G = np.zeros((len(x_room), 3, 6))
    G[:, :, :3] = -np.eye(3)
    # -phi x x = [x]x phi
    G[:, 0, 4], G[:, 0, 5] = -x_room[:, 2], x_room[:, 1]
    G[:, 1, 3], G[:, 1, 5] = x_room[:, 2], -x_room[:, 0]
    G[:, 2, 3], G[:, 2, 4] = -x_room[:, 1], x_room[:, 0]
    return pose.R.T[None] @ G


def _check_registration_covariance(registration_covariance) -> np.ndarray:
    C = np.asarray(registration_covariance, dtype=float)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        raise InputError(f"reconstruction: registration_covariance must be a finite 6x6 matrix, got {C.shape}")
    return C


def _outer(a, b=None):
    return a[:, :, None] * (a if b is None else b)[:, None, :]


def covariance_unconstrained(ctx, X, uv, *, depth_std_mm, extra_iso_mm2, image, registration_covariance, opt):
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

    vals = img[np.stack([vi, vi, vi + 1, vi - 1]), np.stack([ui + 1, ui - 1, ui, ui])].astype(float)
    g = 0.5 * np.column_stack([vals[0] - vals[1], vals[2] - vals[3]])
    lo, hi = float(img.min()), float(img.max())
    if img.dtype.kind == "f" and (np.isnan(lo) or np.isnan(hi)):  # (min and max are faster than nanmin, nanmax)
        lo, hi = float(np.nanmin(img)), float(np.nanmax(img))
    return g / (hi - lo) if hi > lo else np.zeros_like(g)  # intensities normalised to [0, 1] (paper)


#: :func:`beyond_path_mm2`: the depth spread of a wire point beyond the path's last anchor, per mm of
#: wire (in the image plane, at the tree's depth) between that anchor and the point. Those anchors fit
#: no lumen of the tree: the wire there has left the path's vessels (a vessel the CTA tree lacks, or a
#: wrong path) and its depth is extrapolated from the path's end; at 45 degrees to the image plane it
#: moves in depth as much as across it. Off, the tip of a wire running 12 mm past its tracked path's end
#: (``bench_stress --draws wide`` 5006 f5) was reported 25 mm off along the beam with a 2.2 mm 1-sigma, ``ok``.
BEYOND_PATH_DEPTH_PER_MM = 1.0


def beyond_path_mm2(ctx, uv, last_anchor: int) -> tuple[np.ndarray, float]:
    """(M, 3, 3) second moment along each wire point's ray of its depth beyond the path's end, and the
    wire's length past that end (mm).

    ``uv`` (M, 2): the 2D wire; ``last_anchor``: the index in it of the last anchor the path through
    the tree explains. A point past it gets ``(BEYOND_PATH_DEPTH_PER_MM L)^2 d d^T``, ``L`` its 2D arclength
    past that anchor in mm at the tree's depth (``ctx.px_mm``), ``d`` its unit ray; the others zero. The
    length is the last point's ``L``.
    """
    uv = np.asarray(uv, dtype=float)
    s_px = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(uv, axis=0), axis=1))]
    past_mm = np.maximum(s_px - s_px[int(last_anchor)], 0.0) * ctx.px_mm
    spread = past_mm * BEYOND_PATH_DEPTH_PER_MM
    d = ctx.rays(uv)
    return (spread**2)[:, None, None] * d[:, :, None] * d[:, None, :], float(past_mm[-1])


def covariance_lumen(ctx, X, uv, *, tangent, half_width_mm, miss_mm, image, registration_covariance, opt,
                     ambiguity_mm2=None):
    """(M, 3, 3) covariance of points placed in the lumen (``ReconMethod.VESSEL``), see the module doc.

    ``tangent`` (M, 3): unit wire direction at each point; ``half_width_mm`` (M,): half width,
    across the vessel and in the plane of the ray, of the room the wire's centre has
    (``sqrt(rho^2 - dist^2)``); ``miss_mm`` (M,): how far the ray passes outside that room (0 inside).
    ``A S A^T`` is evaluated through the three scalars ``n^T S n``, ``n^T S m``, ``m^T S m``.
    """
    d = ctx.rays(uv)
    g = _image_gradient(image, uv) if image is not None else None
    C = _check_registration_covariance(registration_covariance) if registration_covariance is not None else None
    # per point (compiled, kernels.lumen_covariance): n = d x t / |d x t| (any normal to the ray where
    # the ray runs along the vessel), q = t x n, m = n x d; v^T S w = (J+^T v)^T S2 (J+^T w)
    # (+ (G^T v)^T C (G^T w), G^T v = -(R v, x x R v)); a sideways ray shift along m slides the point
    # along the vessel as long as the placement can follow it: the weighted closest approach of
    # place_on_path leaves the fraction gain = cos / (cos^2 + k^2 sin^2) of it across the vessel,
    # k = along / dist scale. Then a = s_nn + miss^2, b = gain s_nm (+ the ambiguity's n^T B n,
    # n^T B q), c = gain^2 s_mm + (lumen_spread w)^2 + sigma_centerline^2 + miss^2 (+ q^T B q) and
    # Sigma = a n n^T + b (n q^T + q n^T) + c q q^T: where the wire sits in the lumen (across the
    # vessel, along q), the CTA centerline error, a ray that misses the path's tube by miss_mm
    # (that much more across the wire) and another branch at another depth (its part across the wire)
    return kernels.lumen_covariance(
        d, tangent, X, Rc=ctx.Rc, tc=ctx.tc, focal_px=ctx.focal, pose_R=ctx.pose.R, pose_t=ctx.pose.t,
        sigma_geo_px=opt.sigma_geo_px, image_gradient=g, sigma_img=opt.sigma_img, registration_covariance=C,
        half_width_mm=half_width_mm, miss_mm=miss_mm, ambiguity_mm2=ambiguity_mm2,
        k2=(ALONG_SCALE_MM / DIST_SCALE_MM) ** 2, lumen_spread=opt.lumen_spread,
        sigma_centerline_mm=opt.sigma_centerline_mm)
