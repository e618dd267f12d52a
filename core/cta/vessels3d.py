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
from guidewire3d import io
from guidewire3d.cta.centerline import CenterlineOptions, centerline_from_mask
from guidewire3d.cta.segment import VesselOptions, segment_vessels
from guidewire3d.cta.surface import surface_from_mask
from guidewire3d.vesseltree import VesselTree

__all__ = ["CTAVessels", "extract_vessels"]


@dataclass(frozen=True, eq=False)
class CTAVessels:
    """Everything the vessel stage produces for one CTA."""

    mask_zyx: np.ndarray  # (z, y, x) bool, same grid as the input volume
    surface: object  # vtkPolyData, triangles with normals, LPS mm
    tree: VesselTree  # centerline graph, LPS mm
    seconds: dict = field(default_factory=dict)  # stage -> wall seconds (surface and centerline run side by side)


def extract_vessels(volume: io.Volume, *, seeds_lps_mm=None, progress: bool = False,
                    options: VesselOptions | None = None,
                    centerline_options: CenterlineOptions | None = None) -> CTAVessels:
    """Segmentation, surface and centerline graph of a CTA, with stage timings.

    Parameters
    ----------
    volume : io.Volume
        CT in HU.
    seeds_lps_mm : (K, 3) array_like of float, optional
        Points in the vessels; the first also picks the centerline root.
    progress : bool
        tqdm bars per stage.

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
    mask = segment_vessels(volume, seeds_lps_mm=seeds_lps_mm, progress=progress, options=options)
    secs["segment"] = time.perf_counter() - t0
    mask.setflags(write=False)
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
    return CTAVessels(mask_zyx=mask, surface=surf, tree=tree, seconds=secs)
