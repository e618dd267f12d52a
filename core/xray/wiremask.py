"""Model-based guidewire mask: the ordered sub-pixel wire rendered as a tube.

A pixel classifier cannot place the edge of a 1-2 px wide wire: whether a border pixel is
"wire" depends on where the wire's centre lies inside the pixel, to a tenth of a pixel. The
ordered wire (:func:`guidewire3d.xray.orderedwire.ordered_wire`) does know that (its centre line is
within ~0.1 px of the truth on the simulator's frames), so this module draws the mask from it:

- :func:`render_wire_mask`: the pixels of which at least ``COVER_FRACTION`` of the area lies
  within ``radius_px`` of the centre polyline and not beyond its ends (a tube cut flat at both
  ends; estimated on a ``SUBSAMPLE`` x ``SUBSAMPLE`` grid of points per pixel), plus every pixel
  the centre line passes through (a wire always marks the pixels it crosses). This is a
  partial-volume mask of the projected tube.
- :func:`wire_radius_px`: the tube radius whose rendered mask has the same median width across
  the wire as a given (soft) segmentation, measured along the normals of the wire. The median
  ignores where the wire runs inside a catheter or crosses other dark structures.
- :func:`projected_wire_radius_px`: the radius from what is known about the wire and the C-arm
  (the wire's diameter, e.g. 0.014" = 0.36 mm, magnified by SID / SOD for a wire near the
  isocentre, over the detector's pixel spacing): better than the estimate for 1-2 px wires, whose
  width the network (and the blurred image) barely shows.
- :func:`model_wire_mask`: both together; the parts of the segmentation that lie away from the
  rendered tube and are large (a second stretch of a looped wire that the single ordered path
  does not follow) are kept as segmented.

Used by ``guidewire_mask(frame, wire_model=True)`` and ``GuidewireSegmenter(wire_model=True)``
(:mod:`guidewire3d.xray.segmentation`). The live path does not need it: it traces the ordered wire in
the pixel mask and reconstructs from that; the rendered mask is for those who want the 2D mask
itself (display, export, evaluation).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from guidewire3d.errors import InputError
from guidewire3d.metrics import resample_polyline
from guidewire3d.xray.imaging import polyline_normals
from scipy import ndimage as ndi

__all__ = [
    "COVER_FRACTION",
    "render_wire_mask",
    "wire_width_profile_px",
    "wire_radius_px",
    "WireMaskResult",
    "model_wire_mask",
    "projected_wire_radius_px",
]

COVER_FRACTION = 0.34      # a pixel is wire if at least this fraction of its area is inside the tube
SUBSAMPLE = 3              # points per pixel side for the covered fraction
DENSE_STEP_PX = 0.2        # centre-line sampling for the distances (error <= step^2 / (8 r))
WIDTH_HALF_RANGE_PX = 6.0  # cross-wire profile: +- this far from the centre line
WIDTH_STEP_PX = 0.25       # and sampled at this step
WIDTH_SPACING_PX = 2.0     # profiles every this many px along the wire
WIDTH_END_SKIP = 3         # profiles skipped at each end (end caps)
RADIUS_RANGE_PX = (0.3, 6.0)   # search range of the tube radius
RADIUS_TOL_PX = 0.005          # bisection stops at this bracket width
RESIDUAL_MIN_PX = 30       # segmented components away from the tube kept if at least this large
RESIDUAL_GAP_PX = 2        # ... "away" = beyond ceil(radius) + this of the rendered tube


def _polyline(points_uv_px, name: str = "points_uv_px") -> np.ndarray:
    p = np.asarray(points_uv_px, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2:
        raise InputError(f"{name}: expected an (N >= 2, 2) array of (u, v) px, got shape {p.shape}")
    if not np.isfinite(p).all():
        raise InputError(f"{name}: contains NaN or infinite values")
    if not np.any(np.linalg.norm(np.diff(p, axis=0), axis=1) > 0):
        raise InputError(f"{name}: all points coincide (a polyline of zero length)")
    return p


def check_radius_px(value, name: str = "radius_px") -> float:
    """``value`` as a finite radius > 0 px, else an InputError naming ``name``."""
    try:
        r = float(value)
    except (TypeError, ValueError):
        r = float("nan")
    if not np.isfinite(r) or r <= 0:
        raise InputError(f"{name}: expected a finite radius > 0 px, got {value!r}")
    return r


def _shape(shape) -> tuple[int, int]:
    try:
        h, w = (int(x) for x in shape)
    except (TypeError, ValueError):
        raise InputError(f"shape: expected (H, W), got {shape!r}") from None
    if h < 1 or w < 1:
        raise InputError(f"shape: expected positive (H, W), got {shape!r}")
    return h, w


def _dense(p: np.ndarray, step_px: float) -> np.ndarray:
    return resample_polyline(p, step_px)


def _centre_pixels(dense: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    h, w = shape
    ij = np.rint(dense).astype(int)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    m = np.zeros(shape, bool)
    m[ij[ok, 1], ij[ok, 0]] = True
    return m


@dataclass(frozen=True, eq=False)
class _Coverage:
    """Pixels near a polyline and the distances of their sub-pixel samples to it, for rendering
    tubes of radii in ``[r_min, r_max]``: ``inside`` pixels lie wholly within ``r_min``; the
    ``ring`` pixels have their samples' distances in ``dist_px``."""

    inside_rows: np.ndarray   # (I,) int
    inside_cols: np.ndarray   # (I,) int
    rows: np.ndarray          # (K,) int
    cols: np.ndarray          # (K,) int
    dist_px: np.ndarray       # (K, SUBSAMPLE**2) float
    centre: np.ndarray        # (H, W) bool: pixels the centre line passes through

    def render(self, radius_px: float) -> np.ndarray:
        m = self.centre.copy()
        m[self.inside_rows, self.inside_cols] = True
        frac = (self.dist_px <= radius_px).mean(axis=1)
        on = frac >= COVER_FRACTION
        m[self.rows[on], self.cols[on]] = True
        return m


