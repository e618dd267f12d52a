"""Does the wire go on beyond its traced tip? The image along the vessel tree's continuation.

A faint or thin wire (a 0.25 mm wire at a low dose) can be lost by the segmenter over its distal
part: the trace then stops short of the tip with no piece of mask beyond it, and the frame's 3D
wire, right as far as it goes, puts the tip 5-60 mm short. The image itself still shows the wire
there: a dark line along the vessel that continues the traced tip. This module measures that line
along every path of the vessel tree that leaves the reconstructed tip away from the root,
projected in the frame's pose, against the traced wire's own contrast measured the same way:

* at each sample (1 px apart) of a path's first ``WINDOW_PX`` px beyond the tip (starting
  ``SKIP_PX`` px past it, and leaving out samples within ``NEAR_WIRE_PX`` of the traced wire), the
  line contrast is the mean of the image ``BACKGROUND_PX`` px to both sides minus the image on the
  line, at perpendicular offsets of up to ``OFFSET_PX`` px (the registration and the lumen put the
  wire a few px off the projected centerline);
* the path's contrast is the mean along the best line through those offsets that moves at most
  ``LINE_STEP_PX`` px sideways per px along (:func:`best_line_contrast`, a dynamic programme): a wire
  rides anywhere in its lumen and crosses from one side of the projected centerline to the other;
* the traced wire's contrast is the same over its last ``WINDOW_PX`` px, at offsets of up to
  ``WIRE_OFFSET_PX`` px (it is on the wire);
* the evidence is the ratio of the two, and the path's contrast in units of its standard error
  (the robust spread of all its samples over the square root of half their number).

The best line also finds a line in noise alone (on frames traced to their real tip the ratio is
0.3-0.6), so the ratio's limit is set on simulated frames at the true pose
(``live.Session`` on ``phantom.simulate``, 6 frames a seed; every frame the check reads, with the
verdict it would have without the check): with a 0.25 mm wire, seeds 0-59 for the setting, seeds
60-179 held out, and the simulator's own wires on seeds 0-179. Until stop 55 the path's contrast was
the best single offset's mean (limit 0.5), which loses a wire that crosses the centerline (bench_stress
9831 f2: the wire beyond the tip 2.7 px from the projected path, median, its best offset's ratio 0.24,
``ok`` with the tip 25.7 mm short). ``ok`` frames without the check, the wrong ones caught / the right
ones made uncertain:

=================================  ===================  ==================  ==================
frames                             single offset, 0.5   best line, 0.7      best line, 0.75
=================================  ===================  ==================  ==================
0.25 mm, seeds 0-59 (237; 26 off)  16 / 2               24 / 4              20 / 4
0.25 mm, 60-179 (421; 54 off)      22 / 5               37 / 8              32 / 6
simulator's wires, 0-59 (293; 2)   0 / 0                0 / 1               0 / 1
simulator's wires, 60-179 (550; 6) 2 / 0                2 / 0               2 / 0
kept stress cases (663; 23 off)    1 / 0                6 / 1               3 / 1
=================================  ===================  ==================  ==================

(the last row: the 202 cases ``bench_stress.py --keep`` kept at stop 54, seeds 9400-9923, replayed with their trees and
poses; the details in ``scripts/MEASUREMENTS.md``, *Stop 55*)

Since stop 57 the traced wire is neither the line nor its background (:func:`on_traced_wire`: within the wire's dark
half-width, :func:`wire_half_width_px`, plus ``WIRE_CLEAR_MARGIN_PX`` of the trace, but for its last px, beside which
the continuation begins), and a path measured mostly beside the trace (``BESIDE_WIRE_FRACTION`` of its samples within
``OFFSET_PX + BACKGROUND_PX``) needs ``MIN_CONTRAST_RATIO_BESIDE`` of the wire's contrast. A wire that turns back in a
hairpin whose limbs lie 4-8 px apart is held by the segmenter as one line and traced to the turn: the returning limb's
background on one side was the traced wire, and it read 40-44 % (``bench_stress`` 10400 f3-f5, ``ok`` with tips 24-33
mm off); on a trace that ends at the turn the line rode onto the trace itself. Caught / right made uncertain, the same
frames as above read again (*Stop 57* in ``scripts/MEASUREMENTS.md``):

=======================================================  ==================  ==================
frames (``ok`` without the check; off)                   stop 55 (0.7)       stop 57
=======================================================  ==================  ==================
0.25 mm wires, seeds 0-179 (657; 80 off)                 61 / 11             61 / 13
simulator's wires, seeds 0-179 (843; 8 off)              2 / 1               3 / 1
kept stress cases 8700-10423, replayed (1568; 45 off)    10 / 4              16 / 3
=======================================================  ==================  ==================

And where a path beyond the tip runs back over the wire's own shaft (the trace more than ``SHAFT_FROM_TIP_PX`` from
its tip) for ``HIDDEN_MIN_PX`` of its first ``HIDDEN_WINDOW_PX`` px, the image cannot show the wire going on at all:
the tip is in doubt (``WireContinuation.hidden_by_wire``; ``bench_stress`` 10614 f1, its last 15 mm over its own
shaft, ``ok`` with the tip 14.9 mm short). With both, ``bench_stress --replay`` of the kept cases and fresh seeds
(2554 frames): 1695 ``ok`` / 38 wrong with stop 56's code, 1685 / 29 with stop 57's.

Since stop 58 the branches that leave the wire's vessel within ``SIBLING_BACK_MM`` before the reconstructed tip are read
too (:func:`sibling_paths`, each from its junction; ``WireContinuation.branch_before_tip_mm``): where the wire crosses
itself the trace can stop at the crossing and the 3D wire end just past a junction whose other branch the wire took
(``bench_stress`` 10305 f2, ``ok`` with the tip 6.2 mm short: 26 % along the tip's own vessel, 122 % along that
branch). Seven sets kept at stop 58 (770 frames), replayed: it catches 10305 f2 and makes no right frame uncertain; at
the true pose (the frames above, seeds 0-179) 2 of 21 off frames of the 0.25 mm wire caught for 1 right one, and 1 right
one of the simulator's wires (*Stop 58* in ``scripts/MEASUREMENTS.md``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from guidewire3d import kernels
from guidewire3d.xray.imaging import polyline_normals

#: the continuation is followed this far (mm along the tree) beyond the reconstructed tip
BEYOND_MM = 30.0
#: px of each path measured (and of the traced wire's distal part, for its own contrast)
WINDOW_PX = 40
#: the first px beyond the tip's projection are left out (the tip's own end)
SKIP_PX = 3.0
#: samples of a path nearer than this to the traced wire are left out (a path that doubles back)
NEAR_WIRE_PX = 4.0
#: the background is sampled this far to both sides of the line
BACKGROUND_PX = 4.0
#: an image sample within the traced wire's dark half-width plus this margin (px) is on it: neither the
#: continuation's line nor its background
WIRE_CLEAR_MARGIN_PX = 1.0
#: the wire's half-width is where its cross profile falls below this fraction of its depth ...
WIRE_EDGE_FRACTION = 0.25
#: ... read out to this many px from the trace (the background beyond)
WIRE_PROFILE_PX = 8
#: perpendicular offsets tried for the continuation's line, px (each side) ...
OFFSET_PX = 6
#: ... along a line that moves at most this far sideways (px) per px along the path
LINE_STEP_PX = 1
#: the traced wire's own line is looked for at offsets up to this (px, each side)
WIRE_OFFSET_PX = 2
#: fewer samples than this: no evidence either way
MIN_SAMPLES = 8
#: a continuation at least this fraction of the traced wire's contrast ...
MIN_CONTRAST_RATIO = 0.7
#: ... and this many standard errors above zero makes the tip uncertain (the best line through noise alone reads
#: 4-6 standard errors too: since stop 55 the ratio decides)
MIN_Z = 2.5
#: a path measured mostly (at least this fraction of its samples) within ``OFFSET_PX + BACKGROUND_PX`` of the traced
#: wire runs back beside it (a hairpin), where the segmenter merges the two limbs into one line ...
BESIDE_WIRE_FRACTION = 0.5
#: ... and a continuation of this fraction of the wire's contrast suffices
MIN_CONTRAST_RATIO_BESIDE = 0.5
#: the traced wire farther than this (px along it) from its tip is its shaft ...
SHAFT_FROM_TIP_PX = 80.0
#: ... and a path beyond the tip that runs within ``NEAR_WIRE_PX`` of the shaft for this many of its first
#: ``HIDDEN_WINDOW_PX`` px is hidden by the wire itself: one view cannot show whether the wire goes on there
HIDDEN_MIN_PX = 25
HIDDEN_WINDOW_PX = 60
#: the branches that leave the wire's vessel at most this far (mm along the tree) before the reconstructed tip are
#: read as its continuation too (a trace that stopped where the wire crosses itself, the wire going on along a branch
#: the 3D path did not take: ``bench_stress`` 10305 f2, ``ok`` with the tip 6.2 mm short). Measured at 4 / 6 / 10 mm
#: (*Stop 58* in ``scripts/MEASUREMENTS.md``)
SIBLING_BACK_MM = 6.0


@dataclass(frozen=True)
class WireContinuation:
    """The strongest dark line along the vessel tree beyond a frame's traced tip.

    ``contrast_ratio`` is its mean line contrast over the traced wire's (both in image units, each along its best
    line, :func:`best_line_contrast`); ``z`` its contrast in standard errors; ``length_px`` the samples it was
    measured on; ``offset_px`` the mean perpendicular offset of its line from the projected centerline;
    ``beside_wire_fraction`` the share of its samples within ``OFFSET_PX + BACKGROUND_PX`` of the traced wire;
    ``hidden_px`` the most px, of any path's first ``HIDDEN_WINDOW_PX`` beyond the tip, within ``NEAR_WIRE_PX`` of the
    traced wire's shaft (all zero but ``hidden_px`` when no line could be measured).
    """

    contrast_ratio: float
    z: float
    length_px: int
    offset_px: float
    beside_wire_fraction: float = 0.0
    hidden_px: int = 0
    branch_before_tip_mm: float = 0.0

    @property
    def wire_goes_on(self) -> bool:
        """Whether the image shows the wire going on beyond the traced tip."""
        limit = MIN_CONTRAST_RATIO_BESIDE if self.runs_beside_wire else MIN_CONTRAST_RATIO
        return self.contrast_ratio >= limit and self.z >= MIN_Z

    @property
    def hidden_by_wire(self) -> bool:
        """Whether a path beyond the tip runs back over the traced wire's own shaft (``hidden_px``, px of its first
        ``HIDDEN_WINDOW_PX``), where the image cannot show the wire going on."""
        return self.hidden_px >= HIDDEN_MIN_PX

    @property
    def tip_in_doubt(self) -> bool:
        """Whether the wire may go on beyond the traced tip: a line seen there, or a stretch hidden by the wire."""
        return self.wire_goes_on or self.hidden_by_wire

    @property
    def runs_beside_wire(self) -> bool:
        """Whether the path measured runs back beside the traced wire (a hairpin), judged by the lower limit."""
        return self.beside_wire_fraction >= BESIDE_WIRE_FRACTION

    def explain(self) -> str:
        if not self.wire_goes_on and self.hidden_by_wire:
            return (f"tip uncertain: beyond the traced tip its vessel runs back over the traced wire for {self.hidden_px}"
                    f" px of the next {HIDDEN_WINDOW_PX}: one view cannot show whether the wire goes on there, hidden by "
                    f"its own shaft")
        where = (" (the vessel turns back beside the traced wire, where the segmentation can merge the two limbs)"
                 if self.runs_beside_wire else "")
        along = ("along the vessel beyond the traced tip" if self.branch_before_tip_mm <= 0.0 else
                 f"along a branch that leaves the wire's vessel {self.branch_before_tip_mm:.1f} mm before the traced tip "
                 f"(the trace may have stopped where the wire crosses itself or another vessel)")
        return (f"tip uncertain: a dark line continues {along}{where} "
                f"({100 * self.contrast_ratio:.0f} % of the wire's contrast over {self.length_px} px, "
                f"{self.z:.1f} standard errors): the wire may go on there, past what was segmented")


def _resample_1px(uv: np.ndarray) -> np.ndarray:
    """A polyline resampled every 1 px from its first point."""
    seg = np.linalg.norm(np.diff(uv, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if len(uv) < 2 or s[-1] < 1.0:
        return uv[:1]
    t = np.arange(0.0, s[-1], 1.0)
    return np.stack([np.interp(t, s, uv[:, 0]), np.interp(t, s, uv[:, 1])], axis=1)


def _line_contrast(image: np.ndarray, uv: np.ndarray, offsets_px: np.ndarray, on_wire=None) -> np.ndarray:
    """(len(offsets), len(uv)): background (``BACKGROUND_PX`` to both sides) minus the line, at each
    perpendicular offset of the polyline ``uv`` (positive where the line is darker).

    With ``on_wire`` (a function of image points (N, 2), u, v px, to a bool (N,) array: which lie on the traced wire,
    :func:`on_traced_wire`), the traced wire is neither line nor background: a background sample on it is replaced
    by the other side's, and a cell whose line sample, or both of whose background samples, lie on it is NaN (a limb
    running back beside the traced wire, whose background on one side is the traced wire itself, read about half its
    contrast; a line riding onto the trace read the trace)."""
    rc = uv[:, ::-1]
    nrm = polyline_normals(rc)
    o = np.concatenate([offsets_px, offsets_px - BACKGROUND_PX, offsets_px + BACKGROUND_PX])
    q = rc[None] + o[:, None, None] * nrm[None]
    shape = (3, len(offsets_px), len(rc))
    v = kernels.sample_bilinear(image, q[..., 0].ravel(), q[..., 1].ravel(), mode="nearest").reshape(shape)
    if on_wire is None:
        return 0.5 * (v[1] + v[2]) - v[0]
    near = np.asarray(on_wire(q[..., ::-1].reshape(-1, 2)), bool).reshape(shape)
    background = np.where(near[1] & ~near[2], v[2], np.where(near[2] & ~near[1], v[1], 0.5 * (v[1] + v[2])))
    return np.where(near[0] | (near[1] & near[2]), np.nan, background - v[0])


def _from_tip_px(wire: np.ndarray) -> np.ndarray:
    """(M,) px along the polyline ``wire`` (M, 2) from each point to its last (the tip)."""
    return np.concatenate([np.cumsum(np.linalg.norm(np.diff(wire[::-1], axis=0), axis=1))[::-1], [0.0]])


def on_traced_wire(wire_uv_px, clear_px: float, tip_zone_px: float):
    """A function of image points (N, 2) (u, v px) to bool (N,): which lie on the traced wire ``wire_uv_px``
    (ordered, its last point the tip), within ``clear_px`` of one of its points more than ``tip_zone_px`` px from the
    tip along it. The last ``tip_zone_px`` px are left out: the wire's continuation begins beside them."""
    wire = np.asarray(wire_uv_px, float).reshape(-1, 2)
    shaft = wire[_from_tip_px(wire) > tip_zone_px]

    def on_wire(points_uv_px):
        p = np.asarray(points_uv_px, float).reshape(-1, 2)
        if not len(shaft):
            return np.zeros(len(p), bool)
        return kernels.nearest_sq_dist(p, shaft, clear_px) <= clear_px ** 2

    return on_wire


