"""3D-2D registration of the CTA vessel centerline to the 2D roadmap centerline (issue 6): the entry points.

The unknown is the pose ``T = T_iso_from_lps`` of :mod:`guidewire3d.geometry` (CTA LPS -> C-arm
room frame with its origin at the isocentre); the C-arm angles, SID, SOD and pixel size are
known from the DICOM tags. The pipeline of :func:`register` is the paper's:

1. **Start**: the DICOM angles with the isocentre at the vessel-tree centroid
   (:func:`guidewire3d.geometry.nominal_pose`), or a given ``init_pose``.
2. **Coarse global search** (``global_search=True``): a rotation grid about the vessel centroid
   and, for each rotation, an exhaustive in-plane translation search by FFT chamfer
   (:mod:`guidewire3d.registration.search`).
3. **Levenberg-Marquardt on se(3)** of the robust bidirectional energy
   (:mod:`guidewire3d.registration.problem`) from the best ``SEARCH_STARTS`` candidates (wide gate,
   kernel cutoff ``DELTA_WIDE``), then from the best of them with the paper's cutoff and a narrow gate.
4. **Verdict**: quality figures, covariance and a jackknife second opinion
   (:mod:`guidewire3d.registration.verdict`).

:func:`refine` runs LM alone from a user-corrected pose, :func:`nudge` applies the correction.

Depth along the beam is the weakest direction of any single-view registration (a 1 mm depth
change moves the projection of a 70 mm tree by ~0.1 px on average); systematic 2D extraction
errors therefore show up mostly as depth error.
"""
from __future__ import annotations

import time

import guidewire3d.registration.problem as problem  # its constants are read at call time (tests patch them)
import numpy as np
from guidewire3d.errors import InputError
from guidewire3d.geometry import CArm, Pose, nominal_pose
from guidewire3d.registration.model import _check_2d, _model_2d, _model_from_input, _search_cell_px
from guidewire3d.registration.result import RegistrationResult, _failed
from guidewire3d.registration.search import _global_search
from guidewire3d.registration.verdict import _finish

__all__ = ["register", "refine", "nudge"]

SEARCH_STARTS = 2  # LM starts taken from the search


def _check_common(carm, lam, delta, max_iterations):
    if not isinstance(carm, CArm):
        raise InputError(f"carm must be a CArm, got {type(carm).__name__}")
    if not (np.isfinite(lam) and lam >= 0):
        raise InputError(f"lam must be >= 0, got {lam}")
    if not (np.isfinite(delta) and delta > 0):
        raise InputError(f"delta must be > 0, got {delta}")
    if int(max_iterations) < 1:
        raise InputError(f"max_iterations must be >= 1, got {max_iterations}")


