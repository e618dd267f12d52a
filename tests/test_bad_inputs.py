"""Never silently wrong (issue #20): every kind of bad input gets ONE line on stderr,
``guidewire3d: error: ...`` naming the file and the field (or the command-line option), exit
status 2, and nothing is written: no output folder and no staging folder beside it.

Each kind below builds its bad input from the small simulated case (``small_case_dir``: ``ct/``,
``roadmap.dcm``, ``frames.dcm``) and returns the command line and the words the error must name.
All are refused before the CTA vessel stage, so the whole module runs in seconds. At the end:
inputs that are unusual but valid (compressed or big-endian DICOM, an RGB or enhanced XA, an LZW
TIFF) must read, and the faults (a killed run, two runs into one folder, a full disk).
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pydicom
import pytest

from guidewire3d import io
from guidewire3d.app.cli import main
from guidewire3d.errors import OutputError

ENHANCED_XA_STORAGE = "1.2.840.10008.5.1.4.1.1.12.1.1"
GEOMETRY_TAGS = ("PositionerPrimaryAngle", "PositionerSecondaryAngle", "DistanceSourceToDetector",
                 "DistanceSourceToPatient", "ImagerPixelSpacing")


class Kit:
    """Builds bad inputs in ``tmp`` from the simulated case in ``case``."""

    def __init__(self, case: Path, tmp: Path):
        self.case, self.tmp = case, tmp
        self.out = tmp / "out"

    def recon(self, *extra, cta=None, roadmap=None, frames=None) -> list[str]:
        roadmap = roadmap or self.case / "roadmap.dcm"
        return ["reconstruct", "--cta", str(cta or self.case / "ct"), "--roadmap", str(roadmap),
                "--frames", str(frames or self.case / "frames.dcm"), "--out", str(self.out), *extra]

    def xa(self, name: str, edit, src: str = "roadmap.dcm") -> Path:
        """A copy of ``src`` with ``edit(ds)`` applied."""
        ds = pydicom.dcmread(self.case / src)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # pydicom warns about the odd values written on purpose
            edit(ds)
            p = self.tmp / name
            ds.save_as(p)
        return p

    def ct(self, edit=None, *, index: int | None = None) -> Path:
        """A copy of the CT series; ``edit(ds)`` applied to slice ``index`` (every slice if None)."""
        d = self.tmp / "ct"
        d.mkdir()
        for k, f in enumerate(sorted((self.case / "ct").iterdir())):
            if edit is not None and index in (None, k):
                ds = pydicom.dcmread(f)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    edit(ds)
                    ds.save_as(d / f.name)
            else:
                (d / f.name).write_bytes(f.read_bytes())
        return d

    def ct_slice(self, k: int) -> Path:
        return sorted((self.tmp / "ct").iterdir())[k]

    def truncated(self, src: Path, n_bytes: int, name: str | None = None) -> Path:
        p = self.tmp / (name or src.name) if name or src.parent != self.tmp / "ct" else src
        p.write_bytes(src.read_bytes()[:n_bytes])
        return p

    def volume_file(self, name: str, array_zyx, spacing=(0.8, 0.8, 1.0)) -> Path:
        return io.write_volume(io.Volume(np.asarray(array_zyx, np.float32), spacing, (0, 0, 0)), self.tmp / name)

    def png_folder(self, geometry=None, sizes=((64, 64),) * 2) -> Path:
        import cv2

        d = self.tmp / "seq"
        d.mkdir()
        for k, shape in enumerate(sizes):
            cv2.imwrite(str(d / f"f{k}.png"), np.full(shape, 100 + k, np.uint8))
        if geometry is not None:
            (d / "geometry.json").write_text(geometry if isinstance(geometry, str) else json.dumps(geometry))
        return d

    def video(self, name="run.avi") -> Path:
        import cv2

        p = self.tmp / name
        w = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
        rng = np.random.default_rng(0)
        for _ in range(3):
            w.write(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
        w.release()
        return p


GOOD_GEOMETRY = dict(primary_deg=10, secondary_deg=0, sid_mm=1000, sod_mm=700, pixel_mm=0.3)
KINDS = {}


def kind(fn):
    """Register ``fn(kit) -> (argv, words the error line must contain)`` as a kind of bad input."""
    KINDS[fn.__name__] = fn
    return fn


def _del(*keywords):
    def edit(ds):
        for kw in keywords:
            delattr(ds, kw)
    return edit


def _set(**values):
    def edit(ds):
        for kw, v in values.items():
            setattr(ds, kw, v)
    return edit


def _pixels(frames):
    def edit(ds):
        a = np.asarray(frames, np.uint16)
        ds.NumberOfFrames = a.shape[0] if a.ndim == 3 else 1
        ds.PixelData = a.tobytes()
    return edit


# --- the CTA ----------------------------------------------------------------------------------
@kind
def cta_missing(t):
    return t.recon(cta=t.tmp / "nowhere"), ["nowhere", "no such file"]


@kind
def cta_dangling_symlink(t):
    (t.tmp / "link").symlink_to(t.tmp / "gone")
    return t.recon(cta=t.tmp / "link"), ["link", "dangling"]


@kind
def cta_empty_folder(t):
    (t.tmp / "empty").mkdir()
    return t.recon(cta=t.tmp / "empty"), ["empty", "empty directory"]


@kind
def cta_zero_byte_file(t):
    (t.tmp / "ct.nii.gz").write_bytes(b"")
    return t.recon(cta=t.tmp / "ct.nii.gz"), ["ct.nii.gz", "0 bytes"]


@kind
def cta_garbage_file(t):
    (t.tmp / "ct.nrrd").write_bytes(np.random.default_rng(0).bytes(5000))
    return t.recon(cta=t.tmp / "ct.nrrd"), ["ct.nrrd", "not a readable volume"]


@kind
def cta_fifo(t):
    os.mkfifo(t.tmp / "ct.mha")
    return t.recon(cta=t.tmp / "ct.mha"), ["ct.mha", "not a regular file"]


@kind
def cta_without_pixel_spacing(t):
    t.ct(_del("PixelSpacing"))
    return t.recon(cta=t.tmp / "ct"), [t.ct_slice(0).name, "PixelSpacing (0028,0030)", "missing"]


@kind
def cta_pixel_spacing_zero(t):
    t.ct(_set(PixelSpacing=[0, 0]))
    return t.recon(cta=t.tmp / "ct"), [t.ct_slice(0).name, "PixelSpacing (0028,0030)", "positive"]


@kind
def cta_one_slice_truncated_in_pixels(t):
    t.ct()
    f = t.ct_slice(40)
    t.truncated(f, f.stat().st_size // 2)
    return t.recon(cta=t.tmp / "ct"), [f.name, "truncated", "PixelData"]


@kind
def cta_one_slice_cut_to_300_bytes(t):
    t.ct()
    f = t.ct_slice(7)
    t.truncated(f, 300)
    return t.recon(cta=t.tmp / "ct"), [f.name, "truncated"]


@kind
def cta_nan_slice_position(t):
    t.ct(_set(ImagePositionPatient=["NaN", "0", "0"]), index=5)
    return t.recon(cta=t.tmp / "ct"), [t.ct_slice(5).name, "ImagePositionPatient (0020,0032)", "finite"]


@kind
def cta_missing_orientation(t):
    t.ct(_del("ImageOrientationPatient"), index=3)
    return t.recon(cta=t.tmp / "ct"), [t.ct_slice(3).name, "ImageOrientationPatient (0020,0037)"]


@kind
def cta_slice_of_another_size(t):
    t.ct(_set(Rows=32, Columns=32, PixelData=np.zeros((32, 32), np.int16).tobytes()), index=9)
    return t.recon(cta=t.tmp / "ct"), [t.ct_slice(9).name, "Rows x Columns"]


@kind
def cta_uneven_slice_spacing(t):
    def shift(ds):
        ds.ImagePositionPatient[2] = float(ds.ImagePositionPatient[2]) + 0.4
    t.ct(shift, index=20)
    return t.recon(cta=t.tmp / "ct"), [str(t.tmp / "ct"), "uneven slice spacing"]


@kind
def cta_slice_of_another_orientation(t):  # a radial MIP's images, or a localizer in the series
    t.ct(_set(ImageOrientationPatient=[1, 0, 0, 0, 0, -1]), index=7)
    return t.recon(cta=t.tmp / "ct"), [t.ct_slice(7).name, "ImageOrientationPatient (0020,0037)", "not one stack"]


@kind
def cta_single_slice(t):
    d = t.tmp / "one"
    d.mkdir()
    f = sorted((t.case / "ct").iterdir())[0]
    (d / f.name).write_bytes(f.read_bytes())
    return t.recon(cta=d), [str(d), "at least 2 slices"]


@kind
def cta_is_an_xa(t):  # an XA where the CTA is expected
    return t.recon(cta=t.case / "roadmap.dcm"), ["roadmap.dcm", "no CT or MR series", "XA"]


@kind
def cta_nifti_with_nan(t):  # ITK's NIfTI reader reads a stored NaN as 0
    p = t.volume_file("ct.nii", np.full((8, 16, 16), 40.0))
    raw = bytearray(p.read_bytes())
    i = 352 + 4 * (3 * 16 * 16 + 4 * 16 + 5)  # voxel (3, 4, 5) after the NIfTI-1 header
    raw[i:i + 4] = np.array([np.nan], "<f4").tobytes()
    p.write_bytes(bytes(raw))
    return t.recon(cta=p), ["ct.nii", "NaN or infinite"]


@kind
def cta_nifti_with_inf(t):
    a = np.full((8, 16, 16), 40.0)
    a[0, 0, 0] = np.inf
    return t.recon(cta=t.volume_file("ct.nrrd", a)), ["ct.nrrd", "NaN or infinite"]


@kind
def cta_nifti_huge_header(t):
    p = t.volume_file("ct.nii", np.zeros((8, 16, 16)))
    raw = bytearray(p.read_bytes())
    raw[42:48] = np.array([30000, 30000, 30000], "<i2").tobytes()  # dim[1..3] of the NIfTI-1 header
    p.write_bytes(bytes(raw))
    return t.recon(cta=p), ["ct.nii", "exceeds the limit"]


@kind
def cta_nifti_2d(t):
    import SimpleITK as sitk

    p = t.tmp / "slice.nii.gz"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((16, 16), np.float32)), str(p))
    return t.recon(cta=p), ["slice.nii.gz", "3D"]


# --- the XA files -----------------------------------------------------------------------------
@kind
def xa_missing(t):
    return t.recon(roadmap=t.tmp / "roadmap.dcm"), [str(t.tmp / "roadmap.dcm"), "no such file"]


@kind
def xa_dangling_symlink(t):
    (t.tmp / "frames.dcm").symlink_to(t.tmp / "moved.dcm")
    return t.recon(frames=t.tmp / "frames.dcm"), ["frames.dcm", "dangling"]


@kind
def xa_folder_without_frames(t):  # a folder where a file is expected (read as a PNG sequence)
    (t.tmp / "xa").mkdir()
    return t.recon(roadmap=t.tmp / "xa"), [str(t.tmp / "xa"), "no PNG/TIFF/JPEG frames"]


@kind
def xa_zero_byte_file(t):
    (t.tmp / "r.dcm").write_bytes(b"")
    return t.recon(roadmap=t.tmp / "r.dcm"), ["r.dcm", "0 bytes"]


@kind
def xa_fifo(t):
    os.mkfifo(t.tmp / "r.dcm")
    return t.recon(roadmap=t.tmp / "r.dcm"), ["r.dcm", "not a regular file"]


@kind
def xa_not_dicom(t):
    (t.tmp / "notes.dcm").write_text("hello, this is not DICOM\n" * 20)
    return t.recon(roadmap=t.tmp / "notes.dcm"), ["notes.dcm", "not a DICOM file"]


@kind
def xa_cut_to_300_bytes(t):
    p = t.truncated(t.case / "roadmap.dcm", 300)
    return t.recon(roadmap=p), ["roadmap.dcm", "truncated"]


@kind
def xa_truncated_in_pixels(t):
    p = t.truncated(t.case / "frames.dcm", 3 * (t.case / "frames.dcm").stat().st_size // 4)
    return t.recon(frames=p), ["frames.dcm", "truncated", "PixelData (7FE0,0010)"]


@kind
def xa_is_a_ct_slice(t):  # a CT where an XA is expected
    f = sorted((t.case / "ct").iterdir())[0]
    return t.recon(roadmap=f), [f.name, "Modality (0008,0060)", "CT"]


@kind
def xa_without_sid(t):
    return t.recon(roadmap=t.xa("r.dcm", _del("DistanceSourceToDetector"))), ["r.dcm", "DistanceSourceToDetector",
                                                                               "--sid"]


@kind
def xa_without_pixel_spacing(t):
    return t.recon(frames=t.xa("f.dcm", _del("ImagerPixelSpacing"), "frames.dcm")), ["f.dcm", "ImagerPixelSpacing"]


@kind
def xa_nan_angle(t):
    return t.recon(roadmap=t.xa("r.dcm", _set(PositionerPrimaryAngle="NaN"))), ["r.dcm", "PositionerPrimaryAngle",
                                                                                 "finite"]


@kind
def xa_negative_sod(t):
    return t.recon(roadmap=t.xa("r.dcm", _set(DistanceSourceToPatient="-700"))), ["r.dcm", "DistanceSourceToPatient",
                                                                                  "positive"]


@kind
def xa_sid_not_above_sod(t):
    p = t.xa("r.dcm", _set(DistanceSourceToDetector="700", DistanceSourceToPatient="750"))
    return t.recon(roadmap=p), ["r.dcm", "DistanceSourceToDetector must exceed DistanceSourceToPatient"]


@kind
def xa_pixel_spacing_zero(t):
    return t.recon(roadmap=t.xa("r.dcm", _set(ImagerPixelSpacing=["0", "0"]))), ["r.dcm", "ImagerPixelSpacing",
                                                                                  "positive"]


@kind
def xa_angle_out_of_range(t):
    return t.recon(roadmap=t.xa("r.dcm", _set(PositionerSecondaryAngle="120"))), ["r.dcm", "secondary 120"]


@kind
def xa_mislabelled_big_endian(t):  # little-endian data under the big-endian transfer syntax
    raw = bytearray((t.case / "roadmap.dcm").read_bytes())
    i = raw.find(b"1.2.840.10008.1.2.1\x00")
    raw[i:i + 20] = b"1.2.840.10008.1.2.2\x00"
    (t.tmp / "r.dcm").write_bytes(bytes(raw))
    return t.recon(roadmap=t.tmp / "r.dcm"), ["r.dcm", "PixelData"]


@kind
def xa_unknown_transfer_syntax(t):
    raw = bytearray((t.case / "roadmap.dcm").read_bytes())
    i = raw.find(b"1.2.840.10008.1.2.1\x00")
    raw[i:i + 20] = b"1.2.3.4.5.6.7.8.9.10"
    (t.tmp / "r.dcm").write_bytes(bytes(raw))
    return t.recon(roadmap=t.tmp / "r.dcm"), ["r.dcm", "cannot be decoded", "1.2.3.4.5.6.7.8.9.10"]


@kind
def xa_enhanced_without_geometry(t):
    def enhanced(ds):
        ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID = ENHANCED_XA_STORAGE
        _del(*GEOMETRY_TAGS)(ds)
        ds.SharedFunctionalGroupsSequence = [pydicom.Dataset()]
    return t.recon(roadmap=t.xa("r.dcm", enhanced)), ["r.dcm", "PositionerPrimaryAngle", "missing"]


@kind
def xa_garbage_frame_count(t):  # a header that promises far more pixels than the file holds
    return t.recon(frames=t.xa("f.dcm", _set(NumberOfFrames=100000), "frames.dcm")), ["f.dcm", "NumberOfFrames"]


@kind
def xa_without_rows(t):
    return t.recon(roadmap=t.xa("r.dcm", _del("Rows"))), ["r.dcm", "Rows (0028,0010)"]


@kind
def xa_two_samples_per_pixel(t):
    return t.recon(roadmap=t.xa("r.dcm", _set(SamplesPerPixel=2))), ["r.dcm", "SamplesPerPixel"]


@kind
def roadmap_all_zero(t):
    return t.recon(roadmap=t.xa("r.dcm", _pixels(np.zeros((1, 512, 512))))), ["r.dcm", "roadmap frame 0",
                                                                               "no contrast"]


@kind
def roadmap_noise(t):
    noise = np.random.default_rng(1).integers(0, 4000, (1, 512, 512))
    return t.recon(roadmap=t.xa("r.dcm", _pixels(noise))), ["r.dcm", "roadmap frame 0", "noise"]


@kind
def roadmap_frame_constant_in_a_run(t):
    frames = pydicom.dcmread(t.case / "frames.dcm").pixel_array.copy()
    frames[2] = 1000
    p = t.xa("f.dcm", _pixels(frames), "frames.dcm")
    return t.recon("--roadmap-frame", "2", roadmap=p, frames=p), ["f.dcm", "roadmap frame 2", "no contrast"]


# --- image sequences and videos with a JSON geometry sidecar -------------------------------------
@kind
def sequence_without_sidecar(t):
    return t.recon(frames=t.png_folder()), ["geometry.json", "sidecar missing"]


@kind
def sequence_sidecar_bad_json(t):
    return t.recon(frames=t.png_folder('{"sid_mm": 1000,')), ["geometry.json", "invalid JSON"]


@kind
def sequence_sidecar_not_an_object(t):
    return t.recon(frames=t.png_folder("[1, 2, 3]")), ["geometry.json", "JSON object"]


@kind
def sequence_sidecar_missing_key(t):
    geo = {k: v for k, v in GOOD_GEOMETRY.items() if k != "sod_mm"}
    return t.recon(frames=t.png_folder(geo)), ["geometry.json", "sod_mm"]


@kind
def sequence_sidecar_nan_geometry(t):
    return t.recon(frames=t.png_folder('{"primary_deg": 0, "secondary_deg": 0, "sid_mm": NaN, "sod_mm": 700, '
                                       '"pixel_mm": 0.3}')), ["geometry.json", "sid_mm", "finite"]


@kind
def sequence_sidecar_shape_mismatch(t):
    return t.recon(frames=t.png_folder(dict(GOOD_GEOMETRY, shape=[100, 100]))), ["geometry.json", "shape"]


@kind
def sequence_frames_of_different_sizes(t):
    return t.recon(frames=t.png_folder(GOOD_GEOMETRY, sizes=[(64, 64), (64, 80)])), ["f1.png", "differs"]


@kind
def video_without_sidecar(t):
    return t.recon(frames=t.video()), ["run.json", "sidecar missing"]


@kind
def video_unreadable(t):
    p = t.tmp / "run.mp4"
    p.write_bytes(np.random.default_rng(2).bytes(4000))
    (t.tmp / "run.mp4.json").write_text(json.dumps(GOOD_GEOMETRY))
    return t.recon(frames=p), ["run.mp4", "not a readable video"]


# --- command-line options -----------------------------------------------------------------------
@kind
def seed_lps_two_numbers(t):
    return t.recon("--seed-lps", "1,2"), ["--seed-lps", "x,y,z"]


@kind
def seed_lps_not_numbers(t):
    return t.recon("--seed-lps=a,b,c"), ["--seed-lps", "'a,b,c'"]


@kind
def seed_lps_outside_the_cta(t):
    return t.recon("--seed-lps=0,0,5000"), ["--seed-lps=0,0,5000", "outside the CTA"]


@kind
def seed_lps_outside_the_vessels(t):
    vol = io.read_volume(t.case / "ct")
    lo = vol.bounds_lps_mm[0] + 5.0
    assert vol.array_zyx[tuple(np.rint(vol.lps_to_index_zyx(lo[None])[0]).astype(int))] < 100  # soft tissue
    xyz = ",".join(f"{v:.1f}" for v in lo)
    return t.recon(f"--seed-lps={xyz}"), [f"--seed-lps={xyz}", "not inside a vessel"]


# reconstruct options with a bad value: kind -> (the options, the words the error names)
BAD_OPTIONS = {
    "roadmap_frame_too_large": (["--roadmap-frame", "99"], ["--roadmap-frame 99", "out of range"]),
    "roadmap_frame_negative": (["--roadmap-frame", "-1"], ["--roadmap-frame -1", "out of range"]),
    "sid_negative": (["--sid", "-5"], ["--sid -5", "positive"]),
    "sod_nan": (["--sod", "nan"], ["--sod nan", "finite"]),
    "sid_not_above_sod_options": (["--sid", "600", "--sod", "700"], ["--sid 600", "--sod 700"]),
    "sid_option_below_the_files_sod": (["--sid", "600"], ["roadmap.dcm", "--sid 600", "DistanceSourceToPatient"]),
    "primary_out_of_range": (["--primary", "200"], ["--primary 200", "out of range"]),
    "method_unknown": (["--method", "bogus"], ["--method", "bogus"]),
    "option_unknown": (["--frobnicate"], ["--frobnicate"]),
}
for _name, (_options, _words) in BAD_OPTIONS.items():
    KINDS[_name] = lambda t, options=_options, words=_words: (t.recon(*options), words)


@kind
def required_option_missing(t):
    return ["reconstruct", "--roadmap", "r.dcm", "--frames", "r.dcm", "--out", str(t.out)], ["--cta", "required"]


# --- the output folder ----------------------------------------------------------------------------
@kind
def out_parent_is_a_file(t):
    (t.tmp / "file").write_text("x")
    t.out = t.tmp / "file" / "out"
    return t.recon(), [str(t.out), "is a file"]


@kind
def out_is_a_file(t):
    t.out = t.tmp / "out.txt"
    t.out.write_text("mine")
    return t.recon(), ["out.txt", "not a folder"]


@kind
def out_not_empty(t):
    t.out = t.tmp / "full"
    t.out.mkdir()
    (t.out / "keep.txt").write_text("mine")
    return t.recon(), ["full", "not empty"]


@kind
def out_in_a_read_only_place(t):  # /sys refuses even root
    t.out = Path("/sys/guidewire3d-test/out")
    return t.recon(), [str(t.out), "cannot create"]


@kind
def out_name_too_long(t):
    t.out = t.tmp / ("o" * 250)
    return t.recon(), ["ooooo", "too long"]


@kind
def out_dangling_symlink(t):
    t.out = t.tmp / "out-link"
    t.out.symlink_to(t.tmp / "nowhere")
    return t.recon(), ["out-link", "dangling"]


# --- the other commands ---------------------------------------------------------------------------
@kind
def segment_dangling_symlink(t):
    (t.tmp / "a.png").symlink_to(t.tmp / "gone.png")
    return ["segment", str(t.tmp / "a.png"), "--out", str(t.out)], ["a.png", "dangling"]


@kind
def segment_zero_byte_image(t):
    (t.tmp / "a.png").write_bytes(b"")
    return ["segment", str(t.tmp / "a.png"), "--out", str(t.out)], ["a.png", "0 bytes"]


@kind
def segment_truncated_xa(t):
    p = t.truncated(t.case / "roadmap.dcm", 1000)
    return ["segment", str(p), "--out", str(t.out)], ["roadmap.dcm", "truncated"]


@kind
def phantom_seed_negative(t):
    return ["phantom", "--out", str(t.out), "--seed", "-3"], ["--seed", "non-negative"]


@kind
def phantom_no_frames(t):
    return ["phantom", "--out", str(t.out), "--frames", "0"], ["--frames", "1..500"]


@kind
def phantom_wire_too_thick(t):
    return ["phantom", "--out", str(t.out), "--wire-diameter", "3"], ["--wire-diameter", "0.1..1.2"]


@kind
def phantom_dose_zero(t):
    return ["phantom", "--out", str(t.out), "--dose", "0"], ["--dose"]


@kind
def demo_out_not_empty(t):  # the error is the only line (no "phantom case: ..." before it)
    t.out = t.tmp / "full"
    t.out.mkdir()
    (t.out / "keep.txt").write_text("mine")
    return ["demo", "--out", str(t.out)], ["full", "not empty"]


@kind
def demo_seed_negative(t):
    return ["demo", "--out", str(t.out), "--seed", "-1"], ["--seed -1"]


# ---------------------------------------------------------------------------------------------------
def leftovers(out: Path) -> list[str]:
    """What a run left beside ``out``: staging, probe or replaced folders."""
    if not out.parent.is_dir():
        return []
    return sorted(p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}."))


def assert_refused(rc: int, err: str, out: Path, words, *, out_existed: bool = False) -> None:
    """Exit 2, one line ``guidewire3d: error: ...`` naming ``words``, ``out`` not created, nothing beside it."""
    lines = err.split("\n")
    assert rc == 2, err
    assert len(lines) == 2 and lines[1] == "", f"not one line: {err!r}"
    assert lines[0].startswith("guidewire3d: error: "), err
    for w in words:
        assert w in lines[0], f"{w!r} not named in: {lines[0]}"
    if not out_existed:
        assert not out.exists() and not out.is_symlink(), f"{out} was written"
    assert leftovers(out) == [], leftovers(out)


def test_at_least_45_kinds_of_bad_input():
    assert len(KINDS) >= 45


@pytest.fixture
def kit(small_case_dir, tmp_path):
    return Kit(small_case_dir, tmp_path)


@pytest.mark.parametrize("name", list(KINDS))
def test_bad_input_one_line_exit_2_nothing_written(name, kit, capsys, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(kit.tmp / "cache"))  # demo: never touch the user's cache
    argv, words = KINDS[name](kit)
    existed = kit.out.exists() or kit.out.is_symlink()
    before = sorted(p.name for p in kit.out.iterdir()) if kit.out.is_dir() else None
    rc = main(argv)
    captured = capsys.readouterr()
    assert_refused(rc, captured.err, kit.out, words, out_existed=existed)
    assert captured.out == ""
    after = sorted(p.name for p in kit.out.iterdir()) if kit.out.is_dir() else None
    assert after == before  # a folder that was there is untouched
    assert not (kit.tmp / "cache").exists()


# --- as an unprivileged user (the tests run as root, who reads and writes anything) --------------
NOBODY = 65534


def _as_nobody(python, argv, cwd):
    """``guidewire3d argv`` run by user ``NOBODY`` with ``python`` and this environment's packages."""
    import sysconfig

    code = (f"import site, sys; site.addsitedir({sysconfig.get_paths()['purelib']!r}); "
            "from guidewire3d.app.cli import main; sys.exit(main(sys.argv[1:]))")
    env = dict(os.environ, HOME=str(cwd), XDG_CACHE_HOME=str(cwd / "cache"))
    return subprocess.run([python, "-c", code, *argv], user=NOBODY, group=NOBODY, extra_groups=[], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=120)