def wire_half_width_px(image: np.ndarray, uv: np.ndarray) -> float:
    """The dark half-width (px) of a wire traced along ``uv``: its mean cross profile out to ``WIRE_PROFILE_PX`` to
    both sides, the background the brighter of its two outer px, and on each side the first offset where the profile
    is less than ``WIRE_EDGE_FRACTION`` of the wire's depth below it; the narrower side (a second line beside the wire
    widens one side)."""
    rc = uv[:, ::-1]
    nrm = polyline_normals(rc)
    o = np.arange(-WIRE_PROFILE_PX, WIRE_PROFILE_PX + 1, dtype=float)
    q = rc[None] + o[:, None, None] * nrm[None]
    prof = kernels.sample_bilinear(image, q[..., 0].ravel(), q[..., 1].ravel(),
                                   mode="nearest").reshape(len(o), len(rc)).mean(axis=1)
    background = max(prof[:2].mean(), prof[-2:].mean())
    centre = WIRE_PROFILE_PX
    depth = background - prof[centre - 1: centre + 2].min()
    if not depth > 0.0:
        return 0.0
    dark = background - prof >= WIRE_EDGE_FRACTION * depth
    sides = []
    for step in (-1, 1):
        k = 0
        while k < WIRE_PROFILE_PX and dark[centre + step * (k + 1)]:
            k += 1
        sides.append(k)
    return float(min(sides))


