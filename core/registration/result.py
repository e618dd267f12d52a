"""The outcome of a registration: :class:`RegistrationResult` and its :class:`Verdict`.

How the quality figures and the verdict are computed: :mod:`guidewire3d.registration.verdict`
(its constants ``INLIER_PX``, ``MAX_POSE_STD_MM``, ``JACKKNIFE_TILES``, ... are named below).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from enum import Enum

import numpy as np
from guidewire3d.geometry import Pose

__all__ = ["RegistrationResult", "Verdict"]


class Verdict(str, Enum):
    """What a registration's quality checks say (:attr:`RegistrationResult.verdict`)."""

    OK = "ok"  # the overlay fits and the pose is determined: ``success``
    UNCERTAIN = "uncertain"  # the overlay fits, but the roadmap leaves the pose open (e.g. a single path's depth)
    FAILED = "failed"  # the 2D centerline does not lie on the projected tree

    @property
    def label(self) -> str:
        """For status lines: ``ok``, ``UNCERTAIN``, ``FAILED``."""
        return self.value if self is Verdict.OK else self.value.upper()


@dataclass(frozen=True, eq=False)
class RegistrationResult:
    """Outcome of a registration (falsy when ``success`` is false).

    Attributes
    ----------
    pose : Pose
        ``T_iso_from_lps``.
    projection_matrix : (3, 4) ndarray
        Homogeneous LPS mm -> homogeneous ``(u, v)`` px for ``pose``.
    success : bool
        False when the residual or the overlap says the pose is not trustworthy.
    message : str
        One line: why it stopped and the quality figures.
    mean_residual_px : float
        Mean distance (px) of the inlier 2D centerline points to the projected 3D centerline.
    inlier_fraction : float
        Fraction of 2D centerline points within ``INLIER_PX`` of the projected 3D centerline.
    iterations : int
        LM iterations (all stages and starts).
    seconds : float
        Wall time, including the global search.
    covariance_6x6 : (6, 6) ndarray or None
        Pose covariance in the left-perturbation tangent space ``(t mm, phi rad)``.
    energy : float
        Final value of the robust energy (narrow gate).
    pose_std_mm : float
        RMS over the tree's points in view (those projecting into the image at ``pose``; all of a tree
        inside the view) of the 1-sigma point displacement implied by ``covariance_6x6`` (mm); large
        when the visible vessels leave a direction undetermined (e.g. a single path).
    single_path : bool
        The roadmap explains essentially one root-to-leaf vessel path of the tree (see
        ``SINGLE_PATH_FRACTION``): its depth along the beam rests on perspective alone, so its
        limit ``max_pose_std_mm`` is ``MAX_POSE_STD_MM_SINGLE_PATH``.
    fits_2d : bool
        The 2D centerline lies on the projected tree (the residual and inlier checks pass). With
        ``success`` false this means the overlay fits but the roadmap leaves the pose uncertain
        (:attr:`verdict` ``Verdict.UNCERTAIN``): a refinement from a user's correction may be adopted.
    explained_fraction : float
        Fraction of the CTA centerline in view (LM samples projecting into the image at ``pose``) that
        the roadmap explains (the visible segments); ``verdict.IN_VIEW_ONLY`` false: of the whole tree.
    max_pose_std_mm : float
        The pose 1-sigma limit (:func:`pose_std_limit_mm` of ``explained_fraction`` and
        ``single_path``): ``success`` needs ``pose_std_mm`` within ``COVARIANCE_SCREEN_FACTOR`` x it
        (a screen), the jackknife within ``JACKKNIFE_FACTOR`` x it and the depth profile's
        half-width (in the message when it refuses) within ``DEPTH_PROFILE_FACTOR`` x it.
    jackknife_std_mm : float
        The second opinion (NaN when not computed, i.e. when the first checks already failed): the
        RMS 1-sigma displacement of the tree from a block jackknife of the pose, each of
        ``JACKKNIFE_TILES`` spatial tiles of the 2D centerline left out in turn and the pose refined
        without it. ``success`` needs it within ``JACKKNIFE_FACTOR x max_pose_std_mm``: a pose that
        rests on one part of the roadmap (a wrong branch match, a segment off as a whole) moves.
    model_std_mm : float
        The fifth opinion (NaN when not computed, i.e. when the covariance's screen already refused): the RMS
        1-sigma displacement of the tree's points in view that a smooth disagreement of the 2D and the projected 3D
        centerline (``MODEL_ERROR_PX`` per component, correlated over ``MODEL_ERROR_LENGTH_PX``) causes, to first
        order; mostly along the beam. Reported; with ``MODEL_ERROR_GATE`` (off by default) ``success`` also needs
        ``hypot(pose_std_mm, model_std_mm)`` within the covariance's screen. It is not in ``covariance_6x6``.
    depth_scan_rise : float
        The fourth opinion (NaN when not computed): the depth scan's smallest rise of the energy at depths
        ``DEPTH_SCAN_FAR_MM`` or more from the result along the beam, the rest of the pose re-fitted, in units
        of the rise the covariance predicts at its depth 1-sigma. ``success`` needs it at least
        ``DEPTH_SCAN_RISE`` (no second minimum along the beam) and no scanned depth fitting better. It is
        computed on a pose the first checks accept (and, with ``DEPTH_SCAN_SCREEN_FACTOR`` > 0, on one
        whose covariance is too wide along the beam only: then the scan, not the covariance, settles the
        depth and the message says so).
    """

    pose: Pose
    projection_matrix: np.ndarray
    success: bool
    message: str
    mean_residual_px: float
    inlier_fraction: float
    iterations: int
    seconds: float
    covariance_6x6: np.ndarray | None = None
    energy: float = float("nan")
    pose_std_mm: float = float("nan")
    single_path: bool = False
    fits_2d: bool = False
    explained_fraction: float = float("nan")
    max_pose_std_mm: float = float("nan")
    jackknife_std_mm: float = float("nan")
    depth_scan_rise: float = float("nan")
    model_std_mm: float = float("nan")

    def __bool__(self) -> bool:
        return bool(self.success)

    @property
    def verdict(self) -> Verdict:
        """OK, UNCERTAIN (the overlay fits, the pose is not determined) or FAILED."""
        return Verdict.OK if self.success else Verdict.UNCERTAIN if self.fits_2d else Verdict.FAILED

    def to_dict(self) -> dict:
        """JSON-able record (plain lists and floats)."""
        return {
            "pose": self.pose.to_dict(),
            "projection_matrix": np.asarray(self.projection_matrix, dtype=float).tolist(),
            "success": bool(self.success),
            "message": str(self.message),
            "mean_residual_px": _json_float(self.mean_residual_px),
            "inlier_fraction": _json_float(self.inlier_fraction),
            "iterations": int(self.iterations),
            "seconds": float(self.seconds),
            "covariance_6x6": None if self.covariance_6x6 is None else np.asarray(self.covariance_6x6).tolist(),
            "energy": _json_float(self.energy),
            "pose_std_mm": _json_float(self.pose_std_mm),
            "single_path": bool(self.single_path),
            "fits_2d": bool(self.fits_2d),
            "explained_fraction": _json_float(self.explained_fraction),
            "max_pose_std_mm": _json_float(self.max_pose_std_mm),
            "jackknife_std_mm": _json_float(self.jackknife_std_mm),
            "depth_scan_rise": _json_float(self.depth_scan_rise),
            "model_std_mm": _json_float(self.model_std_mm),
        }


def _json_float(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def _failed(pose, carm, message, t0, iterations=0) -> RegistrationResult:
    """A failed result at ``pose`` (no quality figures), timed from ``t0``."""
    return RegistrationResult(
        pose=pose, projection_matrix=carm.projection_matrix(pose), success=False, message=message,
        mean_residual_px=float("inf"), inlier_fraction=0.0, iterations=iterations,
        seconds=time.perf_counter() - t0, covariance_6x6=None,
    )