@pytest.fixture
def shared_dir():
    """(python, folder): a folder in /tmp that user ``NOBODY`` may use (pytest's tmp_path is root's
    only), and a Python of this version that ``NOBODY`` may run (this one may live in /root)."""
    import shutil
    import tempfile

    if os.geteuid() != 0:
        pytest.skip("needs root to run a command as another user")
    d = Path(tempfile.mkdtemp(prefix="gw3d-bad-input-"))
    d.chmod(0o777)
    v = f"{sys.version_info.major}.{sys.version_info.minor}"
    for python in (sys.executable, f"/usr/bin/python{v}", f"/usr/local/bin/python{v}"):
        try:
            ok = subprocess.run([python, "-c", "import os; assert os.getuid() > 0"], user=NOBODY, group=NOBODY,
                                extra_groups=[], cwd=d, capture_output=True, timeout=60).returncode == 0
        except OSError:
            ok = False
        if ok:
            break
    else:
        shutil.rmtree(d)
        pytest.skip(f"no Python {v} interpreter that user {NOBODY} may run")
    yield python, d
    shutil.rmtree(d, ignore_errors=True)


def test_unreadable_file_as_unprivileged_user(shared_dir, small_case_dir):
    python, shared_dir = shared_dir
    road = shared_dir / "roadmap.dcm"
    road.write_bytes((small_case_dir / "roadmap.dcm").read_bytes())
    road.chmod(0o000)
    out = shared_dir / "out"
    res = _as_nobody(python, ["reconstruct", "--cta", "ct", "--roadmap", str(road), "--frames", str(road),
                              "--out", str(out)], shared_dir)
    assert_refused(res.returncode, res.stderr, out, ["roadmap.dcm", "permission denied"])