def best_line_contrast(contrast: np.ndarray, offsets_px: np.ndarray, *,
                       max_step_px: int = LINE_STEP_PX) -> tuple[float, float]:
    """``(mean, mean offset px)`` of the best line through a contrast table: ``contrast`` (offsets, samples) as
    :func:`_line_contrast` gives it at ``offsets_px``, the line one offset per sample, moving at most
    ``max_step_px`` rows between neighbouring samples, with the largest sum of contrast (``kernels.best_line``, a
    Viterbi pass)."""
    total, line = kernels.best_line(contrast, max_step_px)
    return total / contrast.shape[1], float(np.asarray(offsets_px, float)[line].mean())


def downstream_paths(tree, point_id: int, max_mm: float) -> list[np.ndarray]:
    """Every path of tree points from ``point_id`` away from the root, each up to the first point
    ``max_mm`` or more beyond it along the tree (or to a leaf)."""
    children, parent = tree.children, tree.parent
    s = tree.arclength_from_root_mm
    base = s[int(point_id)]
    ends, stack = [], [int(point_id)]
    while stack:
        i = stack.pop()
        if not children[i] or s[i] - base >= max_mm:
            ends.append(i)
        else:
            stack.extend(children[i])
    out = []
    for e in ends:
        path = [e]
        while path[-1] != point_id:
            path.append(int(parent[path[-1]]))
        out.append(np.array(path[::-1], dtype=np.int64))
    return out


