"""The baselines of the single-view reconstruction (``ReconMethod.PAPER``, ``ReconMethod.BSPLINE``):
where each puts the points of the 2D wire in 3D, before the smoothing and uncertainty that every
method shares (``single_view``).

``ReconMethod.PAPER`` applies the paper's closed-form depth literally (it is a two-view
triangulation formula; with one view and the registration's R, t it gives an arbitrary depth),
``ReconMethod.BSPLINE`` is the B-spline baseline: a 2D B-spline fit lifted to the depth of the
nearest projected centerline point, without connectivity. (The EPnP baseline is a pose,
``registration.register_epnp``, that any method takes.)
"""
from __future__ import annotations

import numpy as np
from guidewire3d.geometry import CArm, Pose
from guidewire3d.reconstruction.smoothing import arclength, fit_pspline

__all__ = ["paper_depth_mm", "paper_points", "bspline_points"]


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


def paper_points(ctx, uv) -> np.ndarray | None:
    """(M, 3) LPS mm: the 2D wire ``uv`` (M, 2) backprojected to :func:`paper_depth_mm` at the
    context's pose; None where that depth is undefined (zero denominator) or not in front of the source."""
    d = paper_depth_mm(uv, ctx.pose, ctx.carm)
    if not np.all(np.isfinite(d)) or np.any(d <= 0):
        return None
    return ctx.carm.backproject(uv, d, ctx.pose)


def bspline_points(ctx, uv, opt):
    """The B-spline baseline's points: the P-spline fit of the 2D wire ``uv`` (M, 2), each point lifted
    to the depth of the nearest projected tree point, with no connectivity.

    Returns ``(points (M, 3) LPS mm, tree point ids (M,) (-1 beyond the lumen margin), depth std
    (M,) mm (the lumen's diameter / sqrt(12)), distance outside the projected lumen squared (M,)
    mm^2)``, or None when less than ``opt.min_coverage`` of the wire lies on the projected tree.
    """
    x = arclength(uv)
    if len(uv) >= 5 and x[-1] >= 2 * opt.knot_px:
        spl, Bm = fit_pspline(x, uv, lam=opt.smoothing_lambda, knot=opt.knot_px)
        g = Bm @ spl.c
    else:
        g = uv
    dist, ids = ctx.kd2.query(g)
    ids = ctx.cand_ids[ids]
    outside = np.maximum(dist - ctx.r_px[ids], 0.0)
    if float((outside <= opt.margin_px).mean()) < opt.min_coverage:
        return None
    X = ctx.carm.backproject(g, ctx.depth[ids], ctx.pose)
    depth_std = 2.0 * ctx.radius[ids] / np.sqrt(12.0)
    tid = np.where(outside <= opt.margin_px, ids, -1)
    return X, tid, depth_std, (outside * ctx.px_mm) ** 2
