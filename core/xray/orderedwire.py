"""The ordered guidewire: a guidewire mask -> an ordered, sub-pixel polyline (proximal -> distal).

One stage of the paper's pipeline (DESIGN.md, "The flow of data"), and the paper's wire graph:

- :func:`ordered_wire` turns a guidewire mask into an ordered, sub-pixel polyline:
  Zhang-Suen thinning, an 8-connected pixel graph, the longest path of each skeleton piece
  (a good-continuation trace through junctions, so a wire looping over itself is followed
  through the crossing and spurs are left; double Dijkstra for junction-free pieces), bridging of
  pieces whose ends are close and whose directions agree (with the frame, also across a sharp bend
  whose vertex the mask lost, and across a longer break in line, where the image shows the wire),
  joining the other limb of a hairpin whose limbs touch in the mask (it leaves the merged stretch as a
  piece beside the wire), sub-pixel centring across the normal (mask centroid, weighted by the
  frame's darkness when given), extension of both ends to the mask's end caps, proximal -> distal
  ordering and resampling at ~1 px. With the frame, a presence
  test (:mod:`guidewire3d.xray.wirepresence`) fails a curve that is not a guidewire (a vessel, a branch
  of a vessel tree, the collimator's edge: a frame without a wire).
- :func:`tip_darkness` / :func:`doubled_tip`: whether two layers of wire lie at the traced tip (the
  wire bends back over itself before its tip, and the trace stops at the bend); the frame's
  verdict (:mod:`guidewire3d.live.session`) makes such a tip uncertain.
- :func:`wire_graph_spectrum` builds the paper's gradient-weighted path graph and its Laplacian
  eigenbasis, and projects the wire's discrete curvature onto it.

The roadmap's vessels and their centerline are :mod:`guidewire3d.xray.roadmap`.

Pixel coordinates are ``(u, v) = (col, row)``; pixel ``(0, 0)`` is the centre of the first pixel.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from guidewire3d import kernels
from guidewire3d.errors import InputError
from guidewire3d.metrics import polyline_length, resample_polyline
from guidewire3d.xray.imaging import (
    BLANK_REL_SPREAD,
    as_image,
    as_mask,
    grey,
    normalise01,
    polyline_normals,
)
from guidewire3d.xray.wirepresence import WirePresence, presence_of_curve
from scipy import ndimage as ndi
from scipy import sparse
from scipy.sparse import csgraph

__all__ = [
    "BeyondTip",
    "TipFork",
    "DoubledTip",
    "doubled_tip",
    "BareTip",
    "tip_end_check",
    "tip_darkness",
    "OrderedWire",
    "ordered_wire",
    "WireSpectrum",
    "wire_graph_spectrum",
    "discrete_curvature",
]

# Ordered-wire parameters.
MIN_WIRE_LENGTH_PX = 10.0         # a shorter longest path is "no wire"
MAX_MASK_FRACTION = 0.25          # a mask covering more of the image is not a wire
MAX_MEAN_WIDTH_PX = 20.0          # mask area / path length above this: a blob, not a wire
MIN_PIECE_PX = 3                  # skeleton pieces with fewer pixels are noise
MAX_PIECES = 24                   # only the largest pieces are considered for bridging
TANGENT_BACK_PX = 6               # end tangent from this many pixels back along the piece
BRIDGE_MAX_ANGLE_DEG = 50.0       # gap vector vs each end's outward tangent
TURN_PENALTY_PX = 4.0            # trail score: length - this x (1 - cos turn) at each junction
TRACE_MAX_STEPS = 5000            # search budget of the trail search
BRIDGE_FREE_PX = 2.5              # gaps up to this length are bridged regardless of direction
# A break at a sharp bend. Where the wire's projection turns sharply (the aortic arch seen edge-on makes a V),
# the segmenter loses the vertex and the mask breaks there; the two limbs' ends are close but their directions
# disagree, so the direction test leaves the gap and the trace stops at the bend (real anatomy, biplane poses 1,
# 3 and 9: 7-9 px gaps, the tip 59-63 mm short, every such frame ``uncertain``). With the frame, such a gap is
# bridged when the image shows a wire across it: the darkest route between the two ends
# (``skimage.graph.route_through_array`` over the frame's dark-line response, a black top-hat) is as dark a
# line as the wire on both sides of it. Ends at most BEND_BRIDGE_MAX_PX apart ...
BEND_BRIDGE_MAX_PX = 15.0
BEND_ROUTE_MAX_RATIO = 3.0        # ... joined by a route at most this x their distance + BEND_ROUTE_SLACK_PX ...
BEND_ROUTE_SLACK_PX = 4.0
BEND_MIN_SUPPORT = 0.5            # ... whose dark-line response is everywhere at least this x the wire's beside it,
BEND_MIN_LIKE = 0.5               # ... and whose two pieces are alike: the fainter at least this x as dark a line
BEND_REF_PX = 12                  # the wire's own response: the median over this many px of each piece at its end
# A longer break in line. Where the wire fades (over the mediastinum, into the shoulders) the mask can break for
# more than ``max_gap_px`` with the two pieces in line (real anatomy, seeds 0 and 1: 15-21 px gaps at 2-13 deg in 12
# frames, the tip 20-124 px short, each ``uncertain`` for the piece beyond the tip). With the frame, ends up to
# LONG_GAP_MAX_PX apart whose directions both agree with the gap within LONG_GAP_MAX_ANGLE_DEG are bridged on the
# same evidence as a bend (BEND_ROUTE_*, BEND_MIN_SUPPORT, BEND_MIN_LIKE): the frame shows a wire all across.
# Measured: it bridged 7 of those 320 frames (4 of them traced now, where the presence test had failed the shorter
# curve) and 1 of 360 simulated (the tip 103 -> 1.6 px); most of the 12 fading frames stay short, the frame's wire
# across their gap fainter than half the wire's.
LONG_GAP_MAX_PX = 30.0
LONG_GAP_MAX_ANGLE_DEG = 15.0
# A hairpin whose limbs touch in the mask. Where the wire turns back on itself (over the aortic arch seen from
# the side, at a branch's take-off), the limbs lie side by side for a stretch before the turn; the mask holds
# one line there, the trace runs along it to the turn and stops, and the other limb, where it leaves the
# merged stretch, is a piece of its own whose end lies beside the trace, pointing along it towards the turn
# (real anatomy, seeds 0 and 1, 320 frames: 20 frames, the 2D tip 52-272 px short and no flag; the simulator,
# seeds 0-59: 2 of 360 frames, 179 and 282 px short). Such a piece is joined: the wire runs on to the turn,
# back along the merged stretch and out along the piece. A piece at least HAIRPIN_MIN_PIECE_PX long ...
HAIRPIN_MIN_PIECE_PX = 15.0
HAIRPIN_MAX_BACK_PX = 250.0       # ... whose end lies beside the wire at most this far (px) back from its end ...
HAIRPIN_NEAR_HALF_WIDTHS = 4.0    # ... within this x the mask's mean half-width + HAIRPIN_NEAR_SLACK_PX of it
HAIRPIN_NEAR_SLACK_PX = 3.0       #     (two limbs side by side: the merged skeleton runs between them) ...
HAIRPIN_MIN_COS = 0.7             # ... its outward tangent along the wire's direction towards its end (45 deg) ...
HAIRPIN_MIN_BACK_PX = 3.0         # ... not at the end itself (that is a gap: the bridges above) ...
HAIRPIN_MIN_LIKE = 0.5            # ... and as dark a line as the wire: its response at least this x the wire's
# A piece of the mask left out of the wire that lies beyond the tip, in line with it, makes the tip
# uncertain (the wire may continue there, through a stretch the segmenter lost): a piece whose
# traced length is at least this ...
BEYOND_TIP_MIN_LENGTH_PX = 15.0
BEYOND_TIP_MAX_GAP_PX = 80.0      # ... whose nearer end is at most this far from the tip ...
BEYOND_TIP_MAX_ANGLE_DEG = 40.0   # ... and within this angle of the tip's outward tangent,
BEYOND_TIP_NEAR_GAP_PX = 15.0     # ... or at any angle when this near (a wire bent sharply at its tip:
                                  # the segmenter broke the bend, and the piece beyond runs back)
# The mask forks just before the traced tip: a wire whose tip is bent back (a J tip, or a tip caught in a
# side branch) thins into a skeleton with two ends there, and the trace takes one (``bench_stress`` 7215 f1:
# the tip hooked back 17 px, the trace ended at the bend, the 3D tip 8 mm short, ``ok``). A skeleton branch
# off the trace that leaves it within TIP_FORK_NEAR_PX of the tip (along the trace) and reaches at least
# TIP_FORK_MIN_PX (or TIP_FORK_MIN_HALF_WIDTHS x the mask's half-width) from it makes the tip uncertain
TIP_FORK_NEAR_PX = 15.0
TIP_FORK_MIN_PX = 6.0
TIP_FORK_MIN_HALF_WIDTHS = 3.0
# A second layer of wire over the traced tip: where the wire bends back over itself just before its
# tip, or its vessel turns towards the viewer and back, the distal part projects onto the part
# before it; the mask holds one line there and the trace stops at the turn, short of the true tip
# (bench_stress seeds 3300 frames 3 and 4, 3302 frame 3: tips 10-45 px short, 9-23 mm in 3D). The
# image shows two layers: the line's darkness (the image summed across the line, minus its
# background) over the last ``END_WINDOW_PX`` px, relative to its median over ``END_REFERENCE_PX``
# back from the tip (the wire's own darkness near its tip, past the longest doubled stretch seen,
# 45 px, and before a guiding catheter), is near 2 there and below 1 at a free tip (the wire ends
# inside the window). Calibrated at the true pose on simulated seeds 0-29 (4 frames each, distractors
# in odd seeds): the one folded tip (12 px short, 7 mm in 3D) measured 2.43, the 119 other frames
# at most 1.92. The folds seen measured 2.4-4.1 (more than two layers of a wire lying in the image
# plane: the turn itself, and a limb running partly along the ray, add darkness). The limit was 2.2
# until two folds that lie nearly flat in the image plane, 2.06 and 2.20 (bench_stress seeds 3918
# frame 4 and 3821 frame 4, tips 10-11 mm off), passed it as ``ok``; it is now the two layers
# themselves, 2.0. On 601 frames with the tip at the right end (true pose, seeds 0-179, 4 frames)
# none measured 2.0-2.2 (the largest below 2.2 was 1.98); three measured 2.3-3.0 with their tips
# right (already uncertain at 2.2). A fold that lies exactly flat measures 2.0 give or take the
# noise: about half of them stay below the limit.
END_WINDOW_PX = 10                # px at the tip measured ...
END_REFERENCE_PX = (40, 160)      # ... relative to the median this far (px) back from the tip
END_LINE_HALF_PX = 4.0            # the line's darkness is summed within this of the trace ...
END_BACKGROUND_PX = (5.0, 8.0)    # ... against the median of the image this far to both sides
DOUBLED_END_RATIO = 2.0           # a tip this many times as dark as the wire: two layers (see above)
# The other way round: a traced tip whose last ``END_WINDOW_PX`` px are barely darker than the
# background beside them is not on the wire: the trace ran on past the wire's end, over a false
# stretch of the mask (bench_stress seed 3913 frame 0, dose 0.5: 28 px past the tip, ratio 0.12).
# At a right tip the wire ends inside the window and the ratio falls below 1, rarely below 0.4.
# Set on seeds 0-59 with a 0.25 mm wire at the true pose (below 0.2: 9 frames more than 5 mm off,
# 6 of them reported ok, and 2 within 5 mm); held out: seeds 100-159, 0.25 mm (10 off, 3 of them ok,
# 4 within 5 mm); seeds 0-179, the simulator's wires: 1 of 656 tips within 5 mm is below 0.2.
BARE_END_RATIO = 0.2
TIP_CAP_FRACTION = 0.25          # mask end cap beyond the tip, x local width (flat 0 .. round 0.5)
PROFILE_STEP_PX = 0.5            # sampling step across the normal (centring)
REFINE_STEP_PX = 0.25             # sampling step along the tangent (end extension)
REFINE_SMOOTH_PX = 2.0            # Gaussian smoothing (arc length) of the pixel path before normals
SATURATED_FRACTION = 0.5         # frame with this fraction of pixels at its maximum: saturated
# Proximal end without a hint: a guiding catheter (a darker tube around the wire) marks it.
CATHETER_SEARCH_PX = 30.0         # arc length from each wire end searched for the catheter
CATHETER_NEAR_PX = (1.0, 4.0)     # band beyond the wire's half-width on each side: the catheter wall
CATHETER_FAR_PX = (9.0, 14.0)     # background band beyond the wire's half-width on each side
CATHETER_MIN_Z = 2.0              # catheter contrast (noise sigmas, weaker side) that marks an end
CATHETER_MIN_GAP_Z = 1.5          # ... and by which it must exceed the other end's


# --------------------------------------------------------------------------------------------
# Skeleton helpers
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class _PixelGraph:
    """8-connected graph of skeleton pixels: node ``k`` is pixel ``(rr[k], cc[k])`` (row-major
    order); CSR arrays ``indptr``, ``indices`` (neighbours sorted by node) and ``weights_px``
    (Euclidean edge lengths, 1 or sqrt 2)."""

    rr: np.ndarray
    cc: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    weights_px: np.ndarray

    @property
    def csr(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.indptr, self.indices, self.weights_px

    def matrix(self) -> sparse.csr_matrix:
        """The graph as a SciPy sparse matrix (for csgraph)."""
        n = len(self.rr)
        return sparse.csr_matrix((self.weights_px, self.indices, self.indptr), shape=(n, n))


def _pixel_graph(rr: np.ndarray, cc: np.ndarray, shape: tuple[int, int]) -> _PixelGraph:
    """The :class:`_PixelGraph` of the pixels ``(rr, cc)`` (row-major order) of an image of ``shape``."""
    return _PixelGraph(rr, cc, *kernels.pixel_graph(rr, cc, shape))


# --------------------------------------------------------------------------------------------
# Ordered guidewire
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class BeyondTip:
    """A piece of the wire mask beyond an ordered wire's tip (see ``OrderedWire.beyond_tip``)."""

    length_px: float     #: the piece's traced length
    gap_px: float        #: from the tip to the piece's nearer end
    angle_deg: float     #: between the tip's outward tangent and the direction to that end

    def explain(self) -> str:
        where = (f"in line with the wire ({self.angle_deg:.0f} deg)" if self.angle_deg <= BEYOND_TIP_MAX_ANGLE_DEG
                 else f"at {self.angle_deg:.0f} deg to the wire (a sharp bend at the tip?)")
        return (f"tip uncertain: a wire-like piece of {self.length_px:.0f} px lies {self.gap_px:.0f} px beyond the "
                f"tip, {where}; the wire may continue there")


