import json

import numpy as np
import pydicom
import pytest

from guidewire3d import io
from guidewire3d.errors import DicomError, GeometryError, InputError
from guidewire3d.geometry import CArm


def _volume(rng, shape=(12, 20, 16), spacing=(0.7, 0.7, 1.25), origin=(-30.5, 12.25, -101.0)):
    arr = rng.integers(-200, 600, size=shape).astype(np.float32)
    return io.Volume(arr, spacing, origin)


def test_ct_series_round_trip_sitk_and_pydicom(tmp_path):
    rng = np.random.default_rng(0)
    vol = _volume(rng)
    out = io.write_ct_series(vol, tmp_path / "ct")
    back = io.read_volume(out)
    assert np.array_equal(back.array_zyx, vol.array_zyx)
    assert np.allclose(back.spacing_mm, vol.spacing_mm, atol=1e-5)
    assert np.allclose(back.origin_lps_mm, vol.origin_lps_mm, atol=1e-5)
    assert np.allclose(back.direction, np.eye(3))
    files = sorted(out.glob("*.dcm"))
    assert len(files) == 12
    ds = pydicom.dcmread(files[3])
    assert ds.Modality == "CT" and ds.SOPClassUID == io.CT_IMAGE_STORAGE
    assert np.allclose([float(x) for x in ds.ImagePositionPatient], vol.index_zyx_to_lps([3, 0, 0]), atol=1e-5)
    hu = ds.pixel_array * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
    assert np.array_equal(hu, vol.array_zyx[3])


def test_index_lps_round_trip_with_direction():
    rng = np.random.default_rng(1)
    c, s = np.cos(0.3), np.sin(0.3)
    D = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    vol = io.Volume(np.zeros((4, 5, 6), np.float32), (0.5, 0.6, 1.0), (1, 2, 3), D)
    idx = rng.uniform(0, 4, size=(10, 3))
    assert np.allclose(vol.lps_to_index_zyx(vol.index_zyx_to_lps(idx)), idx)
    assert np.allclose(vol.index_zyx_to_lps([0, 0, 1]), np.array([1, 2, 3]) + 0.5 * D[:, 0])


def test_nifti_nrrd_mha_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    vol = _volume(rng)
    for ext in ("nii.gz", "nrrd", "mha"):
        p = io.write_volume(vol, tmp_path / f"v.{ext}")
        back = io.read_volume(p)
        assert np.array_equal(back.array_zyx, vol.array_zyx)
        assert np.allclose(back.origin_lps_mm, vol.origin_lps_mm, atol=1e-4)


def test_largest_ct_series_chosen_and_series_uid(tmp_path):
    rng = np.random.default_rng(3)
    big, small = _volume(rng, shape=(10, 8, 8)), _volume(rng, shape=(4, 8, 8))
    io.write_ct_series(big, tmp_path / "a", series_uid="1.2.3.10")
    io.write_ct_series(small, tmp_path / "b", series_uid="1.2.3.4")
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for f in list((tmp_path / "a").iterdir()) + list((tmp_path / "b").iterdir()):
        (mixed / f"{f.parent.name}_{f.name}").write_bytes(f.read_bytes())
    said = []
    vol = io.read_volume(mixed, log=said.append)
    assert vol.shape_zyx == (10, 8, 8) and vol.series_uid == "1.2.3.10"
    assert said and "largest volume series 1.2.3.10 (10 slices)" in said[0]
    assert io.read_volume(mixed, series_uid="1.2.3.4").shape_zyx == (4, 8, 8)
    with pytest.raises(DicomError, match="not found"):
        io.read_volume(mixed, series_uid="9.9")


def test_a_radial_mip_series_beside_the_volume_is_not_chosen(tmp_path):
    """A study folder with the MRA's slices and a larger series of radial MIP images (each at its own orientation):
    the stack is read, not the MIPs; the MIP series alone, or chosen, is refused naming a file."""
    rng = np.random.default_rng(6)
    folder = tmp_path / "study"
    io.write_ct_series(_volume(rng, shape=(8, 12, 12)), tmp_path / "ct")
    io.write_ct_series(_volume(rng, shape=(20, 12, 12)), tmp_path / "mip")
    uid = pydicom.uid.generate_uid()
    folder.mkdir()
    for k, f in enumerate(sorted((tmp_path / "mip").glob("*.dcm"))):
        ds = pydicom.dcmread(f)
        a = np.radians(9.0 * k)
        ds.ImageOrientationPatient = [float(np.cos(a)), float(np.sin(a)), 0.0, 0.0, 0.0, -1.0]
        ds.ImagePositionPatient = [0.0, 0.0, 0.0]
        ds.SeriesInstanceUID = uid
        ds.save_as(folder / f"mip_{k:03d}.dcm")
    for f in (tmp_path / "ct").glob("*.dcm"):
        f.rename(folder / f"ct_{f.name}")
    vol = io.read_volume(folder)
    assert vol.shape_zyx == (8, 12, 12)
    with pytest.raises(DicomError, match=r"mip_0\d\d\.dcm: ImageOrientationPatient \(0020,0037\).*not one stack"):
        io.read_volume(folder, series_uid=uid)