HALF_DIAGONAL_PX = 0.5 * np.sqrt(2.0)


def _beyond_ends(q: np.ndarray, idx: np.ndarray, dense: np.ndarray) -> np.ndarray:
    """Points whose nearest centre-line sample is an end point and which lie beyond it along the
    end's tangent (outside the flat cut of the wire's end)."""
    out = np.zeros(len(q), bool)
    for end, nb in ((0, 1), (len(dense) - 1, len(dense) - 2)):
        sel = idx == end
        if not sel.any():
            continue
        t = dense[end] - dense[nb]
        t = t / max(float(np.linalg.norm(t)), 1e-12)
        out[sel] = (q[sel] - dense[end]) @ t > 1e-9
    return out


def _coverage(p: np.ndarray, shape: tuple[int, int], r_max_px: float, r_min_px: float | None = None) -> _Coverage:
    import cv2
    from scipy.spatial import cKDTree

    r_min_px = RADIUS_RANGE_PX[0] if r_min_px is None else r_min_px
    dense = _dense(p, DENSE_STEP_PX)
    tree = cKDTree(dense)
    centre = _centre_pixels(dense, shape)
    # every pixel whose area can reach the tube: centre pixels dilated by ceil(r) + 1
    k = int(np.ceil(r_max_px)) + 1
    se = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * k + 1, 2 * k + 1))
    rows, cols = np.nonzero(cv2.dilate(centre.astype(np.uint8), se))
    pc = np.column_stack([cols, rows]).astype(float)
    d_centre, i_centre = tree.query(pc) if len(pc) else (np.zeros(0), np.zeros(0, int))
    at_end = (i_centre == 0) | (i_centre == len(dense) - 1)
    inside = (d_centre <= r_min_px - HALF_DIAGONAL_PX) & ~at_end
    ring = ~inside & (d_centre <= r_max_px + HALF_DIAGONAL_PX)
    rr, cc = rows[ring], cols[ring]
    off = (np.arange(SUBSAMPLE) + 0.5) / SUBSAMPLE - 0.5
    du, dv = np.meshgrid(off, off)
    q = np.column_stack([(cc[:, None] + du.ravel()).ravel(), (rr[:, None] + dv.ravel()).ravel()])
    if len(q):
        d, i = tree.query(q)
        d[_beyond_ends(q, i, dense)] = np.inf     # the wire ends in a flat cut, not a round cap
    else:
        d = np.zeros(0)
    return _Coverage(rows[inside], cols[inside], rr, cc, d.reshape(len(rr), SUBSAMPLE * SUBSAMPLE), centre)