def test_read_only_output_folder_as_unprivileged_user(shared_dir):
    python, shared_dir = shared_dir
    ro = shared_dir / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    out = ro / "out"
    res = _as_nobody(python, ["phantom", "--out", str(out), "--seed", "1"], shared_dir)
    assert_refused(res.returncode, res.stderr, out, [str(out), "Permission denied"])
    assert list(ro.iterdir()) == []


# --- unusual but valid inputs must read -----------------------------------------------------------
@pytest.fixture
def roadmap(small_case_dir):
    return io.read_xa(small_case_dir / "roadmap.dcm")


@pytest.mark.parametrize("syntax", ["RLELossless", "DeflatedExplicitVRLittleEndian", "ExplicitVRBigEndian",
                                    "ImplicitVRLittleEndian"])
def test_other_transfer_syntaxes_read_the_same_pixels(syntax, small_case_dir, roadmap, tmp_path):
    ds = pydicom.dcmread(small_case_dir / "roadmap.dcm")
    uid = getattr(pydicom.uid, syntax)
    p = tmp_path / "r.dcm"
    if syntax == "RLELossless":
        ds.compress(uid)
        ds.save_as(p)
    else:
        if not uid.is_little_endian:  # pydicom writes the pixel bytes as they are
            ds.PixelData = ds.pixel_array.astype(">u2").tobytes()
        ds.file_meta.TransferSyntaxUID = uid
        pydicom.dcmwrite(p, ds, implicit_vr=uid.is_implicit_VR, little_endian=uid.is_little_endian,
                         enforce_file_format=True)
    assert pydicom.dcmread(p).file_meta.TransferSyntaxUID == uid
    run = io.read_xa(p)
    assert np.array_equal(run.frames, roadmap.frames)
    assert run.carm.to_dict() == roadmap.carm.to_dict()