def test_uneven_slice_spacing_refused(tmp_path):
    rng = np.random.default_rng(4)
    out = io.write_ct_series(_volume(rng, shape=(6, 8, 8)), tmp_path / "ct")
    f = sorted(out.glob("*.dcm"))[2]
    ds = pydicom.dcmread(f)
    ds.ImagePositionPatient[2] = float(ds.ImagePositionPatient[2]) + 0.5
    ds.save_as(f)
    with pytest.raises(DicomError, match="uneven slice spacing"):
        io.read_volume(out)


def test_slice_positions_written_with_two_decimals_are_an_even_stack(tmp_path):
    """0.625 mm slices whose ImagePositionPatient is written with two decimals step 0.62 and 0.63 mm: no slice is
    more than 0.005 mm off an even stack, and SimpleITK places them on one (the mean step). They were refused as
    "uneven slice spacing" (steps within 1 % of each other were asked)."""
    rng = np.random.default_rng(6)
    vol = _volume(rng, shape=(40, 8, 8), spacing=(0.7, 0.7, 0.625))
    out = io.write_ct_series(vol, tmp_path / "ct")
    for f in sorted(out.glob("*.dcm")):
        ds = pydicom.dcmread(f)
        ds.ImagePositionPatient[2] = f"{float(ds.ImagePositionPatient[2]):.2f}"
        ds.save_as(f)
    zs = sorted(float(pydicom.dcmread(f).ImagePositionPatient[2]) for f in out.glob("*.dcm"))
    assert np.ptp(np.diff(zs)) > 0.009   # 0.62 and 0.63 mm steps
    back = io.read_volume(out)
    assert back.shape_zyx == vol.shape_zyx
    assert back.spacing_mm[2] == pytest.approx(0.625, abs=1e-3)
    assert np.allclose(back.array_zyx, vol.array_zyx, atol=1.0)


def test_xa_multiframe_round_trip(tmp_path):
    rng = np.random.default_rng(5)
    carm = CArm(-32.5, 17.25, 1080.0, 760.0, 0.308, (64, 80))
    frames = rng.integers(0, 4000, size=(3, 64, 80))
    p = io.write_xa(tmp_path / "run.dcm", frames, carm, frame_time_ms=50)
    run = io.read_xa(p)
    assert run.n_frames == 3 and np.array_equal(run.frames, frames.astype(np.float32))
    assert np.allclose(run.carm.projection_matrix(), carm.projection_matrix(), atol=1e-6)
    assert run.frame_time_ms == pytest.approx(50)
    ds = pydicom.dcmread(p)
    assert ds.Modality == "XA" and int(ds.NumberOfFrames) == 3


def test_xa_override_supplies_missing_tag(tmp_path):
    carm = CArm(0, 0, 1100, 750, 0.3, (32, 32))
    p = io.write_xa(tmp_path / "x.dcm", np.zeros((1, 32, 32)), carm)
    ds = pydicom.dcmread(p)
    del ds.DistanceSourceToDetector
    ds.save_as(p)
    with pytest.raises(DicomError, match=r"DistanceSourceToDetector \(0018,1110\)"):
        io.read_xa(p)
    run = io.read_xa(p, overrides={"sid_mm": 1200})
    assert run.carm.sid_mm == 1200


def test_image_sequence_with_sidecar(tmp_path):
    import cv2

    d = tmp_path / "seq"
    d.mkdir()
    for k in range(3):
        cv2.imwrite(str(d / f"f{k}.png"), np.full((20, 30), 10 * k, np.uint8))
    with pytest.raises(InputError, match="geometry sidecar missing"):
        io.read_image_sequence(d)
    (d / "geometry.json").write_text(json.dumps(dict(primary_deg=10, secondary_deg=0, sid_mm=1000, sod_mm=700, pixel_mm=0.3)))
    run = io.read_image_sequence(d)
    assert run.frames.shape == (3, 20, 30) and run.frames[2, 0, 0] == 20
    (d / "geometry.json").write_text(json.dumps(dict(primary_deg=10, secondary_deg=0, sid_mm=600, sod_mm=700, pixel_mm=0.3)))
    with pytest.raises(GeometryError, match="geometry.json"):
        io.read_image_sequence(d)


# the bad-input corpus (one line, exit 2, nothing written) is tests/test_bad_inputs.py


def test_xa_compressed_rle_round_trip(tmp_path):
    from pydicom.uid import RLELossless

    rng = np.random.default_rng(7)
    carm = CArm(10, -5, 1100, 750, 0.3, (48, 40))
    frames = rng.integers(0, 4000, size=(2, 48, 40))
    p = io.write_xa(tmp_path / "run.dcm", frames, carm)
    ds = pydicom.dcmread(p)
    ds.compress(RLELossless)
    ds.save_as(tmp_path / "rle.dcm")
    assert pydicom.dcmread(tmp_path / "rle.dcm").file_meta.TransferSyntaxUID == RLELossless
    run = io.read_xa(tmp_path / "rle.dcm")
    assert np.array_equal(run.frames, frames.astype(np.float32))
