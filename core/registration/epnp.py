"""The paper's baseline: the pose from matched 3D/2D landmarks by EPnP (:func:`register_epnp`), with
the tree's bifurcations matched to 2D branch points (:func:`match_bifurcations`)."""
from __future__ import annotations

import time

import guidewire3d.registration.verdict as verdict  # its limits are read at call time (tests patch them)
import numpy as np
from guidewire3d.errors import InputError
from guidewire3d.geometry import CArm, Pose, nominal_pose
from guidewire3d.registration.model import _check_2d
from guidewire3d.registration.result import RegistrationResult, _failed
from guidewire3d.vesseltree import VesselTree
from scipy.optimize import linear_sum_assignment

__all__ = ["register_epnp", "match_bifurcations"]


def _mirror() -> np.ndarray:
    return np.diag([-1.0, 1.0, 1.0])


def register_epnp(tree_landmarks_lps_mm, landmarks_uv_px, carm: CArm) -> RegistrationResult:
    """Pose from matched 3D/2D landmarks with OpenCV ``solvePnP(SOLVEPNP_EPNP)`` (paper's baseline).

    The C-arm camera of DESIGN.md has ``det R = -1`` (the radiological display mirrors the
    camera). OpenCV needs a proper camera, so the mirrored one is converted by flipping its
    x axis: ``R' = F R``, ``t' = F t`` with ``F = diag(-1, 1, 1)``, which in the image is
    ``u' = 2 c_u - u``. EPnP is solved on ``(X, u')`` and the result mapped back with ``F``.

    Parameters
    ----------
    tree_landmarks_lps_mm : (K, 3) ndarray of float
    landmarks_uv_px : (K, 2) ndarray of float
        Matched pairs (``K >= 4``).
    carm : CArm

    Returns
    -------
    RegistrationResult
        ``mean_residual_px`` is the landmark reprojection error; ``success`` needs ``K >= 4``, a
        finite solution and a mean reprojection error <= ``verdict.MAX_MEAN_RESIDUAL_PX``.
    """
    import cv2

    t0 = time.perf_counter()
    if not isinstance(carm, CArm):
        raise InputError(f"carm must be a CArm, got {type(carm).__name__}")
    X = np.asarray(tree_landmarks_lps_mm, dtype=float)
    uv = np.asarray(landmarks_uv_px, dtype=float)
    if X.ndim != 2 or X.shape[1] != 3 or uv.ndim != 2 or uv.shape[1] != 2 or len(X) != len(uv):
        raise InputError(f"landmarks must be (K, 3) and (K, 2) with equal K, got {X.shape} and {uv.shape}")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(uv))):
        raise InputError("landmarks contain non-finite values")
    fallback = nominal_pose(X.mean(axis=0)) if len(X) else Pose.identity()
    if len(X) < 4:
        return _failed(fallback, carm, f"EPnP needs >= 4 landmark pairs, got {len(X)}", t0)
    K = carm.intrinsics()
    uvm = uv.copy()
    uvm[:, 0] = 2.0 * carm.principal_point_px[0] - uv[:, 0]
    ok, rvec, tvec = cv2.solvePnP(X.reshape(-1, 1, 3), uvm.reshape(-1, 1, 2), K, None, flags=cv2.SOLVEPNP_EPNP)
    if not ok or not np.all(np.isfinite(rvec)) or not np.all(np.isfinite(tvec)):
        return _failed(fallback, carm, "EPnP found no solution", t0)
    Rp, _ = cv2.Rodrigues(rvec)
    F = _mirror()
    R_cam, t_cam = F @ Rp, F @ tvec.reshape(3)
    A = carm.axes
    try:
        pose = Pose(A.T @ R_cam, A.T @ t_cam + carm.source_room_mm)
    except Exception as e:  # numerically not a rotation
        return _failed(fallback, carm, f"EPnP returned an invalid pose ({e})", t0)
    res = np.linalg.norm(carm.project(X, pose) - uv, axis=1)
    mean = float(res.mean())
    frac = float(np.mean(res <= verdict.INLIER_PX))
    ok = mean <= verdict.MAX_MEAN_RESIDUAL_PX
    msg = f"EPnP on {len(X)} landmarks; mean reprojection {mean:.2f} px"
    return RegistrationResult(
        pose=pose, projection_matrix=carm.projection_matrix(pose), success=bool(ok),
        message=msg if ok else "untrustworthy: " + msg, mean_residual_px=mean, inlier_fraction=frac,
        iterations=1, seconds=time.perf_counter() - t0, covariance_6x6=None, fits_2d=bool(ok),
    )


def match_bifurcations(tree, centerline2d_branchpoints_uv_px, carm: CArm, init_pose: Pose, *,
                       max_distance_px: float = 25.0, n_rounds: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Match the tree's bifurcations to 2D branch points for the EPnP baseline.

    The 3D bifurcations are projected with ``init_pose`` and assigned to the 2D branch points by
    the Hungarian method on pixel distance; a global image shift (the median offset of the
    matched pairs) is re-estimated and the assignment repeated ``n_rounds`` times, so a start
    that is off by a translation still matches. Pairs farther than ``max_distance_px`` (after
    the shift) are dropped.

    Parameters
    ----------
    tree : VesselTree
    centerline2d_branchpoints_uv_px : (B, 2) ndarray of float
    carm : CArm
    init_pose : Pose

    Returns
    -------
    idx3d : (K,) ndarray of int
        Point indices into ``tree.points_lps_mm``.
    idx2d : (K,) ndarray of int
        Row indices into the branch points.
    """
    if not isinstance(tree, VesselTree):
        raise InputError(f"match_bifurcations needs a VesselTree (for its bifurcations), got {type(tree).__name__}")
    bp = _check_2d(centerline2d_branchpoints_uv_px, "centerline2d_branchpoints_uv_px")
    bif = tree.bifurcations
    empty = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    if len(bif) == 0 or len(bp) == 0:
        return empty
    uv = carm.project(tree.points_lps_mm[bif], init_pose)
    good = np.isfinite(uv).all(axis=1)
    bif, uv = bif[good], uv[good]
    if len(bif) == 0:
        return empty
    shift = np.zeros(2)
    r = c = np.zeros(0, dtype=np.int64)
    for k in range(max(1, int(n_rounds))):
        D = np.linalg.norm((uv + shift)[:, None, :] - bp[None, :, :], axis=2)
        r, c = linear_sum_assignment(D)
        keep = D[r, c] <= (max_distance_px if k > 0 else 4.0 * max_distance_px)
        if keep.sum() == 0:
            return empty
        shift = np.median(bp[c[keep]] - uv[r[keep]], axis=0)
    D = np.linalg.norm((uv + shift)[:, None, :] - bp[None, :, :], axis=2)
    keep = D[r, c] <= max_distance_px
    return bif[r[keep]].astype(np.int64), c[keep].astype(np.int64)