def test_rgb_single_frame_xa_reads_as_one_grey_frame(small_case_dir, roadmap, tmp_path):
    ds = pydicom.dcmread(small_case_dir / "roadmap.dcm")
    grey = (ds.pixel_array >> 4).astype(np.uint8)
    ds.SamplesPerPixel, ds.PhotometricInterpretation, ds.PlanarConfiguration = 3, "RGB", 0
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 8, 8, 7
    del ds.NumberOfFrames
    ds.PixelData = np.repeat(grey[..., None], 3, axis=-1).tobytes()
    ds.save_as(tmp_path / "rgb.dcm")
    run = io.read_xa(tmp_path / "rgb.dcm")
    assert run.frames.shape == (1, 512, 512)
    assert np.allclose(run.frames[0], grey, atol=0.01)  # luminance of a grey RGB is the grey


def test_enhanced_xa_with_geometry_in_functional_groups_reads(small_case_dir, roadmap, tmp_path):
    ds = pydicom.dcmread(small_case_dir / "roadmap.dcm")
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID = ENHANCED_XA_STORAGE
    positioner, geometry, detector = pydicom.Dataset(), pydicom.Dataset(), pydicom.Dataset()
    positioner.PositionerPrimaryAngle = ds.PositionerPrimaryAngle
    positioner.PositionerSecondaryAngle = ds.PositionerSecondaryAngle
    geometry.DistanceSourceToDetector = ds.DistanceSourceToDetector
    geometry.DistanceSourceToIsocenter = ds.DistanceSourceToPatient
    detector.ImagerPixelSpacing = ds.ImagerPixelSpacing
    for kw in GEOMETRY_TAGS:
        delattr(ds, kw)
    shared = pydicom.Dataset()
    shared.PositionerPositionSequence = [positioner]
    shared.XRayGeometrySequence = [geometry]
    shared.FrameDetectorParametersSequence = [detector]
    ds.SharedFunctionalGroupsSequence = [shared]
    ds.save_as(tmp_path / "enhanced.dcm")
    run = io.read_xa(tmp_path / "enhanced.dcm")
    assert np.array_equal(run.frames, roadmap.frames)
    assert np.allclose(run.carm.projection_matrix(), roadmap.carm.projection_matrix())


