"""The simulator's patient motion: a rigid shift per frame, breathing, and a cardiac contraction.

With ``motion_mm > 0`` frame ``t`` is seen with ``pose @ Pose(I, motion_lps_mm[t])`` (the anatomy
shifted by ``motion_lps_mm[t]``, stored per frame in ``truth.json``). Physiological motion
(``breathing_mm``, ``cardiac_mm``; :func:`_physiological_motion`) adds a breathing rotation about the
tree's centroid and a cardiac contraction of the wire and catheter; the true pose of frame ``t`` is
``frame_pose(t)`` (also in ``truth.json``). The 3D truth stays in CTA coordinates. By default there is
no motion and every frame uses ``pose``.
"""
from __future__ import annotations

import numpy as np
from guidewire3d.geometry import Pose
from guidewire3d.phantom.anatomy import _unit
from guidewire3d.vesseltree import VesselTree

__all__ = ["BREATHING_DEG_PER_MM"]

#: rotation of the anatomy per mm of breathing shift (about the left-right axis)
BREATHING_DEG_PER_MM = 0.1


def _frame_pose(pose: Pose, shift, rotvec, centre, t: int) -> Pose:
    """``pose @ M_t``: the anatomy rotated about ``centre`` by ``rotvec[t]``, then shifted by ``shift[t]``."""
    if len(shift) == 0:
        return pose
    m = Pose(np.eye(3), shift[t])
    if len(rotvec) and np.any(rotvec[t] != 0):
        m = m @ Pose.from_rotvec_about(rotvec[t], centre)
    return pose @ m


def _patient_motion(options, rng, tree: VesselTree, n_frames: int):
    """The motion of ``options`` (a ``PhantomOptions``) over ``n_frames``: ``(shift (T, 3) mm,
    rotation (T, 3) rad about centre, centre (3,) mm, cardiac scale (T,))``, all zero without motion.

    The rigid ``motion_mm`` is a sinusoid of 10-20 frames along a mostly cranio-caudal direction;
    breathing and the cardiac contraction (:func:`_physiological_motion`) add to it.
    """
    T = n_frames
    motion = np.zeros((T, 3))
    if options.motion_mm > 0:
        period = rng.uniform(10, 20)
        phase = rng.uniform(0, 2 * np.pi)
        dirn = _unit(np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.4, 0.4), 1.0]))
        motion = np.outer(np.sin(2 * np.pi * np.arange(T) / period + phase), dirn) * float(options.motion_mm)
    motion_rot, motion_centre, cardiac = np.zeros((T, 3)), tree.points_lps_mm.mean(axis=0), np.zeros(T)
    if options.breathing_mm > 0 or options.cardiac_mm > 0:
        shift, motion_rot, motion_centre, cardiac = _physiological_motion(options, rng, tree, T)
        motion = motion + shift
    return motion, motion_rot, motion_centre, cardiac


def _physiological_motion(options, rng, tree: VesselTree, n_frames: int):
    """Per-frame breathing (shift (T, 3) mm, rotation (T, 3) rad about the tree centroid) and
    cardiac contraction (T,) of the simulator.

    Breathing: ``s(t) = (1 - cos(2 pi t / (fps P) + phi)) / 2`` (0 at end-expiration), a shift of
    ``breathing_mm * s(t)`` mostly cranio-caudal (LPS +z is superior; a little antero-posterior and
    left-right) and a rotation of ``0.1 deg per mm`` of it about the left-right axis. Cardiac: the
    tree contracts about its centroid by ``cardiac_mm * h(t)`` at its radius of gyration, ``h`` the
    same raised cosine at the heart rate. Both with a random phase.
    """
    T = n_frames
    t = np.arange(T) / float(options.frame_rate_fps)
    centre = tree.points_lps_mm.mean(axis=0)
    shift, rot, scale = np.zeros((T, 3)), np.zeros((T, 3)), np.zeros(T)
    if options.breathing_mm > 0:
        phase = rng.uniform(0, 2 * np.pi)
        s = 0.5 * (1.0 - np.cos(2 * np.pi * t / float(options.breathing_period_s) + phase))
        dirn = _unit(np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.3, 0.3), 1.0]))
        shift = np.outer(s, dirn) * float(options.breathing_mm)
        rot[:, 0] = np.radians(BREATHING_DEG_PER_MM) * float(options.breathing_mm) * s
    if options.cardiac_mm > 0:
        phase = rng.uniform(0, 2 * np.pi)
        h = 0.5 * (1.0 - np.cos(2 * np.pi * t * float(options.heart_rate_bpm) / 60.0 + phase))
        rg = float(np.sqrt(np.mean(np.sum((tree.points_lps_mm - centre) ** 2, axis=1))))
        scale = float(options.cardiac_mm) / max(rg, 1.0) * h
    return shift, rot, centre, scale


def _contract(points, centre, scale: float) -> np.ndarray:
    """Cardiac contraction of points about ``centre`` (identity at ``scale == 0``)."""
    if scale == 0:
        return points
    return centre + (np.asarray(points) - centre) * (1.0 - scale)