@dataclass(frozen=True)
class TipFork:
    """The wire's mask forks just before its traced tip (see ``OrderedWire.tip_fork``, ``TIP_FORK_*``)."""

    reach_px: float      #: how far the other branch reaches from the trace
    from_tip_px: float   #: where it leaves the trace, along the trace from the tip

    def explain(self) -> str:
        return (f"tip uncertain: the wire's mask forks {self.from_tip_px:.0f} px before the traced tip into a second "
                f"end reaching {self.reach_px:.0f} px from the trace (a tip bent back, or caught in a side branch): "
                f"the tip may be at that end")


@dataclass(frozen=True)
class BareTip:
    """The traced tip is barely darker than the background: the trace runs past the wire's end
    (see ``BARE_END_RATIO``)."""

    darkness_ratio: float  #: the tip's last ``END_WINDOW_PX`` px over the wire's median line darkness

    def explain(self) -> str:
        return (f"tip uncertain: the trace's last {END_WINDOW_PX} px are only {self.darkness_ratio:.2f} x as dark as the "
                f"rest of the wire (barely darker than the background beside them): the trace may run past the "
                f"wire's end, over a false stretch of the mask")


@dataclass(frozen=True)
class DoubledTip:
    """The traced tip is about twice as dark as the wire: two layers of wire (see :func:`tip_darkness`)."""

    darkness_ratio: float  #: the tip's last ``END_WINDOW_PX`` px over the wire's median line darkness

    def explain(self) -> str:
        return (f"tip uncertain: the wire's last {END_WINDOW_PX} px are {self.darkness_ratio:.1f} x as dark as the rest "
                f"of it (two layers of wire: it may bend back over itself, or run on under its own shadow, before "
                f"its tip, which would then lie back along the traced wire)")


@dataclass(frozen=True, eq=False)
class OrderedWire:
    """Ordered 2D guidewire polyline (falsy when extraction failed).

    It behaves as its ``(N, 2)`` point array where an array is expected (``np.asarray(wire)``,
    ``wire[:, 0]``, ``len(wire)``, ``wire.shape``), so callers of the stable API
    ``ordered_wire(mask) -> (N, 2) float`` can use it directly; a failure is empty and falsy.

    Attributes
    ----------
    points_uv_px : (N, 2) ndarray of float
        ``(u, v) = (col, row)`` at ~1 px spacing, proximal -> distal (tip last). Empty on failure.
    success : bool
    message : str
        ``"ok"`` or the reason of the failure.
    length_px : float
        Polyline length, px.
    n_gaps_bridged : int
        Number of breaks in the mask that were bridged.
    n_bends_bridged : int
        How many of them were at a sharp bend, bridged because the frame shows a wire across
        (``BEND_*``; with an image only).
    n_long_gaps_bridged : int
        How many were longer than ``max_gap_px`` and in line, bridged because the frame shows a wire across
        (``LONG_GAP_*``; with an image only).
    beyond_tip : BeyondTip or None
        A piece of the mask that the wire does not include, lying beyond its tip and in line with
        it (``BEYOND_TIP_*``): the wire may continue there, so the tip is not settled. None when
        there is none.
    tip_fork : TipFork or None
        A branch of the mask's skeleton that leaves the wire just before its tip and reaches away
        from it (``TIP_FORK_*``): a tip bent back, whose true end may be at that branch's. None when
        there is none.
    hairpin_px : float
        The length (px) of the stretch the wire runs back along itself where a hairpin whose limbs touch in the
        mask was joined (``HAIRPIN_*``; 0.0 when none was).
    presence : WirePresence or None
        The presence test of the traced curve (:func:`guidewire3d.xray.wirepresence.wire_presence`;
        None when it did not run: no image, ``check_presence=False``, or no curve was traced).
        When it says the curve is not a guidewire, the result is falsy and ``message`` starts
        with ``"no guidewire in the frame: "``.
    """

    points_uv_px: np.ndarray
    success: bool
    message: str
    length_px: float = 0.0
    n_gaps_bridged: int = 0
    n_bends_bridged: int = 0
    n_long_gaps_bridged: int = 0
    presence: WirePresence | None = None
    beyond_tip: "BeyondTip | None" = None
    tip_fork: "TipFork | None" = None
    hairpin_px: float = 0.0

    def __bool__(self) -> bool:
        return bool(self.success)

    # --- the (N, 2) array protocol -------------------------------------------------------------
    def __array__(self, dtype=None, copy=None):
        a = self.points_uv_px if dtype is None else self.points_uv_px.astype(dtype)
        return a.copy() if copy else a

    def __len__(self) -> int:
        return len(self.points_uv_px)

    def __getitem__(self, index):
        return self.points_uv_px[index]

    @property
    def shape(self) -> tuple[int, ...]:
        return self.points_uv_px.shape

    @property
    def dtype(self):
        return self.points_uv_px.dtype

    @property
    def tip_uv_px(self) -> np.ndarray:
        """Distal end ``(u, v)``; NaNs on failure."""
        return self.points_uv_px[-1].copy() if len(self.points_uv_px) else np.full(2, np.nan)


