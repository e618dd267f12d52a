"""A CTA or MRA stored as one multi-frame DICOM file (Enhanced CT / MR Image Storage, or their Legacy Converted
forms): one frame per slice, the geometry in the per-frame and shared functional groups.

Many scanners export MR angiograms this way (and some CT). Until stop 45 ``read_volume`` took the file for a classic
slice and refused it with "missing ImagePositionPatient (0020,0032)". The files here are made with highdicom's
legacy conversion from a classic series written by ``io.write_ct_series``, so the same voxels must come back at the
same physical places; the geometry's faults are named with the frame and the sequence they belong to.
"""
from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pydicom
import pytest
from pydicom.uid import generate_uid

from guidewire3d import io
from guidewire3d.errors import DicomError

hd = pytest.importorskip("highdicom")

# an oblique grid: 10 degrees about the superior axis, the slices 2 mm apart
_C, _S = np.cos(np.radians(10.0)), np.sin(np.radians(10.0))
DIRECTION = np.array([[_C, -_S, 0.0], [_S, _C, 0.0], [0.0, 0.0, 1.0]])
SPACING = (0.7, 0.8, 2.0)
ORIGIN = (-20.0, -30.0, 100.0)


def _tube_volume() -> io.Volume:
    """A 4 mm-radius bright tube along the slice axis over a dim background with noise (HU-like values)."""
    rng = np.random.default_rng(0)
    z, y, x = np.mgrid[0:40, 0:64, 0:64]
    arr = np.where(((y - 32) * SPACING[1]) ** 2 + ((x - 30) * SPACING[0]) ** 2 < 16.0, 400.0, 40.0)
    arr = arr + 3.0 * z + rng.normal(0.0, 5.0, arr.shape)  # a ramp along z shows a slice-order slip
    return io.Volume(arr.astype(np.float32), SPACING, ORIGIN, DIRECTION, source="tube")


def _legacy_datasets(folder: Path, modality: str) -> list:
    dss = [pydicom.dcmread(f) for f in sorted(folder.iterdir())]
    for d in dss:
        if modality == "MR":
            d.Modality = "MR"
            d.SOPClassUID = d.file_meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.4"
            for k in ("RescaleSlope", "RescaleIntercept", "RescaleType", "KVP"):
                if k in d:
                    del d[k]
            d.ScanningSequence, d.SequenceVariant, d.ScanOptions, d.MRAcquisitionType = "GR", "NONE", "", "3D"
            d.EchoTime, d.RepetitionTime, d.EchoTrainLength, d.MagneticFieldStrength = 1.0, 3.0, 1, 1.5
            d.ImageType = ["ORIGINAL", "PRIMARY", "OTHER"]
        else:
            d.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL"]
    return dss


def _enhanced(classic: Path, modality: str) -> pydicom.Dataset:
    cls = hd.legacy.LegacyConvertedEnhancedMRImage if modality == "MR" else hd.legacy.LegacyConvertedEnhancedCTImage
    return cls(legacy_datasets=_legacy_datasets(classic, modality), series_instance_uid=generate_uid(),
               series_number=9, sop_instance_uid=generate_uid(), instance_number=1)


@pytest.fixture(scope="module")
def classic(tmp_path_factory) -> Path:
    return io.write_ct_series(_tube_volume(), tmp_path_factory.mktemp("classic") / "ct")


