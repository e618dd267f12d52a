"""Shared 2D image helpers of the X-ray analysis stages (:mod:`guidewire3d.xray.roadmap`,
:mod:`guidewire3d.xray.orderedwire`, :mod:`guidewire3d.xray.vessels2d_learned`,
:mod:`guidewire3d.xray.segmentation`, :mod:`guidewire3d.xray.wiremask`, :mod:`guidewire3d.app.batch2d`):
input checks, robust normalisation, polarity, the collimator's field of view and polyline normals. The
2D modules import these instead of each other's private names.

Pixel coordinates are ``(u, v) = (col, row)``.
"""
from __future__ import annotations

import numpy as np
from guidewire3d.errors import InputError
from scipy import ndimage as ndi
from skimage.color import rgb2gray
from skimage.morphology import disk

__all__ = [
    "not_dark",
    "REFERENCE_SIZE_PX",
    "as_image",
    "as_mask",
    "dark_vessels_auto",
    "field_of_view",
    "grey",
    "normalise01",
    "polyline_normals",
]

REFERENCE_SIZE_PX = 300.0         # classical 2D lengths are for an image of this size; they scale with it
BLANK_REL_SPREAD = 1e-3           # image 1-99 % spread below this x its level: blank/saturated
FOV_DARK_FRACTION = 0.25          # smoothed intensity below this x median = dark (shutter candidate)
FOV_SHUTTER_SIDE_FRACTION = 0.2   # a dark region is a collimator shutter only if it runs along an image
                                  # side over at least this fraction of the side's length, ...
FOV_SHUTTER_DEPTH_RATIO = 0.5     # ... or reaches no farther into the image than this x its border contact
FOV_FIELD_MIN_FRACTION = 0.01     # bright components at least this fraction of the image span the exposed
                                  # field (a collimated field is convex: a shutter lies outside their hull)
FOV_HULL_SHRINK = 2.0             # that hull shrunk by this x the margin (a real field's edge has dents)
BORDER_PX = 2                     # image border band ignored (edge artefacts)
FOV_MARGIN_PX = 5.0               # erosion of the field of view (edge responses)
POLARITY_TAIL_RATIO = 6.0         # dark tail >= this x the bright one: dark vessels (dark_vessels_auto)
WIDE_RADIUS_PX = 12.0             # wide top-hat radius (polarity test, width completion, search distance)


def grey(image) -> np.ndarray:
    """The image as a 2D array: single-channel stacks ``(1, H, W)`` / ``(H, W, 1)`` squeezed,
    colour ``(H, W, 3)`` / ``(H, W, 4)`` (an angiogram saved as RGB or RGBA) reduced to its
    luminance (alpha ignored); anything else is returned unchanged for the caller's check."""
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[0] == 1:
        return a[0]
    if a.ndim == 3 and a.shape[2] == 1:
        return a[..., 0]
    if a.ndim == 3 and a.shape[2] in (3, 4) and np.issubdtype(a.dtype, np.number) and min(a.shape[:2]) >= 8:
        return rgb2gray(a[..., :3])
    return a


def as_image(image, name: str) -> np.ndarray:
    """The image checked (finite, numeric, 2D, at least 8x8; colour reduced) as float64;
    :class:`InputError` naming ``name`` otherwise."""
    a = grey(image)
    if a.ndim != 2 or min(a.shape) < 8:
        raise InputError(f"{name}: expected a 2D image of at least 8x8 pixels, got shape {a.shape}")
    if a.dtype == bool:
        a = a.astype(np.float32)
    if not np.issubdtype(a.dtype, np.number):
        raise InputError(f"{name}: expected a numeric array, got dtype {a.dtype}")
    a = a.astype(np.float64, copy=False)
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name}: image contains NaN or infinite values")
    return a


def as_mask(mask, name: str) -> np.ndarray:
    """The mask checked (2D, finite) as bool (numbers: > 0.5 for floats, non-zero for integers)."""
    m = np.asarray(mask)
    if m.ndim != 2:
        raise InputError(f"{name}: expected a 2D mask, got shape {m.shape}")
    if m.dtype == bool:
        return m
    if not np.issubdtype(m.dtype, np.number):
        raise InputError(f"{name}: expected a boolean or numeric mask, got dtype {m.dtype}")
    if np.issubdtype(m.dtype, np.floating):
        if not np.all(np.isfinite(m)):
            raise InputError(f"{name}: mask contains NaN or infinite values")
        return m > 0.5
    return m != 0