def _percentiles_1_99(values: np.ndarray) -> tuple[float, float]:
    """``np.percentile(values, [1, 99])`` (method "linear") of finite float64 values, to the last
    bit: the same order statistics (one ``np.partition``) and numpy's interpolation (``_lerp``),
    without ``np.percentile``'s overhead (~10 x the partition's cost on a 128 x 128 frame)."""
    a = values.ravel()
    n = a.size
    virtual = (n - 1) * (np.array([1.0, 99.0]) / 100)
    prev = np.floor(virtual).astype(np.intp)
    nxt = prev + 1
    last = virtual >= n - 1                              # numpy: the maximum
    prev[last] = nxt[last] = n - 1
    part = np.partition(a, np.unique(np.r_[prev, nxt]))
    lo_v, hi_v = part[prev], part[nxt]
    gamma = virtual - prev
    diff = hi_v - lo_v
    out = np.where(gamma >= 0.5, hi_v - diff * (1 - gamma), lo_v + diff * gamma)
    return float(out[0]), float(out[1])


def _failed(msg: str) -> OrderedWire:
    return OrderedWire(points_uv_px=np.zeros((0, 2)), success=False, message=msg)


def _diameter_path(graph: _PixelGraph, node0: int):
    """Geodesic diameter path (double Dijkstra) of the component holding ``node0``: ``(M, 2)``
    rows/cols and its length, px. A compiled kernel; where a node of its path has two predecessors
    at the same distance (the choice then depends on the order of the search), SciPy's
    :func:`_diameter_path_csgraph` answers, so the path is always SciPy's."""
    seq, length, ambiguous = kernels.diameter_path(*graph.csr, node0)
    if ambiguous:
        return _diameter_path_csgraph(graph.matrix(), graph.rr, graph.cc, node0)
    return np.column_stack([graph.rr[seq], graph.cc[seq]]).astype(float), length


def _diameter_path_csgraph(g, rr, cc, node0):
    """:func:`_diameter_path` with SciPy's csgraph (``g`` a sparse matrix of the graph)."""
    d0 = csgraph.dijkstra(g, directed=False, indices=node0)
    d0[~np.isfinite(d0)] = -1.0
    a = int(np.argmax(d0))
    d1, pred = csgraph.dijkstra(g, directed=False, indices=a, return_predecessors=True)
    d1[~np.isfinite(d1)] = -1.0
    b = int(np.argmax(d1))
    node, seq = b, []
    while node >= 0:
        seq.append(node)
        node = pred[node]
    seq = np.asarray(seq[::-1])
    return np.column_stack([rr[seq], cc[seq]]).astype(float), float(d1[b])


def _away_tangent(p: np.ndarray, end: int, centre: np.ndarray) -> np.ndarray:
    """Unit direction along branch ``p`` leaving its ``end`` (0: first point, 1: last point)."""
    q = p if end == 0 else p[::-1]
    k = min(TANGENT_BACK_PX, len(q) - 1)
    t = q[k] - q[0] if k >= 1 else q[0] - centre
    n = np.linalg.norm(t)
    return t / n if n > 0 else np.zeros(2)


def _find_root(parent: list, x: int) -> int:
    """Root of ``x`` in the union-find forest ``parent`` (a list, compressed in place by path halving)."""
    while parent[x] != x:
        parent[x] = parent[parent[x]]
        x = parent[x]
    return x


def _traces(graph: _PixelGraph, lab, comp_ids, merge_px: float):
    """Good-continuation traces of the skeleton pieces that contain junctions.

    The skeleton is cut into branches at its junction pixels; junction clusters joined by a
    branch shorter than ``merge_px`` are merged (an X crossing thins into two T junctions).
    From every free end a depth-first search follows trails (each branch at most once) and keeps
    the one with the best length minus turning penalty, so crossings (a wire looping over itself)
    are passed straight, hairpins whose limbs touch are followed round, and spurs are left. Returns ``{component: ((M, 2) rows/cols, length_px)}`` with the
    longest trace of each component.
    """
    rr, cc, indptr, indices = graph.rr, graph.cc, graph.indptr, graph.indices
    deg = np.diff(indptr)
    junc = deg >= 3
    jidx, bidx = np.flatnonzero(junc), np.flatnonzero(~junc)
    if len(jidx) == 0 or len(bidx) == 0:
        return {}
    n = len(rr)
    gj = kernels.induced_subgraph(*graph.csr, jidx)
    ncl, cl = kernels.graph_components(gj[0], gj[1])
    clus = np.full(n, -1)
    clus[jidx] = cl
    gb = kernels.induced_subgraph(*graph.csr, bidx)
    nbr, bl = kernels.graph_components(gb[0], gb[1])
    sdeg = np.diff(gb[0])
    order = np.lexsort((sdeg, bl))
    starts = order[np.searchsorted(bl[order], np.arange(nbr))]
    dist = kernels.dijkstra(*gb, starts)[0]
    ordr = np.lexsort((dist, bl))
    bounds = np.searchsorted(bl[ordr], np.arange(nbr + 1))
    pts = np.column_stack([rr, cc]).astype(float)
    parent = list(range(ncl))

    branches = []                                   # (points, length, [cluster at end 0, end 1], comp)
    for k in range(nbr):
        nodes = bidx[ordr[bounds[k]:bounds[k + 1]]]
        if lab[nodes[0]] not in comp_ids:
            continue
        ends = []
        for e in (nodes[0], nodes[-1]):
            nb = indices[indptr[e]:indptr[e + 1]]
            c = clus[nb]
            c = c[c >= 0]
            ends.append(c)
        c0 = int(ends[0][0]) if len(ends[0]) else -1
        c1s = [int(x) for x in ends[1] if int(x) != c0] if len(nodes) == 1 else [int(x) for x in ends[1]]
        c1 = c1s[0] if c1s else -1
        length = float(dist[ordr[bounds[k + 1] - 1]])
        branches.append([pts[nodes], length, [c0, c1], int(lab[nodes[0]])])
    for b in branches:                              # merge split crossings
        c0, c1 = b[2]
        if c0 >= 0 and c1 >= 0 and c0 != c1 and b[1] < merge_px:
            parent[_find_root(parent, c0)] = _find_root(parent, c1)
            b.append(True)                          # internal to a merged junction
    cpos_sum = np.zeros((ncl, 2))
    cpos_n = np.zeros(ncl)
    root = np.array([_find_root(parent, c) for c in range(ncl)])
    np.add.at(cpos_sum, root[cl], pts[jidx])
    np.add.at(cpos_n, root[cl], 1.0)
    cpos = cpos_sum / np.maximum(cpos_n, 1.0)[:, None]
    incident: dict[int, list[tuple[int, int]]] = {}
    for k, b in enumerate(branches):
        if len(b) > 4:
            continue
        for e in (0, 1):
            if b[2][e] >= 0:
                b[2][e] = int(root[b[2][e]])
                incident.setdefault(b[2][e], []).append((k, e))
    # Depth-first search over trails (each branch used once) from every free end; the score is the
    # length minus a turning penalty at each junction, so the longest trail wins and, among
    # equally long ones (which way round a loop), the smoothest.
    best: dict[int, tuple[float, list, float]] = {}
    budget = [TRACE_MAX_STEPS]

    def away(k, e, c):
        return _away_tangent(branches[k][0], e, cpos[c])

    for k0, b0 in enumerate(branches):
        if len(b0) > 4:
            continue
        for e0 in (0, 1):
            if b0[2][e0] >= 0:
                continue                            # start only at free ends
            stack = [(k0, 1 - e0, frozenset([k0]), [(k0, e0)], b0[1], b0[1])]
            while stack and budget[0] > 0:
                budget[0] -= 1
                k, out, used, trail, length, score = stack.pop()
                comp = b0[3]
                if comp not in best or score > best[comp][0]:
                    best[comp] = (score, trail, length)
                c = branches[k][2][out]
                if c < 0:
                    continue
                d_in = -away(k, out, c)
                last = branches[k][0][-1] if out == 1 else branches[k][0][0]
                for k2, e2 in incident.get(c, ()):
                    if k2 in used:
                        continue
                    cosv = float(d_in @ away(k2, e2, c))
                    nxt = branches[k2][0][0] if e2 == 0 else branches[k2][0][-1]
                    step = branches[k2][1] + float(np.linalg.norm(nxt - last))
                    stack.append((k2, 1 - e2, used | {k2}, trail + [(k2, e2)], length + step,
                                  score + step - TURN_PENALTY_PX * (1.0 - cosv)))
    out_paths: dict[int, tuple[np.ndarray, float]] = {}
    for comp, (_, trail, length) in best.items():
        seq = [branches[k][0] if e == 0 else branches[k][0][::-1] for k, e in trail]
        out_paths[comp] = (np.vstack(seq), length)
    return out_paths