def sibling_paths(tree, point_id: int, back_mm: float, max_mm: float) -> list[tuple[np.ndarray, float]]:
    """The paths of tree points that leave the way from the root to ``point_id`` at a junction at most ``back_mm``
    before it (along the tree), each from that junction into a branch the way does not take, up to ``max_mm``
    beyond the branch's first point (:func:`downstream_paths`); with each, how far (mm along the tree) before
    ``point_id`` it leaves."""
    children, parent, s = tree.children, tree.parent, tree.arclength_from_root_mm
    tip = int(point_id)
    out = []
    prev, a = tip, int(parent[tip])
    while a >= 0 and s[tip] - s[a] <= back_mm:
        before_mm = float(s[tip] - s[a])
        out += [(np.concatenate([[a], p]), before_mm)
                for c in children[a] if int(c) != prev for p in downstream_paths(tree, int(c), max_mm)]
        prev, a = a, int(parent[a])
    return out


def wire_continuation(image, tree, carm, pose, tip_point_id: int, wire_uv_px) -> WireContinuation | None:
    """The strongest dark line along the tree's paths beyond the tip (see the module's text), or
    None when there is nothing to measure (a tip at a leaf, paths that leave the image at once,
    a traced wire too short or without contrast).

    Parameters
    ----------
    image : (H, W) array
        The raw live frame (the wire darker than the background).
    tree : VesselTree
    carm, pose : the frame's C-arm and pose (the tree is projected with them)
    tip_point_id : int
        The tree point of the reconstructed tip: the last of ``Wire3D.tree_point_ids`` that is not -1 (the tip
        itself may lie just outside its projected lumen).
    wire_uv_px : (M, 2) array
        The traced 2D wire, ordered proximal -> distal (its last point is the tip).
    """
    img = np.asarray(image)
    if img.ndim != 2:
        return None
    wire = np.asarray(wire_uv_px, float).reshape(-1, 2)
    # the last WINDOW_PX px of the wire (a trace is about 1 px per point: a tail of a few times that suffices)
    tail = wire[-4 * WINDOW_PX:]
    distal = _resample_1px(tail[::-1])[:WINDOW_PX]
    if len(distal) < MIN_SAMPLES:
        return None
    wire_offsets = np.arange(-WIRE_OFFSET_PX, WIRE_OFFSET_PX + 1, dtype=float)
    wire_contrast = best_line_contrast(_line_contrast(img, distal, wire_offsets), wire_offsets)[0]
    if not wire_contrast > 0.0:
        return None
    h, w = img.shape
    clear = wire_half_width_px(img, distal) + WIRE_CLEAR_MARGIN_PX
    tip_uv = wire[-1]
    others = wire[:-3] if len(wire) > 3 else wire[:0]
    # the continuation's line and background do not read the traced wire (its dark width and a margin), but for its
    # last px, beside which the continuation begins
    on_wire = on_traced_wire(wire, clear, SKIP_PX + clear)
    offsets = np.arange(-OFFSET_PX, OFFSET_PX + 1, dtype=float)
    # (path, mm before the tip where it leaves the wire's way): the tip's own paths, then the branches leaving just
    # before it, where a trace that stopped at a crossing may have left the wire
    paths = ([(p, 0.0) for p in downstream_paths(tree, tip_point_id, BEYOND_MM) if len(p) >= 2]
             + [(p, mm) for p, mm in sibling_paths(tree, tip_point_id, SIBLING_BACK_MM, BEYOND_MM) if len(p) >= 2])
    if not paths:
        return None
    ids = np.unique(np.concatenate([p for p, _ in paths]))
    where = np.full(tree.n_points, -1, np.int64)
    where[ids] = np.arange(len(ids))
    proj = np.asarray(carm.project(tree.points_lps_mm[ids], pose), float)     # one projection for all paths
    shaft = wire[_from_tip_px(wire) > SHAFT_FROM_TIP_PX]
    best, hidden = None, 0
    for path, before_mm in paths:
        uv = _resample_1px(proj[where[path]])
        keep = np.linalg.norm(uv - tip_uv, axis=1) > SKIP_PX
        keep &= (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        if len(shaft) and before_mm == 0.0:  # the tip's own path's px on the wire's shaft, of its first HIDDEN_WINDOW_PX
            ahead = uv[keep][:HIDDEN_WINDOW_PX]
            hidden = max(hidden, int((kernels.nearest_sq_dist(ahead, shaft, NEAR_WIRE_PX) <= NEAR_WIRE_PX ** 2).sum()))
        reach = OFFSET_PX + BACKGROUND_PX          # distances to the trace, exact out to reach (> NEAR_WIRE_PX)
        d2 = kernels.nearest_sq_dist(uv, others, reach) if len(others) else np.full(len(uv), np.inf)
        keep &= d2 > NEAR_WIRE_PX ** 2
        uv, d2 = uv[keep][:WINDOW_PX], d2[keep][:WINDOW_PX]
        if len(uv) < MIN_SAMPLES:
            continue
        beside = float((d2 <= reach ** 2).mean()) if len(others) else 0.0
        c = _line_contrast(img, uv, offsets, on_wire)
        c = c[:, ~np.isnan(c).all(axis=0)]        # samples whose every offset is on the traced wire: no evidence
        if c.shape[1] < MIN_SAMPLES:
            continue
        valid = c[~np.isnan(c)]
        spread = 1.4826 * float(np.median(np.abs(valid - np.median(valid))))
        c = np.nan_to_num(c, nan=0.0)             # a cell on the traced wire: no evidence either way
        mean, offset = best_line_contrast(c, offsets)
        cand = WireContinuation(contrast_ratio=mean / wire_contrast,
                                z=mean / max(spread / np.sqrt(c.shape[1] / 2.0), 1e-12),
                                length_px=int(c.shape[1]), offset_px=offset, beside_wire_fraction=beside,
                                branch_before_tip_mm=before_mm)
        if best is None or (cand.wire_goes_on, cand.contrast_ratio) > (best.wire_goes_on, best.contrast_ratio):
            best = cand
    if best is None:
        return (WireContinuation(contrast_ratio=0.0, z=0.0, length_px=0, offset_px=0.0, hidden_px=hidden)
                if hidden >= HIDDEN_MIN_PX else None)
    return replace(best, hidden_px=hidden)