def normalise01(a: np.ndarray) -> tuple[np.ndarray, bool]:
    """Robust [0, 1] normalisation; second value False if the image is flat.

    Non-negative images are divided by their 99.5 percentile (zero stays zero, so that ``-log`` is
    the attenuation); images with negative values are stretched between the 0.5 and 99.5 percentiles.
    """
    sub = a[:: max(1, a.shape[0] // 256), :: max(1, a.shape[1] // 256)]
    lo, hi = (float(x) for x in np.percentile(sub, [0.5, 99.5]))
    level = max(abs(lo), abs(hi), 1e-12)
    if hi - lo <= BLANK_REL_SPREAD * level:
        return np.zeros_like(a), False
    if lo >= 0.0:
        # Non-negative intensities (raw X-ray): keep zero as zero so that log(I) is attenuation.
        return np.clip(a / hi, 0.0, 1.0), True
    return np.clip((a - lo) / (hi - lo), 0.0, 1.0), True


def dark_vessels_auto(im01: np.ndarray, scale: float) -> bool:
    """Polarity: compare the strongest dark and bright line-sized details (black vs white top-hat
    with a disk wider than the vessels, on a subsampled copy).

    Decided first by the intensity distribution when it is one-sided: when the image's dark tail
    (median - 1st percentile) is at least ``POLARITY_TAIL_RATIO`` x its bright one (99th percentile -
    median), the vessels are dark (a subtracted aortogram: a flat background near the top of the range
    and a dense aorta far below it, whose arch encloses bright background that the top-hats would take
    for a bright vessel)."""
    sub = im01[:: max(1, im01.shape[0] // 256), :: max(1, im01.shape[1] // 256)]
    p1, med, p99 = (float(x) for x in np.percentile(sub, [1, 50, 99]))
    if med - p1 >= POLARITY_TAIL_RATIO * max(p99 - med, 1e-12):
        return True
    k = max(1, int(round(2.0 * scale)))
    small = ndi.uniform_filter(im01, size=k)[::k, ::k]
    fp = disk(max(2, int(round(WIDE_RADIUS_PX * scale / k))))
    dark = ndi.grey_closing(small, footprint=fp) - small
    bright = small - ndi.grey_opening(small, footprint=fp)
    return float(np.percentile(dark, 99.5)) >= float(np.percentile(bright, 99.5))


def not_dark(im01: np.ndarray, margin_px: int) -> np.ndarray:
    """Pixels away from every dark region (smoothed intensity at most ``FOV_DARK_FRACTION`` x the
    median, eroded by ``margin_px``) and from the image border: where a roadmap's vessel response is
    normalised. A dense aorta or ventricle is in the field of view (:func:`field_of_view`) but not
    here: its response, many times a branch's, would otherwise set the detection thresholds and
    drop the thin vessels."""
    sm = ndi.uniform_filter(im01, size=2 * margin_px + 1)
    med = float(np.median(sm))
    out = sm > FOV_DARK_FRACTION * med if med > 0 else np.ones_like(sm, bool)
    out = ndi.binary_erosion(out, iterations=margin_px, border_value=1)
    b = BORDER_PX
    out[:b] = out[-b:] = False
    out[:, :b] = out[:, -b:] = False
    return out


def field_of_view(im01: np.ndarray, margin_px: int) -> np.ndarray:
    """Pixels inside the collimator, away from the image border and dark shutter edges.

    A collimator shutter is dark (smoothed intensity at most ``FOV_DARK_FRACTION`` x the median)
    *and* enters the image from its border: a dark connected region is taken for a shutter when it
    runs along one image side over at least ``FOV_SHUTTER_SIDE_FRACTION`` of that side (a blade, an
    iris smaller than the image), or when it reaches less far into the image than it runs along the
    border (``FOV_SHUTTER_DEPTH_RATIO``: the corners an iris cuts off). Dark regions inside the image
    (a dense aorta in a subtracted aortogram, a contrast-filled ventricle) and vessels leaving the
    image (a short stretch of border, far into the image) stay in the field of view.
    """
    sm = ndi.uniform_filter(im01, size=2 * margin_px + 1)
    med = float(np.median(sm))
    fov = np.ones(sm.shape, bool)
    if med > 0:
        dark = sm <= FOV_DARK_FRACTION * med
        lab, n = ndi.label(dark) if dark.any() else (None, 0)
        if n:
            along = np.zeros((4, n + 1))
            for i, side in enumerate((lab[0], lab[-1], lab[:, 0], lab[:, -1])):
                along[i] = np.bincount(side, minlength=n + 1) / len(side)
            along[:, 0] = 0.0
            H, W = sm.shape
            rr, cc = np.ogrid[:H, :W]
            to_border = np.minimum(np.minimum(rr, H - 1 - rr), np.minimum(cc, W - 1 - cc)) + 1.0
            depth = np.zeros(n + 1)
            depth[1:] = ndi.maximum(to_border, lab, np.arange(1, n + 1))
            contact_px = along[:2].sum(0) * W + along[2:].sum(0) * H
            shallow = (contact_px > 0) & (depth <= FOV_SHUTTER_DEPTH_RATIO * contact_px)
            shutter = (along.max(0) >= FOV_SHUTTER_SIDE_FRACTION) | shallow
            shutter[0] = shallow[0] = False
            fov = ~shutter[lab]
            deep = shutter & ~shallow
            if deep.any():
                # the exposed field of a collimator (blades, iris) is convex: the pixels of a deep dark
                # region that lie inside the convex hull of the bright field (a dense aorta leaving the
                # image between bright areas on both sides of it; a vessel touching a blade) are vessel,
                # not shutter; shallow regions (blades, iris corners) stay shutters whole
                fov |= deep[lab] & _bright_field_hull(~dark, shrink_px=int(FOV_HULL_SHRINK * margin_px))
    # Erode away from the shutter edges only; the image border itself loses BORDER_PX.
    fov = ndi.binary_erosion(fov, iterations=margin_px, border_value=1)
    b = BORDER_PX
    fov[:b] = fov[-b:] = False
    fov[:, :b] = fov[:, -b:] = False
    return fov


def _bright_field_hull(bright: np.ndarray, *, shrink_px: int) -> np.ndarray:
    """Convex hull of the bright connected components of at least ``FOV_FIELD_MIN_FRACTION`` of the
    image (small bright specks in a shutter, burnt-in text, are left out), shrunk by ``shrink_px`` (a
    real field's edge is not exactly convex: its dents stay shutter); computed on a grid subsampled to
    at most 256 px a side."""
    from skimage.morphology import convex_hull_image

    k = max(1, int(np.ceil(max(bright.shape) / 256)))
    small = bright[::k, ::k]
    lab, n = ndi.label(small)
    if n == 0:
        return np.zeros(bright.shape, bool)
    size = np.bincount(lab.ravel(), minlength=n + 1)
    size[0] = 0
    keep = (size >= FOV_FIELD_MIN_FRACTION * small.size)[lab]
    if not keep.any():
        return np.zeros(bright.shape, bool)
    hull = convex_hull_image(keep)
    # shrunk (in subsampled px, at least one block: never past the bright field's own edge), then
    # back to full resolution (nearest: a pixel's value is that of its block)
    it = max(1 if k > 1 else 0, int(np.ceil(shrink_px / k)))
    if it:
        hull = ndi.binary_erosion(hull, iterations=it, border_value=1)
    full = np.repeat(np.repeat(hull, k, axis=0), k, axis=1)[: bright.shape[0], : bright.shape[1]]
    return full


def polyline_normals(p: np.ndarray) -> np.ndarray:
    """Unit normals ``(N, 2)`` of an ``(N, 2)`` polyline (tangent by central differences, rotated +90 deg)."""
    t = np.gradient(p, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    return np.column_stack([-t[:, 1], t[:, 0]])