def render_wire_mask(points_uv_px, radius_px: float, shape) -> np.ndarray:
    """Partial-volume mask of a tube of ``radius_px`` around a 2D polyline.

    Parameters
    ----------
    points_uv_px : (N, 2) array_like of float
        Ordered centre line, ``(u, v)`` px (``u`` column, ``v`` row; pixel centres at integers).
    radius_px : float
        Tube radius, px (> 0).
    shape : (H, W)
        Output shape.

    Returns
    -------
    (H, W) ndarray of bool
        Pixels of which at least ``COVER_FRACTION`` of the area (``SUBSAMPLE``\\ :sup:`2` samples)
        lies within ``radius_px`` of the polyline (cut flat at its ends), and the pixels the
        polyline passes through.
        The simulator's truth mask of a projected wire follows the same rule.

    Raises
    ------
    InputError
        Bad polyline, radius or shape.
    """
    p = _polyline(points_uv_px)
    hw = _shape(shape)
    r = check_radius_px(radius_px)
    return _coverage(p, hw, r, r).render(r)


def _profile_points(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points every WIDTH_SPACING_PX along the wire (ends skipped) and their unit normals."""
    q = _dense(p, WIDTH_SPACING_PX)
    if len(q) > 2 * WIDTH_END_SKIP + 3:
        q = q[WIDTH_END_SKIP:-WIDTH_END_SKIP]
    # normals from the finer polyline (smoother than the 2 px resampling)
    fine = _dense(p, 0.5)
    n_fine = polyline_normals(ndi.gaussian_filter1d(fine, 2.0, axis=0, mode="nearest"))
    from scipy.spatial import cKDTree

    idx = cKDTree(fine).query(q)[1]
    return q, n_fine[idx]


def wire_width_profile_px(seg, points_uv_px) -> np.ndarray:
    """Width of a (soft) wire segmentation across the wire, at profiles every
    ``WIDTH_SPACING_PX`` along it (``WIDTH_END_SKIP`` skipped at each end).

    Parameters
    ----------
    seg : (H, W) array_like of bool or float in [0, 1]
        Mask or probability map.
    points_uv_px : (N, 2) array_like of float
        Ordered wire centre line, ``(u, v)`` px.

    Returns
    -------
    (M,) ndarray of float
        Per profile: the summed segmentation within ``WIDTH_HALF_RANGE_PX`` of the centre line
        along the normal, times the sampling step (px): the width of a binary mask, the expected
        width of a probability map.
    """
    s = np.asarray(seg)
    if s.ndim != 2:
        raise InputError(f"seg: expected a 2D mask or probability map, got shape {s.shape}")
    return _widths(s, _profile_samples(_polyline(points_uv_px)))


def _profile_samples(p: np.ndarray) -> np.ndarray:
    """(2, M, K) (row, col) sample coordinates of the cross-wire profiles."""
    q, n = _profile_points(p)
    offs = np.arange(-WIDTH_HALF_RANGE_PX, WIDTH_HALF_RANGE_PX + 1e-9, WIDTH_STEP_PX)
    pts = q[:, None, :] + offs[None, :, None] * n[:, None, :]
    return np.stack([pts[..., 1], pts[..., 0]])


def _widths(s: np.ndarray, samples: np.ndarray) -> np.ndarray:
    v = ndi.map_coordinates(s.astype(np.float32), samples.reshape(2, -1), order=1, mode="constant", cval=0.0)
    return v.reshape(samples.shape[1:]).sum(axis=1) * WIDTH_STEP_PX


def _radius_bound_px(target_width_px: float) -> float:
    """Upper end of the radius search: a rendered tube's mask is about 2 r + 0.3 px wide."""
    return float(np.clip(0.5 * target_width_px + 1.0, RADIUS_RANGE_PX[0] + 2 * RADIUS_TOL_PX, RADIUS_RANGE_PX[1]))


def _match_radius(cov: _Coverage, target_width_px: float, samples: np.ndarray) -> float:
    lo, hi = RADIUS_RANGE_PX[0], _radius_bound_px(target_width_px)
    while hi - lo > RADIUS_TOL_PX:
        mid = 0.5 * (lo + hi)
        if np.median(_widths(cov.render(mid), samples)) < target_width_px:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def wire_radius_px(seg, points_uv_px) -> float:
    """Radius of the tube whose rendered mask (:func:`render_wire_mask`) has the same median width
    across the wire as ``seg`` (:func:`wire_width_profile_px`).

    Parameters
    ----------
    seg : (H, W) array_like of bool or float in [0, 1]
        The segmentation the wire was traced in (mask or probability map).
    points_uv_px : (N, 2) array_like of float
        Its ordered centre line, ``(u, v)`` px.

    Returns
    -------
    float
        Radius in px, within ``RADIUS_RANGE_PX``.
    """
    s = np.asarray(seg)
    p = _polyline(points_uv_px)
    if s.ndim != 2:
        raise InputError(f"seg: expected a 2D mask or probability map, got shape {s.shape}")
    samples = _profile_samples(p)
    target = float(np.median(_widths(s, samples)))
    return _match_radius(_coverage(p, s.shape, _radius_bound_px(target)), target, samples)


@dataclass(frozen=True, eq=False)
class WireMaskResult:
    """A model-based wire mask.

    Attributes
    ----------
    mask : (H, W) ndarray of bool
        The rendered tube, plus the large segmented parts away from it.
    radius_px : float
        Tube radius, px.
    tube : (H, W) ndarray of bool
        The rendered tube alone.
    """

    mask: np.ndarray
    radius_px: float
    tube: np.ndarray


def model_wire_mask(seg, points_uv_px, *, width_seg=None, radius_px: float | None = None) -> WireMaskResult:
    """Mask of a guidewire rendered from its ordered centre line.

    Parameters
    ----------
    seg : (H, W) array_like of bool
        The binary segmentation the wire was traced in.
    points_uv_px : (N, 2) array_like of float
        The ordered sub-pixel centre line (:func:`guidewire3d.xray.orderedwire.ordered_wire`).
    width_seg : (H, W) array_like of float, optional
        Segmentation whose width sets the radius (e.g. the network's probability map); ``seg``
        if omitted.
    radius_px : float, optional
        The wire's radius in px when it is known (the wire's diameter and the C-arm's
        magnification, :func:`projected_wire_radius_px`); estimated from the segmentation if omitted.

    Returns
    -------
    WireMaskResult
        ``mask`` = the tube of radius :func:`wire_radius_px` around the centre line, plus the
        components of ``seg`` that lie beyond ``ceil(radius) + RESIDUAL_GAP_PX`` of the tube and
        have at least ``RESIDUAL_MIN_PX`` pixels.
    """
    import cv2

    m = np.asarray(seg)
    if m.ndim != 2:
        raise InputError(f"seg: expected a 2D mask, got shape {m.shape}")
    m = m.astype(bool)
    ws = m if width_seg is None else np.asarray(width_seg)
    if ws.shape != m.shape:
        raise InputError(f"width_seg: shape {ws.shape} differs from the mask's {m.shape}")
    p = _polyline(points_uv_px)
    if radius_px is None:
        samples = _profile_samples(p)
        target = float(np.median(_widths(ws, samples)))
        cov = _coverage(p, m.shape, _radius_bound_px(target))
        r = _match_radius(cov, target, samples)
    else:
        r = check_radius_px(radius_px)
        cov = _coverage(p, m.shape, r, r)
    tube = cov.render(r)
    k = int(np.ceil(r)) + RESIDUAL_GAP_PX
    near = cv2.dilate(tube.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))) > 0
    rest = m & ~near
    out = tube.copy()
    if rest.any():
        lab, n = ndi.label(rest, structure=np.ones((3, 3)))
        sizes = np.bincount(lab.ravel(), minlength=n + 1)
        keep = sizes >= RESIDUAL_MIN_PX
        keep[0] = False
        out |= keep[lab]
    return WireMaskResult(mask=out, radius_px=float(r), tube=tube)


def projected_wire_radius_px(carm, wire_diameter_mm: float) -> float:
    """Radius in detector pixels of a wire of ``wire_diameter_mm`` at the C-arm's isocentre.

    Parameters
    ----------
    carm : guidewire3d.geometry.CArm
        The view (``sid_mm``, ``sod_mm``, ``pixel_mm`` from the XA tags).
    wire_diameter_mm : float
        The guidewire's diameter (0.014" = 0.36 mm, 0.035" = 0.89 mm).

    Returns
    -------
    float
        ``0.5 * wire_diameter_mm * sid_mm / sod_mm / pixel_mm``. A wire 5 cm off the isocentre
        along the beam is ~7 % larger or smaller.
    """
    d = float(wire_diameter_mm)
    if not np.isfinite(d) or d <= 0:
        raise InputError(f"wire_diameter_mm: expected a finite diameter > 0 mm, got {wire_diameter_mm!r}")
    return 0.5 * d * float(carm.sid_mm) / float(carm.sod_mm) / float(carm.pixel_mm)
