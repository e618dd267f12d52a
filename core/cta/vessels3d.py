"""CTA vessels: segmentation mask, surface mesh and centerline graph (issue 4).

Three stages, each a pure function on arrays in a module of its own, chained by :func:`extract_vessels`:

1. :func:`guidewire3d.cta.segment.segment_vessels` - the lumen mask (HU window, local half-maximum
   threshold, bone and blob rejection, multi-scale Frangi vesselness, the tubular component).
2. :func:`guidewire3d.cta.surface.surface_from_mask` - a closed triangle mesh in LPS mm.
3. :func:`guidewire3d.cta.centerline.centerline_from_mask` - the paper's distance-transform ridge
   centerline, a :class:`~guidewire3d.vesseltree.VesselTree` with radii.

Volumes are indexed ``(z, y, x)``; ``spacing_mm`` and ``origin_lps_mm`` are ``(x, y, z)`` as in
SimpleITK and :class:`guidewire3d.io.Volume`; ``direction`` columns are the x, y, z index axes in LPS.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage as ndi

from guidewire3d import io
from guidewire3d.errors import SegmentationError
from guidewire3d.cta.centerline import CenterlineOptions, centerline_from_mask
from guidewire3d.cta.segment import VesselOptions, segment_vessels
from guidewire3d.cta.surface import surface_from_mask
from guidewire3d.vesseltree import VesselTree

__all__ = ["CTAVessels", "SeedsApartError", "extract_vessels"]


class SeedsApartError(SegmentationError):
    """A seed lies in a vessel structure apart from the first seed's: one connected tree cannot hold them all.
    ``which`` names the first such seed in a few words."""

    def __init__(self, message: str, which: str = ""):
        super().__init__(message)
        self.which = which


@dataclass(frozen=True, eq=False)
class CTAVessels:
    """Everything the vessel stage produces for one CTA."""

    mask_zyx: np.ndarray  # (z, y, x) bool, same grid as the input volume
    surface: object  # vtkPolyData, triangles with normals, LPS mm
    tree: VesselTree  # centerline graph, LPS mm
    seconds: dict = field(default_factory=dict)  # stage -> wall seconds (surface and centerline run side by side)
    # LPS mm: regions deeper than the widest vessel cut as heart chambers though a vessel may run through them
    # (``segment_vessels``' record): the tree may stop there
    cut_through_lps_mm: tuple = ()


def extract_vessels(volume: io.Volume, *, seeds_lps_mm=None, progress: bool = False,
                    options: VesselOptions | None = None,
                    centerline_options: CenterlineOptions | None = None,
                    wide_radius_mm: float | None = None) -> CTAVessels:
    """Segmentation, surface and centerline graph of a CTA, with stage timings.

    Parameters
    ----------
    volume : io.Volume
        CT in HU.
    seeds_lps_mm : (K, 3) array_like of float, optional
        Points in the vessels; the first also picks the centerline root.
    progress : bool
        tqdm bars per stage.
    wide_radius_mm : float, optional
        The widest vessel the caller takes, when ``options`` expect narrower ones: see
        :func:`guidewire3d.cta.segment.segment_vessels`.

    Returns
    -------
    CTAVessels

    Notes
    -----
    The stages run on the array in its own order: the centerline's thinning follows it, so the same physical
    volume stored in another axis order gives a slightly different tree. The automatic path
    (:func:`guidewire3d.cta.vesselmodel.extract_vessels_auto`) lays the volume out in a canonical order first;
    this HU path does not, so that the simulator's coronary benchmark (identity layout) keeps its measurements.
    """
    secs = {}
    t_start = t0 = time.perf_counter()
    record = {}
    mask = segment_vessels(volume, seeds_lps_mm=seeds_lps_mm, progress=progress, options=options, record=record,
                           wide_radius_mm=wide_radius_mm)
    secs["segment"] = time.perf_counter() - t0
    mask.setflags(write=False)
    if seeds_lps_mm is not None:
        _check_seeds_connected(volume, mask, np.atleast_2d(np.asarray(seeds_lps_mm, dtype=float)))
    kw = dict(spacing_mm=volume.spacing_mm, origin_lps_mm=volume.origin_lps_mm, direction=volume.direction)

    def surface():
        t = time.perf_counter()
        out = surface_from_mask(mask, **kw)
        return out, time.perf_counter() - t

    # the surface (VTK, which releases the GIL) is built in a thread beside the centerline (numpy)
    with ThreadPoolExecutor(1) as ex:
        fut = ex.submit(surface)
        t0 = time.perf_counter()
        seed = None if seeds_lps_mm is None else np.atleast_2d(np.asarray(seeds_lps_mm, dtype=float))[0]
        tree = centerline_from_mask(mask, **kw, seed_lps_mm=seed, options=centerline_options, progress=progress)
        secs["centerline"] = time.perf_counter() - t0
        surf, secs["surface"] = fut.result()
    secs["total"] = time.perf_counter() - t_start
    return CTAVessels(mask_zyx=mask, surface=surf, tree=tree, seconds=secs,
                      cut_through_lps_mm=tuple(record.get("cut_through_lps_mm", ())))


def _check_seeds_connected(volume: io.Volume, mask_zyx: np.ndarray, seeds_lps_mm: np.ndarray) -> None:
    """SegmentationError when a seed's nearest mask voxel is not in the first seed's connected structure.

    The tree is one connected structure, that of the first seed (:func:`centerline_from_mask`). A second seed in a
    separate one (the other carotid system of a head whose circle of Willis is broken at the threshold, a vein) had
    its lumen in the mask and the surface but not in the tree, and nothing said so.
    """
    if len(seeds_lps_mm) < 2 or not mask_zyx.any():
        return
    lab, n = ndi.label(mask_zyx, structure=np.ones((3, 3, 3)))
    if n < 2:
        return
    vox = np.argwhere(mask_zyx)
    sp_zyx = np.asarray(volume.spacing_mm, dtype=float)[::-1]
    idx = volume.lps_to_index_zyx(seeds_lps_mm)
    near = [vox[int(np.argmin(np.linalg.norm((vox - i) * sp_zyx, axis=1)))] for i in idx]
    labels = [int(lab[tuple(v)]) for v in near]
    apart = [k for k, lb in enumerate(labels) if lb != labels[0]]
    if not apart:
        return
    first = vox[lab[tuple(vox.T)] == labels[0]]
    k = apart[0]
    gap = float(np.min(np.linalg.norm((first - near[k]) * sp_zyx, axis=1)))
    seed = ",".join(f"{v:g}" for v in seeds_lps_mm[k])
    raise SeedsApartError(
        f"{volume.source or 'volume'}: --seed-lps={seed} lies in a vessel structure apart from the first seed's "
        f"({gap:.0f} mm from it at the lumen threshold; {len(apart)} of {len(seeds_lps_mm)} seeds apart): the tree is "
        f"one connected structure; give seeds in one structure, or run once for each (`guidewire3d vessels` writes one "
        f"tree per structure)", which=f"--seed-lps={seed} is {gap:.0f} mm from the first seed's at the lumen threshold")