def _longest_paths(rr: np.ndarray, cc: np.ndarray, shape: tuple[int, int], merge_px: float):
    """Longest path of each piece of the skeleton with pixels ``(rr, cc)`` (row-major order) in an
    image of ``shape``, as ordered (row, col) pixel arrays with their lengths, largest pieces first:
    the good-continuation trace for pieces with junctions (see :func:`_traces`), the geodesic
    diameter (double Dijkstra) otherwise."""
    graph = _pixel_graph(rr, cc, shape)
    n_comp, lab = kernels.graph_components(graph.indptr, graph.indices)
    size = np.bincount(lab, minlength=n_comp)
    comps = [int(c) for c in np.argsort(-size)[:MAX_PIECES] if size[c] >= MIN_PIECE_PX]
    if not comps:
        return []
    traced = _traces(graph, lab, set(comps), merge_px)
    first = np.unique(lab, return_index=True)[1]          # each component's first node
    paths = []
    for c in comps:
        diam = _diameter_path(graph, int(first[c]))
        tr = traced.get(c)
        # The trace wins unless it is much shorter than the diameter (a trace stopped early).
        paths.append(tr if tr is not None and tr[1] >= 0.8 * diam[1] else diam)
    return paths


def _end_tangent(path: np.ndarray, at_end: bool) -> np.ndarray:
    """Outward unit tangent (row, col) of a pixel path at its last (``at_end``) or first point."""
    k = min(TANGENT_BACK_PX, len(path) - 1)
    if k < 1:
        return np.zeros(2)
    t = path[-1] - path[-1 - k] if at_end else path[0] - path[k]
    nrm = np.linalg.norm(t)
    return t / nrm if nrm > 0 else np.zeros(2)


def _bend_route(darkness: np.ndarray, a_rc, b_rc, near_a: np.ndarray, near_b: np.ndarray,
                half_width_px: float) -> tuple[np.ndarray | None, float, float]:
    """The darkest route across a gap of the mask between the ends ``a_rc`` and ``b_rc`` (row, col) of two
    pieces, and how well the image supports it: the least dark-line response along it (a 3 px running mean),
    relative to the wire's own response over ``near_a`` and ``near_b`` (each piece's pixels at that end).

    The response is the black top-hat of ``darkness`` (the frame, the wire darker) on a window around the gap,
    its structuring element wider than the wire. Returns ``(route, support, like)``: the route's pixels from ``a``
    to ``b`` ((K, 2) int rows/cols) or None when it detours (longer than ``BEND_ROUTE_MAX_RATIO`` x the gap +
    ``BEND_ROUTE_SLACK_PX``) or the wire has no response; the support (0 when None); and how alike the two pieces
    are (the fainter's response / the other's; 0 without a response)."""
    from skimage.graph import route_through_array

    a, b = np.asarray(a_rc, int), np.asarray(b_rc, int)
    gap = float(np.linalg.norm(a - b))
    tophat, lo = _black_tophat(darkness, np.minimum(a, b) - BEND_REF_PX, np.maximum(a, b) + BEND_REF_PX,
                               half_width_px)
    ref_a, ref_b = _median_at(tophat, lo, near_a), _median_at(tophat, lo, near_b)
    ref = min(ref_a, ref_b)
    if not ref > 0:
        return None, 0.0, 0.0
    like = ref / max(ref_a, ref_b)
    rel = np.clip(tophat / ref, 0.0, 1.0)
    route, _ = route_through_array(1.0 / (0.1 + rel), tuple(a - lo), tuple(b - lo), fully_connected=True,
                                   geometric=True)
    route = np.asarray(route, int)
    if polyline_length(route) > BEND_ROUTE_MAX_RATIO * gap + BEND_ROUTE_SLACK_PX:
        return None, 0.0, like
    prof = rel[route[:, 0], route[:, 1]]
    if len(prof) >= 3:
        prof = np.convolve(prof, np.ones(3) / 3.0, mode="valid")
    return route + lo, float(prof.min()), like


