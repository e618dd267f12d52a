"""``guidewire3d vessels`` writes the vessel mask: ``vessels_mask.nii.gz`` on the input's grid, and, when the input is
DICOM, ``vessels_seg.dcm``, a DICOM Segmentation referencing the input's images (for a PACS or Slicer's DICOM module).

Until stop 45 the planning folder held the surfaces and the centerline only: a user could not overlay the segmentation
on the CTA to check it voxel by voxel. Checked here in physical space on an oblique grid (10 degrees about the
superior axis), where a slip of axis order, slice order or LPS/RAS would move the mask off the tube.
"""
from __future__ import annotations

import numpy as np
import pydicom
import pytest

from guidewire3d import io
from guidewire3d.app import cli

from test_vesselplan_forest import LEFT_X_MM, RIGHT_X_MM, AXIS_Y_MM, _seed_arg, tubes_file  # noqa: F401

hd = pytest.importorskip("highdicom")

_C, _S = np.cos(np.radians(10.0)), np.sin(np.radians(10.0))
DIRECTION = np.array([[_C, -_S, 0.0], [_S, _C, 0.0], [0.0, 0.0, 1.0]])
SPACING = (0.7, 0.8, 2.0)
ORIGIN = (-20.0, -30.0, 100.0)
RADIUS_MM = 4.0


def _tube() -> io.Volume:
    """A bright tube of radius 4 mm along the slice axis, at column 30, row 32 of an oblique grid."""
    rng = np.random.default_rng(0)
    z, y, x = np.mgrid[0:40, 0:64, 0:64]
    inside = ((y - 32) * SPACING[1]) ** 2 + ((x - 30) * SPACING[0]) ** 2 < RADIUS_MM ** 2
    arr = np.where(inside, 400.0, 40.0) + rng.normal(0.0, 5.0, inside.shape)
    return io.Volume(arr.astype(np.float32), SPACING, ORIGIN, DIRECTION, source="tube")


def _axis_distance_mm(vol: io.Volume, lps: np.ndarray) -> np.ndarray:
    """Distance (mm) of LPS points from the tube's axis."""
    a = vol.index_zyx_to_lps(np.array([[0.0, 32.0, 30.0], [39.0, 32.0, 30.0]]))
    u = (a[1] - a[0]) / np.linalg.norm(a[1] - a[0])
    d = lps - a[0]
    return np.linalg.norm(d - (d @ u)[:, None] * u, axis=1)


@pytest.fixture(scope="module")
def dicom_plan(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mask")
    vol = _tube()
    series = io.write_ct_series(vol, tmp / "ct")
    assert cli.main(["vessels", "--cta", str(series), "--out", str(tmp / "plan"), "--no-screenshot"]) == 0
    return vol, series, tmp / "plan"


def test_the_nifti_mask_lies_on_the_tube(dicom_plan):
    vol, _, plan = dicom_plan
    mask = io.read_volume(plan / "vessels_mask.nii.gz")
    assert mask.shape_zyx == vol.shape_zyx
    assert np.allclose(mask.direction, vol.direction, atol=1e-5) and np.allclose(mask.origin_lps_mm, ORIGIN, atol=1e-4)
    on = np.argwhere(mask.array_zyx == 1).astype(float)
    assert set(np.unique(mask.array_zyx).tolist()) == {0.0, 1.0}
    d = _axis_distance_mm(vol, mask.index_zyx_to_lps(on))
    assert d.max() < RADIUS_MM + 1.0
    tube = np.argwhere(_axis_distance_mm(vol, vol.index_zyx_to_lps(
        np.argwhere(np.ones(vol.shape_zyx, bool)).astype(float))).reshape(vol.shape_zyx) < RADIUS_MM - 1.0)
    assert np.mean(mask.array_zyx[tuple(tube.T)] == 1) > 0.95


def test_the_dicom_segmentation_references_the_series_and_matches_the_mask(dicom_plan):
    vol, series, plan = dicom_plan
    seg = hd.seg.segread(plan / "vessels_seg.dcm")
    assert seg.Modality == "SEG" and seg.number_of_segments == 1
    assert seg.get_segment_description(1).segment_label == "vessels"
    src = {str(pydicom.dcmread(f, stop_before_pixels=True).SOPInstanceUID) for f in series.iterdir()}
    ref = {str(i.ReferencedSOPInstanceUID) for s in seg.ReferencedSeriesSequence for i in s.ReferencedInstanceSequence}
    assert ref == src
    assert str(seg.FrameOfReferenceUID) == str(pydicom.dcmread(next(series.iterdir())).FrameOfReferenceUID)
    sv = seg.get_volume(combine_segments=True)
    lab = np.asarray(sv.array)
    A = np.asarray(sv.affine, float)
    idx = np.argwhere(lab == 1).astype(float)
    lps = idx @ A[:3, :3].T + A[:3, 3]
    mask = io.read_volume(plan / "vessels_mask.nii.gz")
    back = np.rint(mask.lps_to_index_zyx(lps)).astype(int)
    assert np.all(mask.array_zyx[tuple(back.T)] == 1)
    assert len(idx) == int((mask.array_zyx == 1).sum())


def test_a_forest_is_one_label_per_tree_and_a_nifti_input_has_no_dicom_seg(tubes_file, tmp_path):  # noqa: F811
    out = tmp_path / "plan"
    assert cli.main(["vessels", "--cta", str(tubes_file), "--out", str(out), "--no-screenshot",
                     _seed_arg((RIGHT_X_MM, AXIS_Y_MM, 15.0)), _seed_arg((LEFT_X_MM, AXIS_Y_MM, 12.0))]) == 0
    assert not (out / "vessels_seg.dcm").exists()
    mask = io.read_volume(out / "vessels_mask.nii.gz")
    for label, x in ((1, RIGHT_X_MM), (2, LEFT_X_MM)):  # tree 1 is the first seed's structure
        lps = mask.index_zyx_to_lps(np.argwhere(mask.array_zyx == label).astype(float))
        assert len(lps) and np.all(np.abs(lps[:, 0] - x) < 6.0)


def test_a_segmentation_highdicom_refuses_leaves_the_plan_with_a_warning(tmp_path, monkeypatch, capsys):
    """A DICOM input whose headers highdicom cannot make a Segmentation from: the plan is written without
    vessels_seg.dcm, one warning line says so (the mask is in vessels_mask.nii.gz)."""
    series = io.write_ct_series(_tube(), tmp_path / "ct")

    def refuse(*a, **k):
        raise ValueError("Source images must have the same frame of reference")
    monkeypatch.setattr(io, "write_dicom_seg", refuse)
    assert cli.main(["vessels", "--cta", str(series), "--out", str(tmp_path / "plan"), "--no-screenshot"]) == 0
    assert (tmp_path / "plan" / "vessels_mask.nii.gz").exists() and not (tmp_path / "plan" / "vessels_seg.dcm").exists()
    warn = [x for x in capsys.readouterr().err.splitlines() if "vessels_seg.dcm not written" in x]
    assert len(warn) == 1 and "same frame of reference" in warn[0]