def register(
    tree,
    centerline_uv_px,
    carm: CArm,
    *,
    init_pose: Pose | None = None,
    centerline_radius_px=None,
    global_search: bool = True,
    lam: float | None = None,
    delta: float | None = None,
    max_iterations: int = 100,
) -> RegistrationResult:
    """Register the CTA vessel centerline to the 2D roadmap centerline.

    Parameters
    ----------
    tree : VesselTree or (N, 3) ndarray of float
        3D centerline in LPS mm (a bare point cloud is accepted; it should be dense, <= 1 mm).
    centerline_uv_px : (M, 2) ndarray of float
        2D centerline points ``(u, v)`` px of the roadmap (any order; may cover only part of the
        projected tree).
    carm : CArm
        The roadmap's C-arm geometry (DICOM angles, SID, SOD, pixel size, shape).
    init_pose : Pose, optional
        Start; default ``nominal_pose(centroid of the tree)``.
    centerline_radius_px : (M,) ndarray of float, optional
        Vessel radius at each 2D point: larger vessels get a larger point uncertainty.
    global_search : bool
        Run the coarse rotation x in-plane-translation search around the start before LM.
    lam : float, optional
        Weight of the 2D -> 3D term; default ``problem.LAMBDA`` (read at call time).
    delta : float, optional
        Pseudo-Huber cutoff in whitened units; default ``problem.DELTA`` (paper: 1).
    max_iterations : int
        LM iteration cap per LM run (paper: 100).

    Returns
    -------
    RegistrationResult
        Never raises on valid input that cannot be registered: ``success`` is then false.

    Raises
    ------
    InputError
        Malformed ``tree``, ``centerline_uv_px``, ``carm`` or options.
    """
    t0 = time.perf_counter()
    lam = problem.LAMBDA if lam is None else float(lam)
    delta = problem.DELTA if delta is None else float(delta)
    _check_common(carm, lam, delta, max_iterations)
    q = _check_2d(centerline_uv_px)
    m3 = _model_from_input(tree, carm)
    start = nominal_pose(m3.centroid) if init_pose is None else init_pose
    if not isinstance(start, Pose):
        raise InputError(f"init_pose must be a Pose, got {type(start).__name__}")
    if len(q) < 10:
        return _failed(start, carm, f"2D centerline has only {len(q)} points (need >= 10)", t0)
    m2 = _model_2d(q, centerline_radius_px, carm)
    prob = problem._Problem(m3, m2, carm, lam=lam, delta=delta)

    if global_search:
        cands = [p for _, p in _global_search(m3, m2, carm, start, n_best=SEARCH_STARTS)]
        gate_a = max(problem.GATE_WIDE_PX, 3.0 * _search_cell_px(carm))
    else:
        cands = [start]
        gate_a = problem.GATE_WIDE_PX
    out, iterations = problem.two_stage_lm(prob, cands, gate_wide_px=gate_a, delta_wide=max(problem.DELTA_WIDE, delta),
                                           max_iterations=max_iterations)
    return _finish(prob, out, q, carm, iterations, t0, radius_px=centerline_radius_px)


def refine(tree, centerline_uv_px, carm: CArm, from_pose: Pose, **kw) -> RegistrationResult:
    """LM only (no global search) from a user-corrected pose. Keywords as :func:`register`."""
    if not isinstance(from_pose, Pose):
        raise InputError(f"from_pose must be a Pose, got {type(from_pose).__name__}")
    kw = dict(kw)
    kw.pop("global_search", None)
    kw.pop("init_pose", None)
    return register(tree, centerline_uv_px, carm, init_pose=from_pose, global_search=False, **kw)


def nudge(pose: Pose, carm: CArm, *, centroid_lps_mm, translate_mm=(0.0, 0.0, 0.0), rotate_deg=(0.0, 0.0, 0.0)) -> Pose:
    """Move the pose by a user correction expressed in the detector frame.

    The rotation (``rotate_deg`` about the detector axes ``(e_u, e_v, d)``, as one rotation
    vector) is applied about the vessel centroid; then the translation ``translate_mm`` along
    ``(e_u, e_v, d)`` (image right, image down, along the beam) in the room frame. Positive
    ``translate_mm[0]`` moves the projected tree toward larger ``u``.

    Parameters
    ----------
    pose : Pose
    carm : CArm
    centroid_lps_mm : (3,) array_like of float
        Rotation centre (the vessel centroid, LPS mm).
    translate_mm, rotate_deg : (3,) array_like of float

    Returns
    -------
    Pose
        A new pose; the input is unchanged.
    """
    if not isinstance(pose, Pose):
        raise InputError(f"pose must be a Pose, got {type(pose).__name__}")
    if not isinstance(carm, CArm):
        raise InputError(f"carm must be a CArm, got {type(carm).__name__}")
    c = np.asarray(centroid_lps_mm, dtype=float).reshape(-1)
    tr = np.asarray(translate_mm, dtype=float).reshape(-1)
    rd = np.asarray(rotate_deg, dtype=float).reshape(-1)
    for name, v in (("centroid_lps_mm", c), ("translate_mm", tr), ("rotate_deg", rd)):
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise InputError(f"nudge {name} must be 3 finite numbers, got {v.tolist()}")
    A = carm.axes
    c_room = pose.apply(c)
    rot = Pose.from_rotvec_about(A.T @ np.radians(rd), c_room)
    return Pose(np.eye(3), A.T @ tr) @ rot @ pose

