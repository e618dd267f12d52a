"""Where along its vessel can the tip be? The lumen the tip's ray passes through, from one view.

A single view sees the tip's pixel, not its depth. The reconstruction puts the tip where the
tip's ray meets the vessel the path through the tree ends in. Where that vessel runs obliquely to
the beam, the ray crosses its lumen over a stretch of vessel, not at one cross-section: any point
of that stretch projects onto the tip's pixel, and the wire's end may be anywhere along it (a wire
riding one wall of a vessel that dives towards the source). The reconstruction's per-point
uncertainty is across the wire; this stretch is the tip's uncertainty *along* it, which the
``uncertainty_mm`` model leaves out.

:func:`tip_slide_mm` measures it: along the tree, from the tip's tree point back towards the root
and forward into every branch downstream (each up to ``SLIDE_MAX_MM``), the contiguous run of
points whose cross-section (the plane through the point normal to the vessel, the disc of its
radius minus the wire's clearance) the ray passes through. For a vessel at an angle ``theta`` to
the beam, a lumen of half-width ``w`` gives about ``2 w / tan(theta)``: nothing for a vessel across
the beam, the whole vessel for one along it.

``live.frame_verdict`` adds its spread, the length over sqrt 12 (a uniform position along it), to the tip's 1 sigma
across the wire in quadrature, against ``live.TIP_MAX_UNCERTAINTY_MM``. On ``bench_stress`` seeds 8700-8723, 8800-8815
(``--draws wide``), 8900-8939 and 9000-9023 (``--draws wide``), replayed: of 352 ``ok`` frames, it makes 8716 f0
(the tip 6.9 mm off, 15.3 mm of lumen, 0.8 mm across) and 9021 f0 (6.2 mm off, 7.5 mm, 2.0 mm) ``uncertain``, and six
right ones (tips 1.3-3.3 mm off). At the true pose (the simulator, seeds 0-199, 4 frames) it caught 5 of 9 wrong ``ok``
frames and made 12 of 629 right ones ``uncertain``; on seeds drawn after it (9100-9315) it caught none and made 8 of
223 right ones ``uncertain``: the tip's position along the stretch is not seen, and the path's prior gets it right more
often than a uniform spread says.

Since stop 58 :func:`forward_stretch_mm` measures the tip's vessel beyond it as seen in the image: the run of the tree
downstream of the tip that projects within ``live.TIP_STRETCH_PX`` of the 2D tip, less what those px span across the
beam. A thin leaf that dives along the beam beyond the tip projects onto the tip for its whole length while its lumen
is too thin for the ray to cross more than part of it (``bench_stress`` 10916 f3: 10 mm within 4 px, 6.8 mm of lumen
crossed, ``ok`` with the tip 9.6 mm short). ``live.frame_verdict`` takes the longer of the two as the tip's spread.
"""
from __future__ import annotations

import math

import numpy as np
from guidewire3d.live.continuation import downstream_paths

#: the tree is followed this far (mm) from the tip's point, back and forward
SLIDE_MAX_MM = 30.0
#: the wire's centre keeps this far from the wall (``reconstruction.ReconOptions.wire_clearance_mm``)
SLIDE_CLEARANCE_MM = 0.35


def _in_cross_section(P, radius, i: int, a: int, b: int, origin, direction, clearance_mm: float) -> bool:
    """Whether the ray ``origin + l * direction`` passes through the lumen cross-section of point ``i`` (the disc
    of its radius less ``clearance_mm``, at least half the radius, normal to the vessel's direction from point
    ``a`` to point ``b``). A ray parallel to the plane meets it only when it lies in it (then its closest approach
    to the point counts)."""
    pi, pa, pb = P[i].tolist(), P[a].tolist(), P[b].tolist()
    t = [pb[k] - pa[k] for k in range(3)]
    n = math.sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2]) or 1e-9
    t = [c / n for c in t]
    v = [pi[k] - origin[k] for k in range(3)]
    dt = t[0] * direction[0] + t[1] * direction[1] + t[2] * direction[2]
    vt = v[0] * t[0] + v[1] * t[1] + v[2] * t[2]
    if abs(dt) <= 1e-9:
        if abs(vt) > 1e-9:
            return False
        lam = v[0] * direction[0] + v[1] * direction[1] + v[2] * direction[2]
    else:
        lam = vt / dt
    off = [origin[k] + lam * direction[k] - pi[k] for k in range(3)]
    r = float(radius[i])
    rho = max(r - clearance_mm, 0.5 * r)
    return off[0] * off[0] + off[1] * off[1] + off[2] * off[2] <= rho * rho


