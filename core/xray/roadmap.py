"""Classical 2D image analysis of the roadmap: its vessels and their centerline.

Two stages of the paper's pipeline live here (DESIGN.md, "The flow of data"):

- :func:`vessel_mask` segments the vessels of any 2D angiogram (subtracted DSA or a plain,
  non-subtracted XA frame, any dtype). Steps: robust intensity normalisation, automatic
  polarity, log attenuation (Beer-Lambert: contrast becomes independent of the local
  background level), collimator / field-of-view mask, background removal by a morphological
  top-hat, multi-scale Hessian vesselness (Sato) of the top-hat, a combined feature
  ``sqrt(top-hat * vesselness)``, hysteresis thresholds relative to the feature's Otsu threshold,
  and removal of components smaller than a fixed fraction of the image or of the largest
  component (the vessel tree is connected; noise and unlabelled side branches are not), then
  growth to the full vessel width (half maximum of a wide top-hat). Vessels wider than the
  default range (a simulated aorta-sized trunk) need ``max_radius_px``: a second pass on a
  binned image. Every length scales with
  the image size (reference: 300 px), so no parameter is tuned per image.
- :func:`roadmap_centerline` skeletonises that mask and applies the paper's skeleton criteria:
  keep end points and branch points, drop spurs (terminal branches shorter than the local vessel
  width). Points carry the local radius (distance transform, px) and are centred across the
  vessel with sub-pixel precision (midpoint of the half-maximum crossings of the attenuation
  profile): a thinned skeleton cuts the inside of curves, which shrinks the 2D tree and biases
  the depth of a single-view registration.

The ordered guidewire is :mod:`guidewire3d.xray.orderedwire`.

Pixel coordinates are ``(u, v) = (col, row)``; pixel ``(0, 0)`` is the centre of the first pixel.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
from guidewire3d.errors import InputError, SegmentationError
from guidewire3d.xray.imaging import (
    BORDER_PX,
    FOV_MARGIN_PX,
    REFERENCE_SIZE_PX,
    WIDE_RADIUS_PX,
    as_image,
    as_mask,
    dark_vessels_auto,
    field_of_view,
    not_dark,
    normalise01,
)
from guidewire3d.xray.vessels2d_learned import DEFAULT_WEIGHTS_PATH, learned_vessel_mask
from scipy import ndimage as ndi

__all__ = [
    "VesselMethod",
    "vessel_mask",
    "Centerline2D",
    "roadmap_centerline",
]

# --------------------------------------------------------------------------------------------
# Vessel mask parameters (lengths in px for a REFERENCE_SIZE_PX image; they scale with the size).
BACKGROUND_RADIUS_PX = 8.0        # top-hat disk radius (must exceed the widest vessel's radius)
TOPHAT_SMOOTH_PX = 0.7            # Gaussian smoothing of the top-hat (noise)
VESSELNESS_SIGMAS_PX = (1.0, 4.0)  # smallest, largest Hessian scale
VESSELNESS_N_SCALES = 4
HYSTERESIS_LOW = 0.85             # x Otsu threshold of the feature
HYSTERESIS_HIGH = 1.5             # x Otsu threshold of the feature
MIN_COMPONENT_FRACTION = 0.001    # components smaller than this fraction of the image are dropped
MIN_COMPONENT_OF_LARGEST = 0.1    # ... and those smaller than this fraction of the largest (the tree)
FINE_MAX_RADIUS_PX = 6.0          # widest vessel radius the single-resolution pass covers
MAX_COARSE_FACTOR = 8             # largest binning of the coarse pass (see max_radius_px)
HALF_MAX = 0.5                    # fraction of the local vessel contrast at the vessel edge
WIDE_TOPHAT_FACTOR = 1.2          # wide vessels' top-hat disk: this x max_radius_px (see _wide_vessels)
WIDE_VESSELS = True                # the full-resolution pass for vessels wider than the fine pass (_wide_vessels):
                                  # it replaces the coarse pass's blocks only near the wide pieces
                                  # (_replace_coarse_by_wide; replacing whole coarse components dropped a faint
                                  # branch beside the simulator's thick trunk: bench_stress seeds 3606 and 3608)
WIDE_REPLACE_BLOCKS = 2.0         # the wide pieces replace the coarse detections within this many coarse blocks
                                  # of them (see _replace_coarse_by_wide)
WIDE_EDGE_FRACTION = 0.25         # wide vessels' edge: this x the local contrast (a tube's chord there is
                                  # sqrt(1 - 0.25^2) = 97 % of its diameter; at half maximum 87 %)


# --------------------------------------------------------------------------------------------
# Vessels
# --------------------------------------------------------------------------------------------

def _vessel_feature(a: np.ndarray, dark_vessels, scale: float | None = None):
    """Top-hat x vesselness feature in [0, ~1], the mask it was normalised on (the field of view
    outside dark regions), the field-of-view mask, the attenuation image and the length scale used
    (px per reference px)."""
    from skimage.filters import sato
    from skimage.morphology import disk

    im01, ok = normalise01(a)
    if not ok:
        return None, None, None, None, None
    if scale is None:
        scale = max(a.shape) / REFERENCE_SIZE_PX
    if dark_vessels is None:
        dark_vessels = dark_vessels_auto(im01, scale)
    if not dark_vessels:
        im01 = 1.0 - im01
    margin = max(2, int(round(FOV_MARGIN_PX * scale)))
    fov = field_of_view(im01, margin)
    if fov.sum() < 64:
        return None, None, None, None, None
    att = -np.log(im01 + 1.0 / 255.0)                  # vessels bright in attenuation
    att = np.where(fov, att, np.median(att[fov]))
    r_bg = max(2, int(round(BACKGROUND_RADIUS_PX * scale)))
    opened = ndi.grey_opening(att, footprint=disk(r_bg))
    tophat = ndi.gaussian_filter(att - opened, TOPHAT_SMOOTH_PX * max(scale, 1.0)) * fov
    sig = np.geomspace(VESSELNESS_SIGMAS_PX[0] * max(scale, 1.0), VESSELNESS_SIGMAS_PX[1] * scale,
                       VESSELNESS_N_SCALES)
    sig = np.unique(np.maximum(sig, 1.0))
    ves = sato(tophat, sigmas=sig, black_ridges=False) * fov
    # the response is normalised where the image is not dark: a dense trunk (in the field of view)
    # would otherwise set the scale and the thresholds, and the thin vessels would drop out
    stats = fov & not_dark(im01, margin)
    if stats.sum() < 64:
        stats = fov
    t99 = float(np.percentile(tophat[stats], 99))
    v99 = float(np.percentile(ves[stats], 99))
    if t99 <= 0 or v99 <= 0:
        return None, None, None, None
    feat = np.sqrt(np.clip(tophat / t99, 0, None) * np.clip(ves / v99, 0, None))
    return feat, stats, fov, att, scale


def _drop_small(mask: np.ndarray, min_px: int, connectivity: int = 2) -> np.ndarray:
    lab, n = ndi.label(mask, structure=ndi.generate_binary_structure(2, connectivity))
    if n == 0:
        return mask.copy()
    size = np.bincount(lab.ravel())
    size[0] = 0
    return (size >= min_px)[lab]


class VesselMethod(enum.Enum):
    """Vessel segmentation method of :func:`vessel_mask`.

    - ``CLASSICAL``: top-hat x multi-scale Hessian vesselness with hysteresis (this module).
    - ``LEARNED``: the small UNet of :mod:`guidewire3d.xray.vessels2d_learned`, trained on real
      non-subtracted coronary angiograms (``resources/vessel_unet.safetensors``).
    - ``AUTO``: see :func:`vessel_mask`.
    """

    CLASSICAL = "classical"
    LEARNED = "learned"
    AUTO = "auto"


def _vessel_method(method) -> VesselMethod:
    try:
        return method if isinstance(method, VesselMethod) else VesselMethod(str(method).lower())
    except ValueError:
        raise InputError(f"method: expected one of {[m.value for m in VesselMethod]}, got {method!r}") from None


def _auto_vessel_method(image, max_radius_px: float | None) -> VesselMethod:
    """The method ``AUTO`` stands for (see :func:`vessel_mask`)."""
    if max_radius_px is not None or not DEFAULT_WEIGHTS_PATH.is_file():
        return VesselMethod.CLASSICAL
    a = np.asarray(image)
    if a.dtype == bool or not np.issubdtype(a.dtype, np.number):
        return VesselMethod.CLASSICAL                  # (rejected or handled by the classical path)
    stored_pixels = np.issubdtype(a.dtype, np.integer) or bool(np.all(a == np.rint(a)))
    return VesselMethod.LEARNED if stored_pixels else VesselMethod.CLASSICAL


def vessel_mask(image, *, dark_vessels: bool | None = None, max_radius_px: float | None = None,
                method: VesselMethod | str = VesselMethod.AUTO) -> np.ndarray:
    """Segment the vessels of a 2D angiogram.

    Parameters
    ----------
    image : (H, W) array_like of numbers
        Subtracted DSA roadmap or a plain (non-subtracted) XA frame, any dtype and intensity scale.
        A colour array ``(H, W, 3)`` / ``(H, W, 4)`` (an angiogram exported as RGB) is reduced to
        its luminance.
    dark_vessels : bool or None
        ``True`` if contrast-filled vessels are darker than the background (X-ray convention),
        ``False`` if brighter; ``None`` detects the polarity (dark vs bright top-hat details).
    max_radius_px : float, optional
        Radius of the widest vessel expected, px (e.g. from the CTA and the C-arm magnification).
        ``None``: vessels up to ``FINE_MAX_RADIUS_PX`` x (image size / 300 px), typical of
        coronary angiograms. A larger value adds a second detection pass on an f-times binned
        image, ``f = ceil(max_radius_px / (FINE_MAX_RADIUS_PX x scale))`` (at most 8); the vessels
        wider than the fine pass covers (an aorta) are then outlined at full resolution, and they
        replace the binned pass's blocks near them (``WIDE_VESSELS``).
        Used by ``CLASSICAL`` only (the learned model covers coronary-sized vessels).
    method : VesselMethod or str
        ``"classical"``, ``"learned"`` or ``"auto"`` (default). ``AUTO`` is ``CLASSICAL`` when
        ``max_radius_px`` is given (the pipeline's roadmaps, vessels sized from the CTA: there the
        classical method measured better, Dice 0.886 vs 0.791 on 10 simulated roadmaps, and the
        registration was tuned on it) or when the image has non-integer values (a simulated or
        processed DSA: classical 0.796 vs learned 0.791 without ``max_radius_px``); ``LEARNED``
        for integer-valued images (stored detector pixels: 8/16-bit PNG or DICOM data, also when
        read as float), where the learned model measured better on real non-subtracted coronary
        angiograms (5-fold cross-validated Dice 0.778 vs 0.694), provided its weights file is
        present. Measurements: ``scripts/bench_vessels2d_real.py``.

    Returns
    -------
    (H, W) ndarray of bool
        Vessel pixels True. All False for a blank image or one without line structures.

    Raises
    ------
    InputError
        If ``image`` is not a finite 2D numeric array of at least 8x8 pixels, a bad
        ``max_radius_px`` or ``method``, or (``LEARNED``) a missing or unreadable weights file.
    """
    method = _vessel_method(method)
    if max_radius_px is not None and not (np.isfinite(max_radius_px) and max_radius_px > 0):
        raise InputError(f"max_radius_px: expected a positive number of pixels, got {max_radius_px!r}")
    if method is VesselMethod.AUTO:
        method = _auto_vessel_method(image, max_radius_px)
    if method is VesselMethod.LEARNED:
        return learned_vessel_mask(as_image(image, "image"), dark_vessels=dark_vessels)
    a = as_image(image, "image")
    im01, ok = normalise01(a)
    if not ok:
        return np.zeros(a.shape, bool)
    scale = max(a.shape) / REFERENCE_SIZE_PX
    if dark_vessels is None:
        dark_vessels = dark_vessels_auto(im01, scale)
    m, fov, att = _detect(a, bool(dark_vessels), scale)
    if m is None:
        return np.zeros(a.shape, bool)
    th_l = _wide_tophat(att, scale)
    f = 1
    if max_radius_px is not None:
        if not (np.isfinite(max_radius_px) and max_radius_px > 0):
            raise InputError(f"max_radius_px: expected a positive number of pixels, got {max_radius_px!r}")
        f = int(min(MAX_COARSE_FACTOR, np.ceil(max_radius_px / (FINE_MAX_RADIUS_PX * scale))))
    wide = None
    if f > 1 and min(a.shape) >= 64 * f:
        # Coarse pass: the same detector on an f-times binned image finds vessels f times wider.
        h, w = (a.shape[0] // f) * f, (a.shape[1] // f) * f
        binned = a[:h, :w].reshape(h // f, f, w // f, f).mean(axis=(1, 3))
        mc, _, _ = _detect(binned, bool(dark_vessels), scale)
        if mc is not None and mc.any():
            up = np.zeros(a.shape, bool)
            up[:h, :w] = np.repeat(np.repeat(mc, f, axis=0), f, axis=1)
            up &= fov
            wide = (_wide_vessels(att, mc, f, float(max_radius_px), fov, FINE_MAX_RADIUS_PX * scale)
                    if WIDE_VESSELS else None)
            if wide is not None:
                up = _replace_coarse_by_wide(up, wide, f, m)
                m = m | wide
            m = m | up
    # the size filter on the detections (the wide pieces among them), as without the wide pass: filtering
    # again after the width completion measured the branches against the aorta's full extent and dropped a
    # carotid group at 10 % of it (real-anatomy pose 13)
    m = _filter_components(m)
    if m.any():                                  # grow the detections to full width (FWHM)
        m = _complete_width(m, th_l, fov, scale)
    return m


def _replace_coarse_by_wide(up: np.ndarray, wide: np.ndarray, f: int, fine: np.ndarray) -> np.ndarray:
    """The coarse detections ``up`` (f x f blocks, full resolution) with those of the wide vessels
    ``wide`` replaced by the wide pieces' full-resolution extent, locally.

    f x f blocks would fill the bright background an aortic arch encloses, and a blocky outline
    puts spurs and a jagged axis in the skeleton. Removed: the coarse pixels of the components that
    touch a wide piece, within ``WIDE_REPLACE_BLOCKS`` coarse blocks of it (the coarse outline's
    reach beyond a vessel's edge: one block of binning, one of the coarse top-hat's smoothing) or in
    a hole of it (background the vessel encloses). Kept: the rest of such a component where it
    reaches at least one block beyond that band (a narrower vessel beside the wide one that only the
    coarse pass saw; less is the outline's jitter), and the coarse pixels of that band within the
    same reach of such a vessel beyond it, coarse or ``fine`` (the fine pass's detections): a
    branch's root. Without it a faint branch whose fine detection stops short of a thick trunk
    (the trunk's edge hides its end) is cut off from the tree, and dropped as a small component
    (``bench_stress`` seed 3606), where the coarse blocks had joined it.
    """
    lab, n = ndi.label(up, structure=np.ones((3, 3), bool))
    hit = np.zeros(n + 1, bool)
    hit[np.unique(lab[wide])] = True
    hit[0] = False
    touching = up & hit[lab]
    reach = WIDE_REPLACE_BLOCKS * f
    dist = ndi.distance_transform_edt(~wide)
    near = dist <= reach
    holes = ndi.binary_fill_holes(wide) & ~wide
    # what lies beyond the band, in pieces that reach at least one more block out (a vessel; a fringe's tail
    # just past the band is the outline's jitter)
    beyond = (touching | fine) & ~near & ~holes
    lab_b, n_b = ndi.label(beyond, structure=np.ones((3, 3), bool))
    if n_b:
        far = np.zeros(n_b + 1, bool)
        far[1:] = ndi.maximum(dist, lab_b, index=np.arange(1, n_b + 1)) > reach + f
        beyond = far[lab_b]
    rest = touching & beyond
    root = touching & near & ~wide & ~holes
    if beyond.any():
        root &= ndi.distance_transform_edt(~beyond) <= reach
    else:
        root[:] = False
    return (up & ~touching) | rest | root


def _wide_vessels(att: np.ndarray, mc: np.ndarray, f: int, max_radius_px: float, fov: np.ndarray,
                  min_radius_px: float) -> np.ndarray | None:
    """Full-resolution mask of the vessels wider than the fine pass covers (an aorta), from the
    coarse pass's detections ``mc`` on the ``f``-times binned grid; None if there are none.

    The vessel contrast is a white top-hat of the attenuation with a disk of
    ``WIDE_TOPHAT_FACTOR x max_radius_px`` (wider than the widest vessel, so the top-hat of a wide
    vessel is not hollow), on the binned grid; a pixel is vessel where that contrast is at least
    ``WIDE_EDGE_FRACTION`` of the largest contrast of the coarse detections within ``max_radius_px``
    (a projected tube's chord falls steeply at its edge: that fraction puts the outline at 97 % of
    the radius, where the half maximum would put it at 87 %; it also keeps a single-layer stretch
    next to one where the ascending and descending aorta overlap, about twice as dense). The
    contrast and the threshold are interpolated back to full resolution, so the outline is smooth.
    Kept: connected pieces that hold a coarse detection and are wider than ``min_radius_px`` (their
    largest inscribed radius), i.e. what the fine pass cannot resolve.
    """
    from skimage.morphology import disk

    H, W = att.shape
    h, w = mc.shape[0] * f, mc.shape[1] * f
    small = att[:h, :w].reshape(h // f, f, w // f, f).mean(axis=(1, 3))
    th = small - ndi.grey_opening(small, footprint=disk(max(2, int(round(WIDE_TOPHAT_FACTOR * max_radius_px / f)))))
    win = 2 * max(1, int(round(max_radius_px / f))) + 1
    local = ndi.maximum_filter(np.where(mc, th, 0.0), size=win)

    def full(x):
        out = np.empty((H, W))
        out[:h, :w] = ndi.zoom(x, f, order=1, grid_mode=True, mode="nearest")
        out[h:, :w] = out[h - 1:h, :w]
        out[:, w:] = out[:, w - 1:w]
        return out

    thf, locf = full(th), full(local)
    cand = fov & (locf > 0) & (thf >= WIDE_EDGE_FRACTION * locf)
    # only what discs wider than the fine pass's range cover (a morphological opening by that disc,
    # through distance transforms): thin attachments and the narrower branch roots are the fine
    # pass's business
    core = ndi.distance_transform_edt(cand) > min_radius_px
    if not core.any():
        return None
    wide = ndi.distance_transform_edt(~core) <= min_radius_px
    lab, n = ndi.label(wide, structure=np.ones((3, 3), bool))
    seeds = np.zeros((H, W), bool)
    seeds[:h, :w] = np.repeat(np.repeat(mc, f, axis=0), f, axis=1)
    keep = np.zeros(n + 1, bool)
    keep[np.unique(lab[seeds & wide])] = True
    keep[0] = False
    return keep[lab] if keep.any() else None


def _wide_tophat(att: np.ndarray, scale: float) -> np.ndarray:
    """White top-hat of the attenuation with a disk of WIDE_RADIUS_PX (computed on a subsampled
    grid, interpolated back): the local contrast of vessels up to that radius."""
    from skimage.morphology import disk

    k = max(1, int(round(2.0 * scale)))
    small = att[::k, ::k]
    r_l = max(2, int(round(WIDE_RADIUS_PX * scale / k)))
    th_l = small - ndi.grey_opening(small, footprint=disk(r_l))
    zoom = (att.shape[0] / small.shape[0], att.shape[1] / small.shape[1])
    return ndi.zoom(th_l, zoom, order=1, grid_mode=True, mode="nearest")[: att.shape[0], : att.shape[1]]


def _detect(a: np.ndarray, dark_vessels: bool, scale: float):
    """One detection pass: hysteresis on the feature (thresholds relative to its Otsu level)."""
    from skimage.filters import apply_hysteresis_threshold, threshold_otsu

    feat, stats, fov, att, _ = _vessel_feature(a, dark_vessels, scale)
    if feat is None:
        return None, None, None
    vals = feat[stats]
    if float(vals.max()) - float(vals.min()) <= 1e-9:
        return None, None, None
    t = float(threshold_otsu(vals))
    return apply_hysteresis_threshold(feat, HYSTERESIS_LOW * t, HYSTERESIS_HIGH * t), fov, att


def _filter_components(m: np.ndarray) -> np.ndarray:
    """Drop components smaller than a fraction of the image or of the largest component."""
    lab, n = ndi.label(m, structure=np.ones((3, 3), bool))
    if n == 0:
        return m
    size = np.bincount(lab.ravel())
    size[0] = 0
    keep = (size >= MIN_COMPONENT_FRACTION * m.size) & (size >= MIN_COMPONENT_OF_LARGEST * size.max())
    return keep[lab]


def _complete_width(m: np.ndarray, th_l: np.ndarray, fov: np.ndarray, scale: float) -> np.ndarray:
    """Grow the detected vessels to their full width: pixels near the mask whose wide top-hat is
    at least half of the local vessel contrast (full width at half maximum). This also fills wide
    vessels whose small-radius top-hat is hollow."""
    win = 2 * int(round(WIDE_RADIUS_PX * scale)) + 1
    local = ndi.maximum_filter(np.where(m, th_l, 0.0), size=win)
    near = ndi.binary_dilation(m, iterations=max(1, int(round(WIDE_RADIUS_PX * scale))))
    grown = near & fov & (th_l >= HALF_MAX * local) & (local > 0)
    # Keep only grown pixels connected to the detected vessels.
    lab, n = ndi.label(grown | m, structure=np.ones((3, 3), bool))
    hit = np.zeros(n + 1, bool)
    hit[np.unique(lab[m])] = True
    hit[0] = False
    return hit[lab]


# --------------------------------------------------------------------------------------------
# Skeleton helpers
# --------------------------------------------------------------------------------------------

def _neighbour_count(skel: np.ndarray) -> np.ndarray:
    k = np.ones((3, 3), np.int32)
    k[1, 1] = 0
    return ndi.convolve(skel.astype(np.int32), k, mode="constant") * skel


def _prune_spurs(skel: np.ndarray, radius: np.ndarray, *, min_spur_px: float, n_iter: int = 6) -> np.ndarray:
    """Remove terminal branches (end point to junction) shorter than max(min_spur_px, 2 x radius
    at the junction). Iterated, then re-thinned; isolated pieces are kept."""
    from skimage.morphology import skeletonize

    sk = skel.copy()
    for it in range(n_iter):
        nb = _neighbour_count(sk)
        junction = (nb >= 3) & sk
        if not junction.any():
            break
        # Cut the skeleton at the junctions: the remaining pieces are the branches.
        lab, n = ndi.label(sk & ~ndi.binary_dilation(junction, np.ones((3, 3), bool)),
                           structure=np.ones((3, 3), bool))
        if n == 0:
            break
        ends = (nb == 1) & sk
        size = np.bincount(lab.ravel(), minlength=n + 1)
        has_end = np.bincount(lab[ends], minlength=n + 1) > 0
        # A branch touching a junction neighbourhood (not an isolated piece).
        near_j = ndi.binary_dilation(junction, np.ones((5, 5), bool))
        touches = np.bincount(lab[near_j & (lab > 0)], minlength=n + 1) > 0
        rmax = ndi.maximum(radius, lab, index=np.arange(n + 1)) if n else np.zeros(1)
        rmax = np.asarray(rmax, float)
        # Radius at the parent junction ~ the largest radius of the branch's neighbourhood.
        thresh = np.maximum(min_spur_px, 2.0 * rmax)
        # One pass of spur removal (no cascade into the branches the spurs hung from), then
        # only the leftover stubs inside junction neighbourhoods.
        spur = has_end & touches & (size < thresh) & (it == 0)
        spur[0] = False
        stub = ends & (lab == 0)                   # end pixels inside a junction's neighbourhood
        if not spur.any() and not stub.any():
            break
        sk = sk & ~spur[lab] & ~stub
        sk = skeletonize(sk)
    return sk


def _trim_wide_ends_at_border(skel: np.ndarray, radius: np.ndarray, *, wide_px: float, border_px: int) -> np.ndarray:
    """Trim the skeleton's ends near the image border on vessels wider than ``wide_px``.

    A wide vessel that leaves the image is cut square by the field of view; the medial axis of a square
    end bends into one of its corners (a hook up to a radius long, off the vessel's axis). End pixels
    closer to the image border than the local vessel radius (the largest skeleton radius within
    ``wide_px`` of the end) plus ``border_px`` are removed, repeatedly, where that radius exceeds
    ``wide_px``; thinner vessels keep their ends.
    """
    H, W = skel.shape
    rr, cc = np.ogrid[:H, :W]
    to_border = np.minimum(np.minimum(rr, H - 1 - rr), np.minimum(cc, W - 1 - cc)).astype(float)
    r_loc = ndi.maximum_filter(np.where(skel, radius, 0.0), size=2 * int(np.ceil(wide_px)) + 1)
    zone = skel & (r_loc > wide_px) & (to_border < r_loc + border_px)
    if not zone.any():
        return skel
    sk = skel.copy()
    for _ in range(int(np.ceil(float(r_loc[zone].max()))) + border_px + int(np.ceil(wide_px))):
        ends = (_neighbour_count(sk) == 1) & sk & zone
        if not ends.any():
            break
        sk &= ~ends
    return sk


# Sub-pixel centring of the roadmap centerline (see _centre_across).
CENTRE_SMOOTH_PX = 0.7            # Gaussian smoothing of the attenuation image (noise)
CENTRE_STEP_PX = 0.25             # profile sampling step across the vessel
CENTRE_MARGIN_PX = 4.0            # profile reaches this far beyond the local mask radius
CENTRE_TANGENT_K = 9              # skeleton neighbours of the local tangent (PCA)
CENTRE_MAX_HALF_WIDTH = 2.0       # a half-width above this x radius + 2 px: merged with a neighbour


def _attenuation(a: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Smoothed attenuation ``-log(I)`` with the vessels bright, polarity from the mask (vessel
    pixels darker or brighter than their surroundings)."""
    im01, ok = normalise01(a)
    if not ok:
        return np.zeros_like(a)
    ring = ndi.binary_dilation(mask, iterations=3) & ~mask
    if ring.any() and float(np.mean(im01[mask])) > float(np.mean(im01[ring])):
        im01 = 1.0 - im01                              # bright vessels
    return ndi.gaussian_filter(-np.log(im01 + 1.0 / 255.0), CENTRE_SMOOTH_PX)


def _centre_across(att: np.ndarray, skel_uv: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Move skeleton points to the centre of the vessel's intensity profile across the vessel.

    A thinned skeleton of a curved vessel lies slightly inside the curve (and is quantised to
    pixels), which shrinks the 2D tree by a fraction of a per cent: in a single-view registration
    that is a depth error of millimetres. Here each point is moved along the normal of the local
    skeleton direction to the midpoint of the two half-maximum crossings of the attenuation
    profile (background = the mean of the profile's outer minima on both sides): the full width at half
    maximum is symmetric about the axis of a projected tube, straight or curved. Points whose
    profile is not a single isolated peak (junctions, touching or crossing vessels, the image
    border) keep their skeleton position.

    Parameters
    ----------
    att : (H, W) ndarray
        Attenuation image, vessels bright.
    skel_uv : (M, 2) ndarray
        Skeleton pixel centres ``(u, v)``.
    radius : (M,) ndarray
        Mask radius at each point (px).

    Returns
    -------
    (M, 2) ndarray
        Centred points.
    """
    n_pts = len(skel_uv)
    if n_pts < 3:
        return skel_uv.copy()
    from scipy.spatial import cKDTree

    k = int(min(CENTRE_TANGENT_K, n_pts))
    _, idx = cKDTree(skel_uv).query(skel_uv, k=k)
    nb = skel_uv[idx] - skel_uv[idx].mean(axis=1, keepdims=True)
    _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    t = vec[:, :, -1]
    nrm = np.column_stack([-t[:, 1], t[:, 0]])
    reach = np.maximum(radius, 1.0) + CENTRE_MARGIN_PX
    s = np.arange(-np.ceil(reach.max()), np.ceil(reach.max()) + 1e-9, CENTRE_STEP_PX)
    P = skel_uv[:, None, :] + s[None, :, None] * nrm[:, None, :]
    prof = ndi.map_coordinates(att, [P[..., 1].ravel(), P[..., 0].ravel()], order=1, mode="nearest")
    prof = prof.reshape(P.shape[:2])
    inside = np.abs(s)[None, :] <= reach[:, None]
    i = np.arange(n_pts)
    col = np.arange(len(s))[None, :]
    c = len(s) // 2
    # the peak near the skeleton point; the background on each side
    ip = np.argmax(np.where(np.abs(s)[None, :] <= np.maximum(radius, 1.0)[:, None], prof, -np.inf), axis=1)
    peak = prof[i, ip]
    left_min = np.min(np.where(inside & (col < ip[:, None]), prof, np.inf), axis=1)
    right_min = np.min(np.where(inside & (col > ip[:, None]), prof, np.inf), axis=1)
    base = 0.5 * (left_min + right_min)
    level = 0.5 * (peak + base)
    below = (prof < level[:, None]) & inside
    rmask = below & (col > ip[:, None])
    lmask = below & (col < ip[:, None])
    ok = rmask.any(axis=1) & lmask.any(axis=1) & np.isfinite(base) & (peak > base)
    ir = np.clip(np.where(ok, np.argmax(rmask, axis=1), c + 1), 1, len(s) - 1)
    il = np.clip(np.where(ok, len(s) - 1 - np.argmax(lmask[:, ::-1], axis=1), c - 1), 0, len(s) - 2)

    def crossing(a_idx, b_idx):
        pa, pb = prof[i, a_idx], prof[i, b_idx]
        d = pa - pb
        f = np.clip((pa - level) / np.where(np.abs(d) < 1e-12, 1.0, d), 0.0, 1.0)
        return s[a_idx] + f * (s[b_idx] - s[a_idx])

    s_r, s_l = crossing(ir - 1, ir), crossing(il + 1, il)
    mid, half = 0.5 * (s_r + s_l), 0.5 * (s_r - s_l)
    ok &= (np.abs(mid) <= np.maximum(1.0, 0.5 * radius)) & (half <= CENTRE_MAX_HALF_WIDTH * radius + 2.0)
    out = skel_uv.copy()
    out[ok] += mid[ok, None] * nrm[ok]
    return out


@dataclass(frozen=True, eq=False)
class Centerline2D:
    """2D vessel centerline of a roadmap.

    Attributes
    ----------
    points_uv_px : (M, 2) ndarray of float
        Centerline points ``(u, v) = (col, row)``, one per skeleton pixel (after spur removal),
        moved across the vessel to the centre of its intensity profile (sub-pixel). Points where the profile is not one isolated vessel (junctions,
        touching vessels) stay at their skeleton pixel centre.
    radius_px : (M,) ndarray of float
        Local vessel radius (Euclidean distance transform of the mask at the skeleton pixel), px.
    mask : (H, W) ndarray of bool
        Vessel mask the centerline was taken from.
    skeleton : (H, W) ndarray of bool
        One-pixel-wide skeleton (the pixels ``points_uv_px`` were centred from).
    endpoints_uv_px : (K, 2) ndarray of float
        Skeleton end points (one neighbour).
    branchpoints_uv_px : (L, 2) ndarray of float
        Branch points (three or more neighbours; adjacent junction pixels merged to their centroid).
    """

    points_uv_px: np.ndarray
    radius_px: np.ndarray
    mask: np.ndarray
    skeleton: np.ndarray
    endpoints_uv_px: np.ndarray
    branchpoints_uv_px: np.ndarray

    @property
    def n_points(self) -> int:
        return int(len(self.points_uv_px))


def roadmap_centerline(image, *, mask=None, max_radius_px: float | None = None) -> Centerline2D:
    """Vessel centerline (skeleton with local radius) of a roadmap image.

    The skeleton of the vessel mask gives the topology (end and branch points, one point per
    skeleton pixel); each point is then moved across the vessel to the midpoint of the
    half-maximum crossings of the image's attenuation profile (:func:`_centre_across`), so the
    points are unbiased on curved vessels (measured on 30 ``guidewire3d bench`` roadmaps: mean
    distance to the projected true centerline 0.73 -> 0.42 px, 2D scale error 1.4 -> 0.1 per
    mille, which single-view registration turns into depth error).

    Parameters
    ----------
    image : (H, W) array_like
        Contrast XA frame (subtracted DSA or not); its intensities centre the points.
    mask : (H, W) array_like of bool, optional
        Vessel mask to use instead of :func:`vessel_mask` of ``image``.
    max_radius_px : float, optional
        Passed to :func:`vessel_mask` (widest expected vessel radius, px) when ``mask`` is None.

    Returns
    -------
    Centerline2D

    Raises
    ------
    InputError
        Bad image or a mask of another shape.
    SegmentationError
        If no vessels are found.
    """
    from skimage.morphology import skeletonize

    a = as_image(image, "image")
    if mask is None:
        m = vessel_mask(a, max_radius_px=max_radius_px)
    else:
        m = as_mask(mask, "mask")
        if m.shape != a.shape:
            raise InputError(f"mask: shape {m.shape} differs from the image's {a.shape}")
        m = m.copy()
    if not m.any():
        raise SegmentationError("roadmap_centerline: no vessels found in the image")
    # Fill pin holes so that the skeleton has no small loops.
    holes = ndi.binary_fill_holes(m) & ~m
    m = m | (holes & ~_drop_small(holes, 16, connectivity=1))
    radius = ndi.distance_transform_edt(m)
    scale = max(a.shape) / REFERENCE_SIZE_PX
    skel = skeletonize(m)
    skel = _prune_spurs(skel, radius, min_spur_px=max(4.0, 4.0 * scale))
    skel = _trim_wide_ends_at_border(skel, radius, wide_px=FINE_MAX_RADIUS_PX * scale,
                                     border_px=BORDER_PX + max(2, int(round(FOV_MARGIN_PX * scale))))
    if not skel.any():
        raise SegmentationError("roadmap_centerline: the vessel mask has an empty skeleton")
    nb = _neighbour_count(skel)
    rr, cc = np.nonzero(skel)
    er, ec = np.nonzero((nb == 1) & skel)
    jl, nj = ndi.label((nb >= 3) & skel, structure=np.ones((3, 3), bool))
    if nj:
        cen = np.asarray(ndi.center_of_mass(np.ones_like(jl), jl, np.arange(1, nj + 1)), float)
        branch = cen[:, ::-1]
    else:
        branch = np.zeros((0, 2))
    pts = np.column_stack([cc, rr]).astype(float)
    rad = radius[rr, cc].astype(float)
    pts = _centre_across(_attenuation(a, m), pts, rad)
    return Centerline2D(
        points_uv_px=pts,
        radius_px=rad,
        mask=m,
        skeleton=skel,
        endpoints_uv_px=np.column_stack([ec, er]).astype(float),
        branchpoints_uv_px=branch,
    )