def _bridge(paths, max_gap_px: float, darkness: np.ndarray | None = None, half_width_px: float = 1.0,
            inner_rc: tuple[int, int, int, int] | None = None):
    """Join path ends that are close and whose directions agree, and, with the frame (``darkness``, in the paths'
    pixel coordinates), ends at a sharp bend the image shows a wire across (``BEND_*``, :func:`_bend_route`; ends
    within ``inner_rc`` = (row0, row1, col0, col1), the image's own pixels, 3 px inside); return the longest chain
    as one ordered (row, col) array, the number of bridges on it, the indices of its pieces, the number of
    its bridges across a bend and the number across a long break in line (``LONG_GAP_*``)."""
    n = len(paths)
    if n == 1 or max_gap_px <= 0:
        return paths[0][0], 0, {0}, 0, 0
    ends = []                                      # (piece, at_end, point, outward tangent)
    for i, (p, _) in enumerate(paths):
        ends.append((i, False, p[0], _end_tangent(p, False)))
        ends.append((i, True, p[-1], _end_tangent(p, True)))
    pts = np.array([e[2] for e in ends])
    tan = np.array([e[3] for e in ends])
    piece = np.array([e[0] for e in ends])
    diff = pts[None, :, :] - pts[:, None, :]       # from end i to end j
    dist = np.linalg.norm(diff, axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = diff / dist[:, :, None]
    cos_i = np.einsum("ijk,ik->ij", unit, tan)     # gap vs outward tangent at i
    cos_j = -np.einsum("ijk,jk->ij", unit, tan)    # gap vs outward tangent at j (reversed)
    cmin = np.cos(np.radians(BRIDGE_MAX_ANGLE_DEG))
    no_tan = np.linalg.norm(tan, axis=1) == 0
    ok_i = (cos_i >= cmin) | no_tan[:, None]
    ok_j = (cos_j >= cmin) | no_tan[None, :]
    valid = (dist <= max_gap_px) & (piece[:, None] != piece[None, :])
    valid &= (ok_i & ok_j) | (dist <= BRIDGE_FREE_PX)
    valid = np.triu(valid, 1)
    cost = dist * (2.0 + np.nan_to_num(-cos_i - cos_j))
    routes = {}
    if darkness is not None:
        bend = np.triu((dist <= min(max_gap_px, BEND_BRIDGE_MAX_PX)) & (piece[:, None] != piece[None, :]), 1)
        c_long = np.cos(np.radians(LONG_GAP_MAX_ANGLE_DEG))
        long_gap = np.triu((dist > max_gap_px) & (dist <= LONG_GAP_MAX_PX) & (cos_i >= c_long) & (cos_j >= c_long)
                           & (piece[:, None] != piece[None, :]), 1)
        bend = (bend | long_gap) & ~valid
        if inner_rc is not None:
            r0, r1, c0, c1 = inner_rc
            inside = ((pts[:, 0] >= r0 + 3) & (pts[:, 0] <= r1 - 4) & (pts[:, 1] >= c0 + 3)
                      & (pts[:, 1] <= c1 - 4))
            bend &= inside[:, None] & inside[None, :]
        for i, j in zip(*np.nonzero(bend)):
            near = [paths[piece[e]][0][-BEND_REF_PX:] if ends[e][1] else paths[piece[e]][0][:BEND_REF_PX]
                    for e in (i, j)]
            route, support, like = _bend_route(darkness, pts[i], pts[j], near[0], near[1], half_width_px)
            if route is not None and support >= BEND_MIN_SUPPORT and like >= BEND_MIN_LIKE:
                valid[i, j] = True
                routes[(int(i), int(j))] = (route, polyline_length(route), bool(long_gap[i, j]))
                cost[i, j] = 2.0 * routes[(int(i), int(j))][1]   # after any bridge whose directions agree
    ii, jj = np.nonzero(valid)
    order = np.argsort(cost[ii, jj])
    used = np.zeros(len(ends), bool)
    parent = list(range(n))

    link = {}
    for k in order:
        i, j = ii[k], jj[k]
        if used[i] or used[j]:
            continue
        ri, rj = _find_root(parent, piece[i]), _find_root(parent, piece[j])
        if ri == rj:
            continue
        parent[ri] = rj
        used[i] = used[j] = True
        link[i], link[j] = j, i
    # Walk the chains: start from a piece end with no link (every chain is acyclic).
    best, best_len, best_bridges, best_pieces, best_bends, best_longs = None, -1.0, 0, set(), 0, 0
    seen = np.zeros(n, bool)
    for start in range(len(ends)):
        if start in link or seen[piece[start]]:
            continue
        seq, total, bridges, e, pieces, bends, longs = [], 0.0, 0, start, set(), 0, 0
        while True:
            i = piece[e]
            seen[i] = True
            pieces.add(int(i))
            p, length = paths[i]
            forward = not ends[e][1]               # entering at the first point: keep the order
            seq.append(p if forward else p[::-1])
            total += length
            other = e + 1 if forward else e - 1    # the same piece's other end
            if other not in link:
                break
            nxt = link[other]
            bend = routes.get((min(other, nxt), max(other, nxt)))
            if bend is None:
                total += dist[other, nxt]
            else:                                   # across a bend or a long break: the image's route, not the chord
                route, route_px, is_long = bend
                seq.append((route if other < nxt else route[::-1])[1:-1])
                total += route_px
                longs += int(is_long)
                bends += int(not is_long)
            bridges += 1
            e = nxt
        if total > best_len:
            best, best_len, best_bridges, best_pieces, best_bends, best_longs = (np.vstack(seq), total, bridges,
                                                                                 pieces, bends, longs)
    return best, best_bridges, best_pieces, best_bends, best_longs


def _tophat_size_px(half_width_px: float) -> int:
    """The black top-hat's structuring element (px): wider than the wire."""
    return 2 * int(np.ceil(2.0 * half_width_px)) + 3


def _black_tophat(darkness: np.ndarray, lo_rc, hi_rc, half_width_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The dark-line response of ``darkness`` (the frame, the wire darker): its black top-hat, the structuring
    element wider than the wire, on the window from ``lo_rc`` to ``hi_rc`` (rows/cols, inclusive) widened by that
    element and clipped to the frame. Returns ``(response, window origin)``."""
    k = _tophat_size_px(half_width_px)
    lo = np.maximum(np.asarray(lo_rc, int) - k, 0)
    hi = np.minimum(np.asarray(hi_rc, int) + k + 1, darkness.shape)
    sub = np.asarray(darkness[lo[0]:hi[0], lo[1]:hi[1]], np.float64)
    return ndi.grey_closing(sub, size=(k, k)) - sub, lo


def _median_at(response: np.ndarray, lo: np.ndarray, pixels_rc) -> float:
    """The median of ``response`` (a window whose origin is ``lo``) at the pixels ``pixels_rc`` inside it, else 0."""
    q = np.asarray(pixels_rc, int).reshape(-1, 2) - lo
    q = q[(q >= 0).all(axis=1) & (q < response.shape).all(axis=1)]
    return float(np.median(response[q[:, 0], q[:, 1]])) if len(q) else 0.0


def _line_response(darkness: np.ndarray, pixels_rc: np.ndarray, half_width_px: float) -> float:
    """The median dark-line response (:func:`_black_tophat` on the pixels' bounding box) of ``darkness`` at the
    pixels ``pixels_rc`` ((K, 2) rows/cols)."""
    q = np.asarray(pixels_rc, int).reshape(-1, 2)
    q = q[(q >= 0).all(axis=1) & (q < darkness.shape).all(axis=1)]
    if not len(q):
        return 0.0
    tophat, lo = _black_tophat(darkness, q.min(axis=0), q.max(axis=0), half_width_px)
    return _median_at(tophat, lo, q)


def _hairpin(chain_rc: np.ndarray, paths, used: set, half_width_px: float, *, at_last: bool,
             darkness: np.ndarray | None = None) -> tuple[np.ndarray, float, int | None]:
    """Join, at one end of the chain ``chain_rc`` ((M, 2) rows/cols; its last point when ``at_last``), the other
    limb of a hairpin whose limbs touch in the mask (``HAIRPIN_*``): the longest piece of ``paths`` not in
    ``used`` whose end lies beside the chain's last ``HAIRPIN_MAX_BACK_PX`` px, its outward tangent along the
    chain towards that end, and its other end away from the chain. The chain runs on to its end, back along
    itself to beside the piece's end, and out along the piece. With the frame (``darkness``), the piece must be
    as dark a line as the chain's stretch before it (``HAIRPIN_MIN_LIKE``). The caller checks that the join
    keeps the wire's order (:func:`ordered_wire`). Returns ``(chain, px run back, piece joined or None)``."""
    from scipy.spatial import cKDTree

    pieces = [i for i, (_, length) in enumerate(paths) if i not in used and length >= HAIRPIN_MIN_PIECE_PX]
    if not pieces:                                              # most frames: the trace is the whole mask
        return chain_rc, 0.0, None
    c = np.asarray(chain_rc, float)
    c = c if at_last else c[::-1]
    n = len(c)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))]
    from_end = arc[-1] - arc
    tail = np.flatnonzero(from_end <= HAIRPIN_MAX_BACK_PX)
    if n < 8 or len(tail) < 2:
        return chain_rc, 0.0, None
    near = HAIRPIN_NEAR_HALF_WIDTHS * half_width_px + HAIRPIN_NEAR_SLACK_PX
    tree, whole = cKDTree(c[tail]), cKDTree(c)
    best = None
    for i in pieces:
        p, length = paths[i]
        for piece_end in (False, True):
            d, j = tree.query(p[-1] if piece_end else p[0])
            k = int(tail[j])
            if d > near or from_end[k] < HAIRPIN_MIN_BACK_PX:
                continue
            fwd = c[min(k + 3, n - 1)] - c[max(k - 3, 0)]
            fwd = fwd / max(float(np.linalg.norm(fwd)), 1e-12)
            if float(fwd @ _end_tangent(p, piece_end)) < HAIRPIN_MIN_COS:
                continue
            if whole.query(p[0] if piece_end else p[-1])[0] <= near:
                continue                                        # both its ends beside the chain: no limb leaving it
            if best is None or length > best[0]:
                best = (length, i, piece_end, k)
    if best is None:
        return chain_rc, 0.0, None
    _, i, piece_end, k = best
    limb = paths[i][0][::-1] if piece_end else paths[i][0]
    if darkness is not None:
        before = c[np.flatnonzero((from_end > from_end[k]) & (from_end <= from_end[k] + 4 * BEND_REF_PX))]
        ref = _line_response(darkness, np.round(before), half_width_px) if len(before) else 0.0
        if not ref > 0 or _line_response(darkness, limb, half_width_px) < HAIRPIN_MIN_LIKE * ref:
            return chain_rc, 0.0, None
    c = np.vstack([c, c[k:-1][::-1], limb])
    return (c if at_last else c[::-1]), float(from_end[k]), i


