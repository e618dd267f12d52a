"""Error measures against ground truth (mm and px). Pure functions on arrays."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "dice",
    "precision_recall",
    "polyline_length",
    "resample_polyline",
    "mean_closest_distance",
    "symmetric_polyline_distance",
    "mtre_mm",
    "length_deviation_pct",
]


def dice(pred, truth) -> float:
    """Dice coefficient of two boolean masks (1.0 when both are empty)."""
    p, t = np.asarray(pred, bool), np.asarray(truth, bool)
    s = p.sum() + t.sum()
    return 1.0 if s == 0 else float(2.0 * np.logical_and(p, t).sum() / s)


def precision_recall(pred, truth) -> tuple[float, float]:
    p, t = np.asarray(pred, bool), np.asarray(truth, bool)
    tp = np.logical_and(p, t).sum()
    prec = float(tp / p.sum()) if p.sum() else (1.0 if not t.any() else 0.0)
    rec = float(tp / t.sum()) if t.sum() else 1.0
    return prec, rec


def polyline_length(points) -> float:
    """Length of an ordered polyline ``(N, D)`` in its own units."""
    p = np.asarray(points, dtype=float)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def resample_polyline(points, step: float) -> np.ndarray:
    """Resample an ordered polyline ``(N, D)`` at a fixed arc-length ``step`` (keeps both ends)."""
    p = np.asarray(points, dtype=float)
    if len(p) < 2:
        return p.copy()
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    if s[-1] <= 0:
        return p[:1].copy()
    n = max(int(np.ceil(s[-1] / step)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    return np.column_stack([np.interp(t, s, p[:, k]) for k in range(p.shape[1])])


def mean_closest_distance(a, b) -> float:
    """Mean distance from each point of ``a`` to its nearest point of ``b``."""
    a, b = np.atleast_2d(a), np.atleast_2d(b)
    d, _ = cKDTree(b).query(a)
    return float(d.mean())


def symmetric_polyline_distance(a, b, *, step: float | None = None) -> float:
    """Mean of both directed mean closest distances between two (densely resampled) polylines."""
    if step is not None:
        a, b = resample_polyline(a, step), resample_polyline(b, step)
    return 0.5 * (mean_closest_distance(a, b) + mean_closest_distance(b, a))


def mtre_mm(pose_est, pose_true, points_lps_mm) -> float:
    """Mean target registration error: mean distance between the points moved by each pose."""
    p = np.asarray(points_lps_mm, dtype=float)
    return float(np.linalg.norm(pose_est.apply(p) - pose_true.apply(p), axis=1).mean())


def length_deviation_pct(length_est, length_true) -> float:
    return float(100.0 * abs(length_est - length_true) / max(length_true, 1e-9))


def wire_errors_mm(points_lps_mm, truth_points_lps_mm, *, step_mm: float = 0.1) -> dict:
    """3D errors of a reconstructed wire against the true wire (both ordered proximal -> distal).

    ``mean_error_mm``: mean distance from each reconstructed point to the densely resampled true
    polyline; ``tip_error_mm``: distance between the distal ends; ``length_deviation_pct``.
    """
    est = np.asarray(points_lps_mm, float).reshape(-1, 3)
    tru = np.asarray(truth_points_lps_mm, float).reshape(-1, 3)
    dense = resample_polyline(tru, step_mm)
    return {
        "mean_error_mm": mean_closest_distance(est, dense),
        "max_error_mm": float(cKDTree(dense).query(est)[0].max()),
        "tip_error_mm": float(np.linalg.norm(est[-1] - tru[-1])),
        "length_deviation_pct": length_deviation_pct(polyline_length(est), polyline_length(tru)),
    }


def evaluate_against_truth(result, truth) -> dict:
    """Registration mTRE and per-frame 3D wire errors of a pipeline result against simulator truth.

    ``truth`` is a ``guidewire3d.phantom.Truth``; only the visible (in-image) part of each true wire
    is compared, since that is all a single view can show.
    """
    pts = truth.tree.points_lps_mm
    out = {"mtre_mm": mtre_mm(result.registration.pose, truth.pose, pts), "frames": []}
    for idx, w in zip(result.frame_indices, result.wires3d):
        rec = {"index": int(idx), "success": bool(w.success)}
        if w.success:
            vis = np.asarray(truth.wire_visible[idx], bool)
            tru = np.asarray(truth.wire_lps_mm[idx])[vis]
            if len(tru) >= 2:
                rec.update({k: round(v, 4) for k, v in wire_errors_mm(w.points_lps_mm, tru).items()})
        out["frames"].append(rec)
    out["mtre_mm"] = round(out["mtre_mm"], 4)
    return out