def test_lzw_tiff_16_bit_reads(tmp_path):
    import cv2

    from guidewire3d.app.batch2d import read_inputs

    img = np.random.default_rng(3).integers(0, 65535, (40, 56), dtype=np.uint16)
    p = tmp_path / "frame.tif"
    assert cv2.imwrite(str(p), img)  # OpenCV writes LZW-compressed TIFF by default
    assert p.read_bytes()[:2] in (b"II", b"MM")
    (im,) = read_inputs([p])
    assert np.array_equal(im.image, img)


# --- faults: killed runs, concurrent runs, a full disk ------------------------------------------------
def _holder(out: Path) -> subprocess.Popen:
    """Another process that holds ``out`` (its staging folder, with a few MB in it) until killed."""
    code = ("import sys, time\nfrom guidewire3d import io\n"
            "with io.staged_folder(sys.argv[1]) as s:\n"
            "    (s / 'vessels.stl').write_bytes(bytes(4 << 20))\n"
            "    print('ready', flush=True)\n"
            "    time.sleep(120)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    return proc


def test_second_run_into_the_same_out_is_refused_and_a_killed_runs_staging_is_cleaned(small_case_dir, tmp_path, capsys):
    out = tmp_path / "out"
    proc = _holder(out)
    try:
        assert leftovers(out) == [".out.staging"]
        rc = main(["reconstruct", "--cta", str(small_case_dir / "ct"), "--roadmap", str(small_case_dir / "roadmap.dcm"),
                   "--frames", str(small_case_dir / "frames.dcm"), "--out", str(out)])
        err = capsys.readouterr().err
        assert rc == 2 and err.count("\n") == 1 and f"pid {proc.pid}" in err and "another guidewire3d run" in err
        assert not out.exists() and leftovers(out) == [".out.staging"]  # the holder's, untouched
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
    assert leftovers(out) == [".out.staging"]  # what kill -9 leaves behind
    assert main(["phantom", "--out", str(out), "--seed", "4", "--frames", "1", "--no-ct", "--no-catheter"]) == 0
    assert leftovers(out) == [] and (out / "truth.json").is_file()


def test_stale_staging_folders_are_cleaned_and_live_ones_kept(tmp_path):
    out = tmp_path / "out"
    legacy_old = tmp_path / ".out.staging-abc123"  # mkdtemp name of earlier versions, 2 hours old
    legacy_new = tmp_path / ".out.staging-def456"  # the same, written a minute ago (may still be running)
    other_dead = tmp_path / ".other.staging"  # another output's staging folder, its process gone
    other_alive = tmp_path / ".third.staging"  # another output's, its process alive (this one)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    for d, pid in ((legacy_old, None), (legacy_new, None), (other_dead, int(dead.stdout)), (other_alive, os.getpid())):
        d.mkdir()
        (d / "data.bin").write_bytes(b"0" * 1000)
        if pid is not None:
            (d / io.STAGING_OWNER).write_text(json.dumps({**io._owner_record(), "pid": pid,
                                                          "start": io._process_start(pid)}))
    two_hours_ago = time.time() - 7200
    os.utime(legacy_old, (two_hours_ago, two_hours_ago))
    removed = io.clean_stale_staging(out)
    assert sorted(p.name for p in removed) == [".other.staging", ".out.staging-abc123"]
    assert legacy_new.exists() and other_alive.exists()


def test_output_filled_by_something_else_during_the_run_is_not_replaced(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(OutputError, match="filled by something else"):
        with io.staged_folder(out) as staging:
            (staging / "report.json").write_text("{}")
            out.mkdir()
            (out / "theirs.txt").write_text("theirs")
    assert sorted(p.name for p in out.iterdir()) == ["theirs.txt"]
    assert leftovers(out) == []


def test_full_disk_while_writing_is_one_line_and_leaves_nothing(small_case_dir, tmp_path, monkeypatch, capsys):
    import errno

    from guidewire3d.app import export
    from guidewire3d.app import pipeline

    class Result:  # what pipeline.run returns, as far as run_to_outdir looks
        roadmap_frame_index = 0
        timing = {}

    def full_disk(result, staging, **kw):
        (staging / "vessels.stl").write_bytes(bytes(1 << 20))
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(staging / "guidewire_0000.vtp"))

    monkeypatch.setattr(pipeline, "run", lambda *a, **k: Result())
    monkeypatch.setattr(export, "write_outdir", full_disk)
    out = tmp_path / "deep" / "out"
    rc = main(["reconstruct", "--cta", str(small_case_dir / "ct"), "--roadmap", str(small_case_dir / "roadmap.dcm"),
               "--frames", str(small_case_dir / "frames.dcm"), "--out", str(out)])
    assert_refused(rc, capsys.readouterr().err, out, [str(out), "No space left on device"])
    assert not (tmp_path / "deep").exists()  # the parent it created is gone too


def test_nearly_full_disk_is_refused_before_the_work(small_case_dir, tmp_path, monkeypatch, capsys):
    import shutil

    from guidewire3d.app import pipeline

    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(io.shutil, "disk_usage", lambda p: usage._replace(free=5 << 20))
    monkeypatch.setattr(pipeline, "load_inputs", lambda *a, **k: pytest.fail("inputs read before the disk check"))
    out = tmp_path / "out"
    rc = main(["reconstruct", "--cta", str(small_case_dir / "ct"), "--roadmap", str(small_case_dir / "roadmap.dcm"),
               "--frames", str(small_case_dir / "frames.dcm"), "--out", str(out)])
    assert_refused(rc, capsys.readouterr().err, out, [str(out), "only 5 MB free", f"{pipeline.MIN_FREE_MB} MB needed"])


def test_error_after_a_progress_bar_starts_on_its_own_line(small_case_dir, tmp_path, monkeypatch, capsys):
    """A late error (here: no vessels near the seed, found in the vessel stage) closes the bar first."""
    from tqdm import tqdm

    from guidewire3d.app import pipeline
    from guidewire3d.errors import SegmentationError

    def vessel_stage(*a, **k):
        bar = tqdm(total=4, desc="vessels: segment", file=sys.stderr, leave=False)
        bar.update()
        raise SegmentationError("ct: no vessels found within 3 mm of the seeds")

    monkeypatch.setattr(pipeline, "run", vessel_stage)
    out = tmp_path / "out"
    rc = main(["reconstruct", "--cta", str(small_case_dir / "ct"), "--roadmap", str(small_case_dir / "roadmap.dcm"),
               "--frames", str(small_case_dir / "frames.dcm"), "--out", str(out)])
    err = capsys.readouterr().err
    bar, line, end = err.split("\n")  # not a terminal: the bar's line is ended before the error
    assert rc == 2 and "vessels: segment" in bar and end == ""
    assert line == "guidewire3d: error: ct: no vessels found within 3 mm of the seeds"
    assert not out.exists() and leftovers(out) == []