def _tip_fork(uv: np.ndarray, skel_uv: np.ndarray, half_width_px: float) -> TipFork | None:
    """The skeleton branch (of the skeleton pixels ``skel_uv``, (u, v)) off the ordered wire ``uv`` that leaves it
    within ``TIP_FORK_NEAR_PX`` of its tip and reaches farthest from it, if that is at least ``TIP_FORK_MIN_PX``
    (or ``TIP_FORK_MIN_HALF_WIDTHS`` half-widths); else None. Off the wire: farther than the half-width + 1.5
    px from it; a branch is an 8-connected group of such pixels, attached when its nearest pixel lies within
    the half-width + 3 px of the wire."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    if len(uv) < 3 or len(skel_uv) == 0:
        return None
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(uv, axis=0), axis=1))]
    from_tip = s[-1] - s
    d, j = cKDTree(uv).query(skel_uv)
    off = np.flatnonzero(d > half_width_px + 1.5)
    if len(off) == 0:
        return None
    pairs = cKDTree(skel_uv[off]).query_pairs(1.5, output_type="ndarray")
    n = len(off)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)) if len(pairs) else \
        coo_matrix((n, n))
    _, lab = connected_components(g, directed=False)
    best = None
    need = max(TIP_FORK_MIN_PX, TIP_FORK_MIN_HALF_WIDTHS * half_width_px)
    for c in np.unique(lab):
        members = off[lab == c]
        a = members[np.argmin(d[members])]
        if d[a] > half_width_px + 3.0 or from_tip[j[a]] > TIP_FORK_NEAR_PX:
            continue
        reach = float(d[members].max())
        if reach >= need and (best is None or reach > best.reach_px):
            best = TipFork(reach, float(from_tip[j[a]]))
    return best


def _beyond_tip(uv: np.ndarray, paths, used: set, offset_uv: np.ndarray) -> BeyondTip | None:
    """The piece (of ``paths``, (row, col) arrays in the ROI whose origin is ``offset_uv``) not in
    ``used`` that lies beyond the tip ``uv[-1]`` of the ordered wire and in line with it, or very
    near it at any angle (``BEYOND_TIP_*``), the nearest if several; None if there is none."""
    k = min(TANGENT_BACK_PX, len(uv) - 1)
    t = uv[-1] - uv[-1 - k]
    if k < 1 or not np.linalg.norm(t) > 0:
        return None
    t = t / np.linalg.norm(t)
    cmin = np.cos(np.radians(BEYOND_TIP_MAX_ANGLE_DEG))
    best = None
    for i, (p, length) in enumerate(paths):
        if i in used or length < BEYOND_TIP_MIN_LENGTH_PX:
            continue
        for end in (p[0], p[-1]):
            d = end[::-1] + offset_uv - uv[-1]
            gap = float(np.linalg.norm(d))
            if gap > BEYOND_TIP_MAX_GAP_PX or gap <= 0:
                continue
            c = float(d @ t) / gap
            if (c >= cmin or gap <= BEYOND_TIP_NEAR_GAP_PX) and (best is None or gap < best.gap_px):
                best = BeyondTip(float(length), gap, float(np.degrees(np.arccos(min(c, 1.0)))))
    return best


def tip_darkness(image, points_uv_px, *, at_end: bool = True) -> float:
    """How many times as dark as the wire its tip is: two layers of wire at a traced tip (see
    ``DOUBLED_END_RATIO``).

    The line darkness (the image summed across the line within ``END_LINE_HALF_PX``, 1 px apart,
    minus its background: the median of the samples at ``END_BACKGROUND_PX`` to both sides) over
    the ``END_WINDOW_PX`` points at the tip, over its median at every fourth point of
    ``END_REFERENCE_PX`` back from the tip.

    Parameters
    ----------
    image : (H, W) ndarray
        The live frame (the wire darker than the background).
    points_uv_px : (N, 2) array_like of float
        The ordered wire, ~1 px apart (``OrderedWire.points_uv_px``).
    at_end : bool
        The tip is the last point (else the first: a caller that reversed the order).

    Returns
    -------
    float
        Near 1 along a single wire, below 1 at a free tip (the wire ends inside the window), near 2
        or more where two layers lie; NaN for fewer than ``3 * END_WINDOW_PX`` points or a wire
        without contrast.
    """
    uv = np.asarray(points_uv_px, float).reshape(-1, 2)
    n = len(uv)
    if n < 3 * END_WINDOW_PX:
        return float("nan")
    if not at_end:
        uv = uv[::-1]
    w = END_WINDOW_PX
    ref = n - 1 - np.arange(min(END_REFERENCE_PX[0], n // 3), min(END_REFERENCE_PX[1], n), 4)
    idx = np.concatenate([ref, np.arange(n - w, n)])
    tangent = uv[np.minimum(idx + 1, n - 1)] - uv[np.maximum(idx - 1, 0)]
    tangent /= np.maximum(np.sqrt((tangent ** 2).sum(axis=1)), 1e-12)[:, None]
    offs = np.arange(-END_BACKGROUND_PX[1], END_BACKGROUND_PX[1] + 1e-9, 1.0)
    p = uv[idx]
    rows = p[:, 1:2] + offs[None, :] * tangent[:, 0:1]     # the normal (row, col) = (t_u, -t_v)
    cols = p[:, 0:1] - offs[None, :] * tangent[:, 1:2]
    v = kernels.sample_bilinear(np.asarray(image), rows, cols, mode="nearest")
    a = np.abs(offs)
    band = v[:, a >= END_BACKGROUND_PX[0]]
    m = band.shape[1]                                       # the band's median: its middle order statistics
    mid = np.partition(band, [(m - 1) // 2, m // 2], axis=1)
    background = 0.5 * (mid[:, (m - 1) // 2] + mid[:, m // 2])
    dark = background * np.count_nonzero(a <= END_LINE_HALF_PX) - v[:, a <= END_LINE_HALF_PX].sum(axis=1)
    med = float(np.sort(dark[:-w])[(len(dark) - w) // 2])
    return float(dark[-w:].mean() / med) if med > 0 else float("nan")


def tip_end_check(image, points_uv_px, *, at_end: bool = True) -> "DoubledTip | BareTip | None":
    """What the image shows at a traced tip (:func:`tip_darkness`): a :class:`DoubledTip` at
    ``DOUBLED_END_RATIO`` or more (two layers of wire), a :class:`BareTip` below ``BARE_END_RATIO``
    (no wire: the trace runs past its end), else None (also when the ratio cannot be measured)."""
    r = tip_darkness(image, points_uv_px, at_end=at_end)
    if r >= DOUBLED_END_RATIO:
        return DoubledTip(r)
    if r < BARE_END_RATIO:
        return BareTip(r)
    return None


def doubled_tip(image, points_uv_px, *, at_end: bool = True) -> DoubledTip | None:
    """A :class:`DoubledTip` when the tip (see :func:`tip_darkness`) is at least
    ``DOUBLED_END_RATIO`` times as dark as the wire, else None."""
    r = tip_darkness(image, points_uv_px, at_end=at_end)
    return DoubledTip(r) if r >= DOUBLED_END_RATIO else None


def _smooth_polyline(p: np.ndarray, sigma_px: float) -> np.ndarray:
    """Resample at 1 px and Gaussian-smooth along the arc length (ends kept in place)."""
    q = resample_polyline(p, 1.0)
    if len(q) < 5 or sigma_px <= 0:
        return q
    s = ndi.gaussian_filter1d(q, sigma_px, axis=0, mode="nearest")
    s[0], s[-1] = q[0], q[-1]
    return s


def _refine(p_rc: np.ndarray, maskf: np.ndarray, image: np.ndarray | None, half_px: float) -> np.ndarray:
    """Move each point of an ordered (row, col) polyline to the weighted centroid of the mask
    (times the image darkness ``-image``, if given) sampled along its normal. ``maskf`` and
    ``image`` may be of any real dtype (a 0/1 uint8 mask, the frame's own dtype): the samples are
    float64."""
    nrm = polyline_normals(p_rc)
    offs = np.arange(-half_px, half_px + 1e-9, PROFILE_STEP_PX)
    # (N, K) sample rows and columns (each its own contiguous array: faster than (N, K, 2))
    rows = p_rc[:, 0:1] + offs[None, :] * nrm[:, 0:1]
    cols = p_rc[:, 1:2] + offs[None, :] * nrm[:, 1:2]
    w = kernels.sample_bilinear(maskf, rows, cols, mode="constant")
    if image is not None:
        dk = -kernels.sample_bilinear(image, rows, cols, mode="nearest")
        w = w * np.clip(dk - dk.min(axis=1, keepdims=True), 0, None)
    sw = w.sum(axis=1)
    ok = sw > 1e-6
    delta = np.zeros(len(p_rc))
    delta[ok] = (w[ok] * offs[None, :]).sum(axis=1) / sw[ok]
    return p_rc + delta[:, None] * nrm


def _pad_edge(a: np.ndarray, ext) -> np.ndarray:
    """``np.pad(a, ext, mode="edge")`` of a 2D array (OpenCV's border replication where it takes the dtype)."""
    import cv2

    (top, bottom), (left, right) = ext
    if a.dtype == bool:
        return _pad_edge(a.view(np.uint8), ext).view(bool)
    if a.dtype in (np.uint8, np.uint16, np.int16, np.float32, np.float64) and min(a.shape) > 0:
        return cv2.copyMakeBorder(np.ascontiguousarray(a), int(top), int(bottom), int(left), int(right),
                                  cv2.BORDER_REPLICATE)
    return np.pad(a, ext, mode="edge")


def _catheter_contrast(img: np.ndarray, uv: np.ndarray, half_width_px: float) -> float:
    """How strongly a darker tube (a guiding catheter) encloses the first ``CATHETER_SEARCH_PX``
    of the ordered wire ``uv`` (from ``uv[0]``): on each side, the median of a background band
    (``CATHETER_FAR_PX`` beyond the wire's half-width) minus that of the band next to the wire
    (``CATHETER_NEAR_PX``), in units of the background's noise (1.4826 MAD); the weaker side
    counts, so a tube (dark on both sides) scores and a neighbouring structure on one side does not."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(uv, axis=0), axis=1))])
    rc = uv[s <= CATHETER_SEARCH_PX][:, ::-1]
    if len(rc) < 3:
        return 0.0
    nrm = polyline_normals(rc)

    def band(lo_hi, sign):
        w = sign * (half_width_px + np.arange(lo_hi[0], lo_hi[1] + 1e-9, PROFILE_STEP_PX))
        pts = rc[:, None, :] + w[None, :, None] * nrm[:, None, :]
        return kernels.sample_bilinear(img, pts[..., 0].ravel(), pts[..., 1].ravel(), mode="nearest")

    far = {sign: band(CATHETER_FAR_PX, sign) for sign in (1, -1)}
    both = np.concatenate(list(far.values()))
    noise = 1.4826 * float(np.median(np.abs(both - np.median(both))))
    if noise <= 0.0:
        noise = max(1e-12, 1e-6 * float(np.ptp(both)))
    return min(float(np.median(far[sign]) - np.median(band(CATHETER_NEAR_PX, sign))) / noise for sign in (1, -1))


def _catheter_end(img: np.ndarray, uv: np.ndarray, half_width_px: float) -> int | None:
    """0 or 1 (first or last point of ``uv``) if a guiding catheter clearly encloses that end of the
    wire and not the other (``CATHETER_MIN_Z``, ``CATHETER_MIN_GAP_Z``), else None."""
    z = (_catheter_contrast(img, uv, half_width_px), _catheter_contrast(img, uv[::-1], half_width_px))
    k = int(np.argmax(z))
    if z[k] >= CATHETER_MIN_Z and z[k] - z[1 - k] >= CATHETER_MIN_GAP_Z:
        return k
    return None


def _extend_end(p_rc: np.ndarray, maskf: np.ndarray, at_end: bool, max_px: float) -> np.ndarray:
    """Extend one end along its tangent to where the mask's centre line leaves the mask, minus
    ``TIP_CAP_FRACTION`` x the local mask width (the end cap: 0 for a flat cut, 0.5 for a round
    cap; the rasterised mask of a tube's end lies in between)."""
    k = min(4, len(p_rc) - 1)
    if k < 1:
        return p_rc
    t = p_rc[-1] - p_rc[-1 - k] if at_end else p_rc[0] - p_rc[k]
    nt = np.linalg.norm(t)
    if nt == 0:
        return p_rc
    t /= nt
    e = p_rc[-1] if at_end else p_rc[0]
    steps = np.arange(0.0, max_px + 1e-9, REFINE_STEP_PX)
    line = e[None, :] + steps[:, None] * t[None, :]
    val = kernels.sample_bilinear(maskf, line[:, 0], line[:, 1], mode="constant")
    outside = np.nonzero(val < 0.5)[0]
    reach = steps[outside[0]] - REFINE_STEP_PX / 2 if len(outside) else steps[-1]
    # Half-width across the end: mask sampled along the normal at the end point.
    nrm = np.array([-t[1], t[0]])
    offs = np.arange(-max_px, max_px + 1e-9, REFINE_STEP_PX)
    across = e[None, :] + offs[:, None] * nrm[None, :]
    width = kernels.sample_bilinear(maskf, across[:, 0], across[:, 1], mode="constant").sum() * REFINE_STEP_PX
    ext = reach - TIP_CAP_FRACTION * width
    if ext <= 0.25:
        return p_rc
    new = e + ext * t
    return np.vstack([p_rc, new]) if at_end else np.vstack([new, p_rc])


def ordered_wire(mask, *, image=None, proximal_hint_uv=None, max_gap_px: float = 15.0,
                 check_presence: bool = True) -> OrderedWire:
    """Ordered sub-pixel guidewire centerline from a guidewire mask.

    Zhang-Suen thinning of the mask, an 8-connected pixel graph, the longest path of each skeleton
    piece (a good-continuation trace through junctions and crossings; spurs are left), bridging of
    pieces whose end points are within ``max_gap_px`` with agreeing directions (with ``image``, also
    ends at a sharp bend, within ``BEND_BRIDGE_MAX_PX``, and ends in line up to ``LONG_GAP_MAX_PX`` apart,
    when the frame's darkest route between them is as dark a line as the wire: ``BEND_*``, ``LONG_GAP_*``),
    joining the other limb of a hairpin whose limbs merge in the mask (``HAIRPIN_*``),
    sub-pixel centring across the local normal, extension of both ends to the mask's end caps,
    proximal -> distal ordering and resampling at ~1 px.

    Parameters
    ----------
    mask : (H, W) array_like of bool
        Guidewire mask (float masks are thresholded at 0.5, integer masks at != 0).
    image : (H, W) array_like, optional
        The live frame (wire darker than background); if given, the sub-pixel centring weights the
        mask by the local darkness of the image, and a blank or saturated image fails.
    proximal_hint_uv : (2,) array_like, optional
        ``(u, v)`` near the proximal end (e.g. the projected vessel root). Without it, the end
        enclosed by a guiding catheter (a darker tube around the wire, seen in ``image``; see
        ``CATHETER_*``) is proximal if only one end is, else the end closer to the image border.
    max_gap_px : float
        Largest break in the mask that is bridged, px.
    check_presence : bool
        With ``image``: test whether the traced curve is a guidewire at all
        (:func:`guidewire3d.xray.wirepresence.wire_presence`: its width across the curve, the mask
        branching around it, a one-sided edge), and fail with ``"no guidewire in the frame: <why>"``
        if not (a frame without a wire: the segmenter's answer is a vessel, a branch of the tree or
        the collimator's edge). ``False`` skips the test (callers that trace a curve in any case).

    Returns
    -------
    OrderedWire
        Falsy (``success=False`` and a reason) for an empty or blob-like mask, a blank image, no
        path longer than ``MIN_WIRE_LENGTH_PX`` or (with ``image``) a curve that is not a
        guidewire; never a fabricated wire. ``presence`` holds the presence test's evidence.

    Raises
    ------
    InputError
        If the mask is not 2D, the image shape differs, or the hint is not a finite (u, v).
    """
    m_full = as_mask(mask, "mask")
    img = None
    if image is not None:
        img = grey(image)
        if img.shape != m_full.shape:
            raise InputError(f"image: shape {img.shape} differs from the mask's {m_full.shape}")
        if img.dtype == bool or not np.issubdtype(img.dtype, np.number):
            raise InputError(f"image: expected a numeric image, got dtype {img.dtype}")
        if np.issubdtype(img.dtype, np.floating) and not np.isfinite(img).all():
            raise InputError("image: image contains NaN or infinite values")
    hint = None
    if proximal_hint_uv is not None:
        hint = np.asarray(proximal_hint_uv, float).reshape(-1)
        if hint.shape != (2,) or not np.all(np.isfinite(hint)):
            raise InputError(f"proximal_hint_uv: expected a finite (u, v) pair, got {proximal_hint_uv!r}")
    if not np.isfinite(max_gap_px) or max_gap_px < 0:
        raise InputError(f"max_gap_px: expected a finite value >= 0, got {max_gap_px}")
    if img is not None:
        sub = img[::4, ::4].astype(np.float64)
        lo, hi = _percentiles_1_99(sub)
        if hi - lo <= BLANK_REL_SPREAD * max(abs(lo), abs(hi), 1e-12):
            return _failed("image is blank or saturated (no intensity contrast)")
        at_max = float(np.mean(sub >= sub.max()))
        if at_max >= SATURATED_FRACTION:
            return _failed(f"image is saturated ({100 * at_max:.0f}% of the pixels at the maximum)")
    n_on = int(np.count_nonzero(m_full))
    if n_on == 0:
        return _failed("empty guidewire mask")
    if n_on > MAX_MASK_FRACTION * m_full.size:
        return _failed(f"mask covers {100.0 * n_on / m_full.size:.0f}% of the image: not a guidewire")

    # Region of interest around the mask (speed), with a margin for the refinement samples.
    rows = np.flatnonzero(m_full.any(axis=1))
    cols = np.flatnonzero(m_full.any(axis=0))
    pad = 8
    r0, r1 = max(rows[0] - pad, 0), min(rows[-1] + pad + 1, m_full.shape[0])
    c0, c1 = max(cols[0] - pad, 0), min(cols[-1] + pad + 1, m_full.shape[1])
    # Where the wire leaves the image, continue the mask beyond the border (edge replication) so
    # that the skeleton does not fork at the cut; points outside the image are dropped at the end.
    H, W = m_full.shape
    ext = ((pad if r0 == 0 else 0, pad if r1 == H else 0), (pad if c0 == 0 else 0, pad if c1 == W else 0))
    m = _pad_edge(m_full[r0:r1, c0:c1], ext) if any(map(any, ext)) else m_full[r0:r1, c0:c1]
    o_r, o_c = r0 - ext[0][0], c0 - ext[1][0]           # ROI (0, 0) in image pixels
    m = np.ascontiguousarray(m)                          # sampled below: one contiguous copy

    sr, sc, n_mask = kernels.skeleton_pixels(m)          # Zhang-Suen thinning (skimage's skeletonize)
    half_width = 0.5 * float(n_mask) / max(float(len(sr)), 1.0)   # mean half-width, px
    paths = _longest_paths(sr, sc, m.shape, merge_px=4.0 * half_width + 2.0)
    if not paths:
        return _failed("no skeleton piece of the mask is long enough to be a guidewire")
    darkness = None
    if img is not None:
        darkness = img[r0:r1, c0:c1]                    # the wire darker: _refine weighs by -image
        if any(map(any, ext)):
            darkness = _pad_edge(darkness, ext)
    path_rc, n_bridges, used, n_bends, n_long = _bridge(paths, float(max_gap_px), darkness, half_width,
                                                (-o_r, H - 1 - o_r, -o_c, W - 1 - o_c))
    # A hairpin whose limbs touch in the mask (``HAIRPIN_*``): the trace holds one limb and the merged stretch, the
    # other limb is a piece beside it. At the trace's distal end (the end the ordering below would take as distal:
    # farther from the hint, else from the image border) that piece is the distal limb, or, when it leads nearer
    # the hint than the trace's other end, the proximal one (the trace then held the distal limb, and the order
    # turns). At the proximal end it is joined only when it leads nearer the hint than that end: a side branch
    # that leaves the wire pointing along it is not joined there.
    def proximity(rc):
        uv_end = np.asarray(rc, float)[::-1] + np.array([o_c, o_r], float)
        if hint is not None:
            return float(np.linalg.norm(uv_end - hint))
        return float(min(uv_end[0], uv_end[1], m_full.shape[1] - 1 - uv_end[0], m_full.shape[0] - 1 - uv_end[1]))

    hairpin_px = 0.0
    for distal in (True, False):
        at_last = (proximity(path_rc[-1]) >= proximity(path_rc[0])) == distal
        joined_rc, back_px, piece = _hairpin(path_rc, paths, used, half_width, at_last=at_last, darkness=darkness)
        if piece is None:
            continue
        new_end, replaced = (joined_rc[-1], path_rc[-1]) if at_last else (joined_rc[0], path_rc[0])
        if distal or proximity(new_end) < proximity(replaced):
            path_rc, hairpin_px, used = joined_rc, hairpin_px + back_px, used | {piece}
    if len(path_rc) < 2:
        return _failed("no skeleton piece of the mask is long enough to be a guidewire")
    raw_len = float(np.linalg.norm(np.diff(path_rc, axis=0), axis=1).sum())
    if raw_len < MIN_WIRE_LENGTH_PX:
        return _failed(f"longest wire path is {raw_len:.1f} px (< {MIN_WIRE_LENGTH_PX:.0f} px): no guidewire")
    comp_area = float(n_mask)
    if comp_area / max(raw_len, 1.0) > MAX_MEAN_WIDTH_PX:
        return _failed(f"mask is blob-like (area / length = {comp_area / raw_len:.1f} px): not a guidewire")

    # Sub-pixel centring.
    maskf = m.view(np.uint8)                            # 0/1, sampled as float64
    half = float(np.clip(np.ceil(half_width + 2.0), 2.0, 8.0))
    p = _smooth_polyline(path_rc, REFINE_SMOOTH_PX)
    p = _refine(p, maskf, darkness, half)
    p = _smooth_polyline(p, 1.0)
    p = _extend_end(p, maskf, True, half + 2.0)
    p = _extend_end(p, maskf, False, half + 2.0)
    uv = p[:, ::-1] + np.array([o_c, o_r], float)
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= W - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= H - 0.5)
    if not inside.all():
        idx = np.flatnonzero(inside)
        if len(idx) < 2:
            return _failed("the wire path lies outside the image")
        runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
        uv = uv[max(runs, key=len)]                      # the longest stretch inside the image
    uv = resample_polyline(uv, 1.0)

    # Is the curve a guidewire at all (a frame without a wire: a vessel, a tree, an edge)?
    presence = None
    if img is not None and check_presence:
        skel_uv = np.column_stack([sc + o_c, sr + o_r])     # with the mask's extension beyond the border
        presence = presence_of_curve(img, uv, skel_uv)
        if not presence:
            why = presence.reason.removeprefix("no guidewire: ")
            return OrderedWire(points_uv_px=np.zeros((0, 2)), success=False,
                               message=f"no guidewire in the frame: {why}", presence=presence)

    # Proximal -> distal.
    h, w = m_full.shape
    if hint is not None:
        flip = np.linalg.norm(uv[-1] - hint) < np.linalg.norm(uv[0] - hint)
    else:
        catheter = None if img is None else _catheter_end(img, uv, half_width)
        if catheter is not None:
            flip = catheter == 1
        else:
            def border(q):
                return min(q[0], q[1], w - 1 - q[0], h - 1 - q[1])
            flip = border(uv[-1]) < border(uv[0])
    if flip:
        uv = uv[::-1].copy()
    length = float(np.linalg.norm(np.diff(uv, axis=0), axis=1).sum())
    beyond = _beyond_tip(uv, paths, used, np.array([o_c, o_r], float)) if len(paths) > 1 else None
    skel = np.column_stack([sc + o_c, sr + o_r]).astype(float)
    # the skeleton of the mask as the image holds it (not of its replication beyond the border, which forks there)
    skel = skel[(skel[:, 0] >= 0) & (skel[:, 0] <= W - 1) & (skel[:, 1] >= 0) & (skel[:, 1] <= H - 1)]
    fork = _tip_fork(uv, skel, half_width)
    return OrderedWire(points_uv_px=uv, success=True, message="ok", length_px=length,
                       n_gaps_bridged=int(n_bridges), n_bends_bridged=int(n_bends), n_long_gaps_bridged=int(n_long),
                       presence=presence, beyond_tip=beyond, tip_fork=fork, hairpin_px=hairpin_px)


# --------------------------------------------------------------------------------------------
# The paper's gradient-weighted wire graph
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class WireSpectrum:
    """Spectral decomposition of the paper's weighted wire graph.

    Attributes
    ----------
    weights : (N-1,) ndarray of float
        ``W[i, i+1] = exp(-||grad I(v_i) - grad I(v_{i+1})||^2 / (2 sigma_g^2))``.
    laplacian : (N, N) ndarray of float
        ``L = D - W``.
    eigenvalues : (N,) ndarray of float
        Ascending; the first is 0 (the constant vector).
    eigenvectors : (N, N) ndarray of float
        Orthonormal columns ``Phi`` with ``L = Phi diag(eigenvalues) Phi^T``.
    curvature_per_px : (N,) ndarray of float
        Discrete signed curvature of the wire at each point (turning angle / arc length), 1/px.
    curvature_spectrum : (N,) ndarray of float
        ``Phi^T curvature`` (graph Fourier coefficients, low frequencies first).
    gradient : (N, 2) ndarray of float
        ``(dI/du, dI/dv)`` of the normalised image at the points, 1/px.
    """

    weights: np.ndarray
    laplacian: np.ndarray
    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    curvature_per_px: np.ndarray
    curvature_spectrum: np.ndarray
    gradient: np.ndarray

    def energy_fraction(self, k: int) -> float:
        """Fraction of the curvature energy in the ``k`` lowest graph frequencies."""
        e = self.curvature_spectrum ** 2
        tot = float(e.sum())
        return 1.0 if tot == 0 else float(e[:k].sum() / tot)


def discrete_curvature(points_uv_px) -> np.ndarray:
    """Signed discrete curvature (1/px) of an ordered polyline: turning angle at each interior
    point divided by the mean of its two segment lengths; 0 at both ends."""
    p = np.asarray(points_uv_px, float)
    k = np.zeros(len(p))
    if len(p) < 3:
        return k
    a, b = p[1:-1] - p[:-2], p[2:] - p[1:-1]
    ang = np.arctan2(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0], (a * b).sum(axis=1))
    ds = 0.5 * (np.linalg.norm(a, axis=1) + np.linalg.norm(b, axis=1))
    k[1:-1] = ang / np.maximum(ds, 1e-12)
    return k


def wire_graph_spectrum(points_uv_px, image, *, sigma_g: float = 0.85) -> WireSpectrum:
    """The paper's weighted wire graph, its Laplacian eigenbasis and the curvature spectrum.

    Adjacency ``A[i, j] = 1`` for consecutive points (``|i - j| = 1``); weights
    ``W = A * exp(-||grad I(v_i) - grad I(v_j)||^2 / (2 sigma_g^2))`` with the gradient of the
    image normalised to [0, 1] (robust 0.5-99.5 % range), Gaussian derivative at 1 px, sampled
    bilinearly at the points; ``L = D - W = Phi Lambda Phi^T``.

    Parameters
    ----------
    points_uv_px : (N, 2) array_like of float
        Ordered wire points ``(u, v)``, N >= 2 (e.g. ``OrderedWire.points_uv_px``).
    image : (H, W) array_like
        The frame the points come from.
    sigma_g : float
        Gradient similarity bandwidth (paper: 0.85).

    Returns
    -------
    WireSpectrum

    Raises
    ------
    InputError
        Fewer than 2 points, non-finite points, bad image or ``sigma_g <= 0``.
    """
    from scipy.linalg import eigh_tridiagonal

    p = np.asarray(points_uv_px, float)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2 or not np.all(np.isfinite(p)):
        raise InputError(f"points_uv_px: expected finite (N, 2) points with N >= 2, got shape {p.shape}")
    if not (np.isfinite(sigma_g) and sigma_g > 0):
        raise InputError(f"sigma_g: expected a positive number, got {sigma_g}")
    a = as_image(image, "image")
    im01, _ = normalise01(a)
    gv = ndi.gaussian_filter(im01, 1.0, order=(1, 0))
    gu = ndi.gaussian_filter(im01, 1.0, order=(0, 1))
    coords = [p[:, 1], p[:, 0]]
    grad = np.column_stack([ndi.map_coordinates(gu, coords, order=1, mode="nearest"),
                            ndi.map_coordinates(gv, coords, order=1, mode="nearest")])
    dg = np.sum(np.diff(grad, axis=0) ** 2, axis=1)
    w = np.exp(-dg / (2.0 * sigma_g ** 2))
    deg = np.r_[w, 0.0] + np.r_[0.0, w]
    lam, phi = eigh_tridiagonal(deg, -w)
    lap = np.diag(deg) - np.diag(w, 1) - np.diag(w, -1)
    kappa = discrete_curvature(p)
    return WireSpectrum(weights=w, laplacian=lap, eigenvalues=lam, eigenvectors=phi,
                        curvature_per_px=kappa, curvature_spectrum=phi.T @ kappa, gradient=grad)