def tip_slide_mm(tree, carm, pose, tip_uv_px, tip_point_id: int, *, clearance_mm: float = SLIDE_CLEARANCE_MM,
                 max_mm: float = SLIDE_MAX_MM) -> float:
    """The length (mm along the tree) of the stretch of vessel through whose lumen the ray of the 2D
    tip passes, around the tip's tree point (see the module's text); 0 when the ray misses the tip
    point's own cross-section.

    The tree is walked from the tip's point back towards the root and into every branch downstream, each
    until the first point whose cross-section the ray misses, or ``max_mm``.

    Parameters
    ----------
    tree : VesselTree
    carm, pose : the frame's C-arm and pose
    tip_uv_px : (2,) array
        The traced 2D tip.
    tip_point_id : int
        The tree point of the reconstructed tip (the last of ``Wire3D.tree_point_ids`` that is not -1).
    """
    o, d = carm.rays(np.asarray(tip_uv_px, float).reshape(1, 2), pose)
    origin, direction = o[0].tolist(), d[0].tolist()
    P, radius, parent = tree.points_lps_mm, tree.radius_mm, tree.parent
    children, s = tree.children, tree.arclength_from_root_mm
    tip = int(tip_point_id)

    def inside(i: int) -> bool:          # the vessel's direction at i: from its parent, or to its first child
        j = int(parent[i])
        if j >= 0:
            return _in_cross_section(P, radius, i, j, i, origin, direction, clearance_mm)
        return bool(children[i]) and _in_cross_section(P, radius, i, i, children[i][0], origin, direction,
                                                       clearance_mm)

    if not inside(tip):
        return 0.0
    first = tip                          # back towards the root
    while parent[first] >= 0 and s[tip] - s[int(parent[first])] <= max_mm and inside(int(parent[first])):
        first = int(parent[first])
    far, stack = 0.0, [tip]              # forward, into every branch
    while stack:
        i = stack.pop()
        far = max(far, float(s[i] - s[tip]))
        stack.extend(c for c in children[i] if s[c] - s[tip] <= max_mm and inside(c))
    return float(s[tip] - s[first]) + far


def forward_stretch_mm(tree, carm, pose, tip_uv_px, tip_point_id: int, *, stretch_px: float,
                       max_mm: float = SLIDE_MAX_MM) -> float:
    """How much more vessel (mm along the tree) beyond the reconstructed tip projects within ``stretch_px`` of the 2D
    tip than a vessel across the beam would: from the tip's tree point into every branch downstream (each up to
    ``max_mm``), the longest run of points from the tip on whose projection stays that close, less the ``stretch_px``
    at the isocentre's pixel size (what a vessel in the image plane spans over those px); 0 at the least. Where the
    tip's vessel turns along the beam beyond the tip, the wire may go on along it with nothing more to see in the
    image (``live.frame_verdict`` counts it as the tip's spread along its vessel, as ``tip_slide_mm``; the px are
    those of ``live.tip_stretch_mm``, which measures the 3D wire's own last px)."""
    paths = [p for p in downstream_paths(tree, int(tip_point_id), max_mm) if len(p) >= 2]
    if not paths:
        return 0.0
    ids = np.unique(np.concatenate(paths))
    where = np.full(tree.n_points, -1, np.int64)
    where[ids] = np.arange(len(ids))
    near = np.linalg.norm(np.asarray(carm.project(tree.points_lps_mm[ids], pose), float)
                          - np.asarray(tip_uv_px, float).reshape(1, 2), axis=1) <= stretch_px
    s = tree.arclength_from_root_mm
    best = 0.0
    for p in paths:
        inside = near[where[p]]
        n = len(p) if inside.all() else int(np.argmin(inside))     # the run from the tip
        if n >= 2:
            best = max(best, float(s[p[n - 1]] - s[p[0]]))
    return max(best - stretch_px * float(carm.pixel_at_iso_mm), 0.0)