def _save(ds, folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    ds.save_as(folder / "enhanced.dcm", enforce_file_format=True)
    return folder / "enhanced.dcm"


def _same_physical_volume(a: io.Volume, b: io.Volume) -> None:
    """Every voxel of ``a`` is found in ``b`` at the same LPS position with the same value."""
    assert a.shape_zyx == b.shape_zyx or sorted(a.shape_zyx) == sorted(b.shape_zyx)
    idx = np.argwhere(np.ones(a.shape_zyx, bool))[::97].astype(float)
    lps = a.index_zyx_to_lps(idx)
    jdx = b.lps_to_index_zyx(lps)
    assert np.abs(jdx - np.rint(jdx)).max() < 1e-3
    jdx = np.rint(jdx).astype(int)
    assert np.all(jdx >= 0) and np.all(jdx < np.array(b.shape_zyx))
    ia = idx.astype(int)
    np.testing.assert_array_equal(a.array_zyx[tuple(ia.T)], b.array_zyx[tuple(jdx.T)])


@pytest.mark.parametrize("modality", ["CT", "MR"])
def test_an_enhanced_file_is_the_same_volume_as_its_classic_series(classic, tmp_path, modality):
    path = _save(_enhanced(classic, modality), tmp_path / modality)
    vol = io.read_volume(path, modalities=("CT", "MR"))
    ref = io.read_volume(classic)
    assert np.allclose(sorted(vol.spacing_mm), sorted(ref.spacing_mm), atol=1e-4)
    _same_physical_volume(ref, vol)
    # the folder, not only the file, reads the same
    _same_physical_volume(ref, io.read_volume(path.parent, modalities=("CT", "MR")))


def test_frames_stored_out_of_order_read_in_place(classic, tmp_path):
    ds = _enhanced(classic, "CT")
    arr = ds.pixel_array
    order = np.random.default_rng(1).permutation(arr.shape[0])
    ds.PerFrameFunctionalGroupsSequence = [copy.deepcopy(ds.PerFrameFunctionalGroupsSequence[i]) for i in order]
    ds.PixelData = np.ascontiguousarray(arr[order]).tobytes()
    assert not np.array_equal(order, np.arange(len(order)))  # the file's frames are out of order
    vol = io.read_volume(_save(ds, tmp_path), modalities=("CT",))
    ref = io.read_volume(classic)
    _same_physical_volume(ref, vol)
    # the ramp of 3 HU a slice runs along the slice axis in the volume read, in order: each slice at its own place
    means = vol.array_zyx.mean(axis=(1, 2))
    assert np.all(np.abs(np.diff(means)) > 2.0) and (np.all(np.diff(means) > 0) or np.all(np.diff(means) < 0))
    assert vol.shape_zyx == ref.shape_zyx


def test_a_folder_holding_a_localizer_reads_the_multi_frame_volume(classic, tmp_path):
    """The series with the most slices is read: a multi-frame file counts its frames, not as one slice."""
    folder = tmp_path / "study"
    _save(_enhanced(classic, "CT"), folder)
    loc = _tube_volume()
    loc = io.Volume(loc.array_zyx[:3], loc.spacing_mm, loc.origin_lps_mm, loc.direction, source="localizer")
    io.write_ct_series(loc, tmp_path / "loc")
    for f in (tmp_path / "loc").iterdir():
        f.rename(folder / f"loc_{f.name}")
    said = []
    vol = io.read_volume(folder, log=said.append)
    assert vol.shape_zyx[0] == 40 and "(40 slices)" in said[0]


def _broken(classic, tmp_path, change) -> Path:
    ds = _enhanced(classic, "CT")
    change(ds)
    return _save(ds, tmp_path)


def test_a_frame_without_its_position_is_named(classic, tmp_path):
    def drop(ds):
        del ds.PerFrameFunctionalGroupsSequence[2].PlanePositionSequence
    path = _broken(classic, tmp_path, drop)
    with pytest.raises(DicomError, match=r"enhanced\.dcm: frame 3: missing PlanePositionSequence"):
        io.read_volume(path)


def test_a_time_series_in_one_file_is_refused_named(classic, tmp_path):
    """Two frames at each position (a time-resolved MRA's phases, or echoes): not one volume."""
    def twice(ds):
        pf = ds.PerFrameFunctionalGroupsSequence
        for k in range(1, len(pf), 2):
            pf[k].PlanePositionSequence[0].ImagePositionPatient = \
                list(pf[k - 1].PlanePositionSequence[0].ImagePositionPatient)
    path = _broken(classic, tmp_path, twice)
    with pytest.raises(DicomError, match=r"40 frames at only 20 slice positions"):
        io.read_volume(path)


def test_uneven_frames_and_a_wrong_orientation_are_named(classic, tmp_path):
    def uneven(ds):
        p = ds.PerFrameFunctionalGroupsSequence[5].PlanePositionSequence[0]
        p.ImagePositionPatient = [float(v) for v in np.asarray(p.ImagePositionPatient, float) + 0.7 * DIRECTION[:, 2]]
    with pytest.raises(DicomError, match=r"enhanced\.dcm: uneven slice spacing"):
        io.read_volume(_broken(classic, tmp_path / "a", uneven))

    def skew(ds):
        ds.SharedFunctionalGroupsSequence[0].PlaneOrientationSequence[0].ImageOrientationPatient = [1, 0, 0, 0.5, 1, 0]
        for item in ds.PerFrameFunctionalGroupsSequence:
            if "PlaneOrientationSequence" in item:
                del item.PlaneOrientationSequence
    with pytest.raises(DicomError, match=r"frame 1: .*ImageOrientationPatient.*not two orthogonal unit vectors"):
        io.read_volume(_broken(classic, tmp_path / "b", skew))


def test_vessels_on_an_enhanced_mr_gives_the_classic_series_tree(classic, tmp_path):
    """The planning command end to end: the same tree from the multi-frame MR as from the classic series; a broken
    file is one line, exit 2, nothing written."""
    path = _save(_enhanced(classic, "MR"), tmp_path / "mr")

    def vessels(cta, out):
        return subprocess.run([sys.executable, "-m", "guidewire3d.app.cli", "vessels", "--cta", str(cta), "--out", str(out),
                               "--no-screenshot"], capture_output=True, text=True, timeout=300)

    a, b = vessels(path, tmp_path / "out_mr"), vessels(classic, tmp_path / "out_ct")
    assert a.returncode == 0 and b.returncode == 0, a.stderr + b.stderr
    ja = json.loads((tmp_path / "out_mr" / "vessels.json").read_text())
    jb = json.loads((tmp_path / "out_ct" / "vessels.json").read_text())
    assert len(ja["branches"]) == len(jb["branches"]) >= 1
    la = sum(br["length_mm"] for br in ja["branches"])
    lb = sum(br["length_mm"] for br in jb["branches"])
    assert abs(la - lb) < 0.01 * lb and lb > 60.0  # the 80 mm tube

    def no_pixel_spacing(ds):
        for item in [*ds.SharedFunctionalGroupsSequence, *ds.PerFrameFunctionalGroupsSequence]:
            if "PixelMeasuresSequence" in item:
                del item.PixelMeasuresSequence
    r = vessels(_broken(classic, tmp_path / "bad", no_pixel_spacing), tmp_path / "out_bad")
    assert r.returncode == 2
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and "enhanced.dcm: frame 1: missing PixelMeasuresSequence" in lines[0], r.stderr
    assert not (tmp_path / "out_bad").exists()


def test_an_x_ray_3d_angiographic_volume_is_read_as_a_vessel_volume(classic, tmp_path):
    """A C-arm's 3D rotational angiogram stored as X-Ray 3D Angiographic Image Storage (Modality XA, the geometry in
    functional groups, as an enhanced CT's): a vessel volume for every command, not refused as an XA run."""
    ds = _enhanced(classic, "CT")
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID = io.XRAY_3D_STORAGE[0]
    ds.Modality = "XA"
    path = _save(ds, tmp_path)
    vol = io.read_volume(path)
    _same_physical_volume(io.read_volume(classic), vol)
    assert io.volume_files(path.parent)[1] == [path]
