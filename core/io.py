"""File input and output: CTA volumes (DICOM series, NIfTI, NRRD, MHA) and XA runs (DICOM).

This is the only module that reads files. Every failure raises a ``Guidewire3DError``
subclass whose message names the file and the field.

Conventions
-----------
* ``Volume.array_zyx`` is indexed ``[z, y, x]`` (slice, row, column), float32 HU.
* ``Volume.spacing_mm`` and ``Volume.origin_lps_mm`` are in ``(x, y, z)`` order, as SimpleITK
  gives them; ``Volume.direction`` is the 3x3 matrix whose columns are the x, y, z index axes
  in LPS.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from guidewire3d.errors import DicomError, GeometryError, InputError
from guidewire3d.geometry import CArm

__all__ = [
    "Volume",
    "XARun",
    "read_volume",
    "write_volume",
    "write_ct_series",
    "read_xa",
    "write_xa",
    "read_image_sequence",
    "atomic_write_bytes",
    "atomic_write_text",
    "CT_IMAGE_STORAGE",
    "XA_IMAGE_STORAGE",
]

CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
XA_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.12.1"
RF_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.12.2"

MAX_VOXELS_DEFAULT = 512 * 512 * 1200


# --------------------------------------------------------------------------------------
# atomic writes
# --------------------------------------------------------------------------------------
def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _chmod_default(path, *, directory: bool = False) -> None:
    """Give a temporary file (mkstemp: 0600) or folder (mkdtemp: 0700) the usual permissions."""
    os.chmod(path, (0o777 if directory else 0o666) & ~_umask())


def atomic_write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder, then rename."""
    return atomic_write_via(path, lambda tmp: Path(tmp).write_bytes(data))


def atomic_write_text(path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def require_empty_folder(out_dir) -> Path:
    """``out_dir`` as a Path; InputError if it exists and is not an empty folder."""
    out_dir = Path(out_dir)
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise InputError(f"{out_dir}: output folder exists and is not empty")
    return out_dir


def write_folder_atomically(out_dir, writer) -> Path:
    """Call ``writer(staging)`` for a new temporary sibling folder of ``out_dir``, then rename it
    to ``out_dir`` (replacing an existing ``out_dir``: the caller decides whether that is allowed).
    On any error the staging folder is removed and ``out_dir`` is untouched."""
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.staging-", dir=out_dir.parent))
    try:
        writer(staging)
        _chmod_default(staging, directory=True)
        if out_dir.exists():
            old = out_dir.with_name(f".{out_dir.name}.old-{int(time.time() * 1e6)}")
            out_dir.rename(old)
            staging.rename(out_dir)
            shutil.rmtree(old, ignore_errors=True)
        else:
            staging.rename(out_dir)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return out_dir


def atomic_write_via(path, writer) -> Path:
    """Call ``writer(tmp_path)`` for a temporary sibling of ``path``, then rename it into place.

    The temporary name keeps the final suffix so that writers that dispatch on it still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.tmp.", suffix="".join(path.suffixes) or ".tmp", dir=path.parent)
    os.close(fd)
    try:
        writer(tmp)
        _chmod_default(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


# --------------------------------------------------------------------------------------
# volumes
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Volume:
    """A CT volume in HU with its placement in patient LPS (mm)."""

    array_zyx: np.ndarray
    spacing_mm: tuple[float, float, float]  # (x, y, z)
    origin_lps_mm: tuple[float, float, float]  # (x, y, z) of voxel [0, 0, 0]
    direction: np.ndarray = field(default_factory=lambda: np.eye(3))  # columns = index axes in LPS
    source: str = ""
    series_uid: str = ""

    def __post_init__(self):
        a = np.asarray(self.array_zyx)
        if a.ndim != 3 or min(a.shape) < 1:
            raise InputError(f"{self.source or 'volume'}: expected a 3D array, got shape {a.shape}")
        sp = tuple(float(s) for s in self.spacing_mm)
        if len(sp) != 3 or min(sp) <= 0 or not np.all(np.isfinite(sp)):
            raise InputError(f"{self.source or 'volume'}: spacing must be 3 positive numbers, got {self.spacing_mm}")
        org = tuple(float(s) for s in self.origin_lps_mm)
        D = np.asarray(self.direction, dtype=float).reshape(3, 3)
        if abs(abs(np.linalg.det(D)) - 1) > 1e-3:
            raise InputError(f"{self.source or 'volume'}: direction matrix is not orthonormal")
        a.setflags(write=False)
        D = D.copy()
        D.setflags(write=False)
        object.__setattr__(self, "array_zyx", a)
        object.__setattr__(self, "spacing_mm", sp)
        object.__setattr__(self, "origin_lps_mm", org)
        object.__setattr__(self, "direction", D)

    @property
    def shape_zyx(self) -> tuple[int, int, int]:
        return tuple(self.array_zyx.shape)

    @property
    def affine_lps(self) -> np.ndarray:
        """4x4 matrix mapping homogeneous index ``(x, y, z, 1)`` to LPS mm."""
        A = np.eye(4)
        A[:3, :3] = self.direction @ np.diag(self.spacing_mm)
        A[:3, 3] = self.origin_lps_mm
        return A

    def index_zyx_to_lps(self, idx_zyx) -> np.ndarray:
        """``(N, 3)`` continuous ``(z, y, x)`` indices -> ``(N, 3)`` LPS mm."""
        idx = np.asarray(idx_zyx, dtype=float)[..., ::-1]
        A = self.affine_lps
        return idx @ A[:3, :3].T + A[:3, 3]

    def lps_to_index_zyx(self, points_lps_mm) -> np.ndarray:
        """``(N, 3)`` LPS mm -> continuous ``(z, y, x)`` indices."""
        p = np.asarray(points_lps_mm, dtype=float)
        A = self.affine_lps
        ijk = (p - A[:3, 3]) @ np.linalg.inv(A[:3, :3]).T
        return ijk[..., ::-1]

    @property
    def bounds_lps_mm(self) -> np.ndarray:
        """``(2, 3)`` min and max LPS corner of the voxel-centre grid."""
        nz, ny, nx = self.shape_zyx
        corners = np.array([[z, y, x] for z in (0, nz - 1) for y in (0, ny - 1) for x in (0, nx - 1)], float)
        pts = self.index_zyx_to_lps(corners)
        return np.vstack([pts.min(0), pts.max(0)])

    def to_sitk(self):
        import SimpleITK as sitk

        img = sitk.GetImageFromArray(np.ascontiguousarray(self.array_zyx))
        img.SetSpacing(self.spacing_mm)
        img.SetOrigin(self.origin_lps_mm)
        img.SetDirection(tuple(np.asarray(self.direction).ravel()))
        return img

    @classmethod
    def from_sitk(cls, img, *, source: str = "", series_uid: str = "") -> "Volume":
        import SimpleITK as sitk

        if img.GetDimension() != 3:
            raise InputError(f"{source}: expected a 3D image, got {img.GetDimension()}D")
        if img.GetNumberOfComponentsPerPixel() != 1:
            raise InputError(f"{source}: expected a scalar image, got {img.GetNumberOfComponentsPerPixel()} components")
        arr = sitk.GetArrayFromImage(img).astype(np.float32, copy=False)
        return cls(
            arr,
            img.GetSpacing(),
            img.GetOrigin(),
            np.asarray(img.GetDirection(), float).reshape(3, 3),
            source=source,
            series_uid=series_uid,
        )


def _sitk_quiet():
    import SimpleITK as sitk

    sitk.ProcessObject_SetGlobalWarningDisplay(False)
    return sitk


def _dicom_series_in(folder: Path) -> dict[str, list[str]]:
    sitk = _sitk_quiet()
    reader = sitk.ImageSeriesReader()
    out = {}
    for uid in reader.GetGDCMSeriesIDs(str(folder)) or ():
        files = reader.GetGDCMSeriesFileNames(str(folder), uid)
        if files:
            out[uid] = list(files)
    return out


def _check_slice_geometry(files: list[str], folder: Path) -> None:
    """Refuse gantry tilt and uneven slice spacing instead of misplacing slices."""
    import pydicom

    ipps, iop = [], None
    for f in files:
        try:
            ds = pydicom.dcmread(f, stop_before_pixels=True)
        except Exception as e:  # noqa: BLE001
            raise DicomError(f"{f}: unreadable DICOM header ({e.__class__.__name__})") from None
        if "ImagePositionPatient" not in ds:
            raise DicomError(f"{f}: missing ImagePositionPatient (0020,0032)")
        if "ImageOrientationPatient" not in ds:
            raise DicomError(f"{f}: missing ImageOrientationPatient (0020,0037)")
        ipps.append([float(x) for x in ds.ImagePositionPatient])
        iop = [float(x) for x in ds.ImageOrientationPatient]
    if len(files) < 2:
        raise DicomError(f"{folder}: a CT series needs at least 2 slices, found {len(files)}")
    row, col = np.array(iop[:3]), np.array(iop[3:])
    normal = np.cross(row, col)
    ipps = np.array(ipps)
    pos = ipps @ normal
    order = np.argsort(pos)
    ipps, pos = ipps[order], pos[order]
    steps = np.diff(pos)
    if np.any(steps < 1e-6):
        raise DicomError(f"{folder}: duplicate slice positions (ImagePositionPatient) in the series")
    if np.ptp(steps) > 0.01 * max(np.median(steps), 1e-6) + 1e-3:
        raise DicomError(
            f"{folder}: uneven slice spacing (ImagePositionPatient steps {steps.min():.3f}..{steps.max():.3f} mm); "
            "resample the series to even spacing first"
        )
    # gantry tilt: consecutive positions must move along the slice normal
    d = ipps[-1] - ipps[0]
    off_axis = np.linalg.norm(d - (d @ normal) * normal)
    if off_axis > 0.01 * np.linalg.norm(d) + 1e-3:
        raise DicomError(
            f"{folder}: gantry tilt detected (slices not stacked along ImageOrientationPatient normal); "
            "resample the series first"
        )


def read_volume(path, *, series_uid: str | None = None, max_voxels: int = MAX_VOXELS_DEFAULT, log=None) -> Volume:
    """Read a CTA: a DICOM series folder (or one of its files), or a NIfTI/NRRD/MHA file.

    If a folder holds several series, the CT series with the most slices is read (and ``log``
    is told); ``series_uid`` chooses one explicitly.
    """
    path = Path(path)
    sitk = _sitk_quiet()
    if not path.exists():
        raise InputError(f"{path}: no such file or directory")
    if path.is_file() and not _looks_like_dicom(path):
        try:
            img = sitk.ReadImage(str(path), sitk.sitkFloat32)
        except RuntimeError:
            raise InputError(f"{path}: not a readable volume (expected DICOM, NIfTI, NRRD or MHA)") from None
        vol = Volume.from_sitk(img, source=str(path))
        _check_size(vol, path, max_voxels)
        return vol
    folder = path if path.is_dir() else path.parent
    series = _dicom_series_in(folder)
    if not series:
        if path.is_dir() and not any(folder.iterdir()):
            raise InputError(f"{folder}: empty directory, expected a DICOM CT series")
        raise DicomError(f"{folder}: no readable DICOM series found")
    if series_uid is not None:
        if series_uid not in series:
            raise DicomError(f"{folder}: SeriesInstanceUID {series_uid} not found (have {', '.join(series)})")
        uid = series_uid
    else:
        import pydicom

        cands = []
        for uid, files in series.items():
            try:
                ds = pydicom.dcmread(files[0], stop_before_pixels=True)
            except Exception:  # noqa: BLE001
                continue
            modality = str(getattr(ds, "Modality", "")).strip()
            cands.append((modality == "CT", len(files), uid, modality))
        if not cands:
            raise DicomError(f"{folder}: no readable DICOM series found")
        cands.sort(reverse=True)
        is_ct, _, uid, modality = cands[0]
        if not is_ct:
            raise DicomError(f"{folder}: no CT series found (Modality is {modality or 'missing'}), expected a CTA")
        if len(series) > 1 and log is not None:
            log(f"{folder}: {len(series)} series found, using the largest CT series {uid} ({len(series[uid])} slices)")
    files = series[uid]
    _check_slice_geometry(files, folder)
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files)
    reader.SetOutputPixelType(sitk.sitkFloat32)
    try:
        img = reader.Execute()
    except RuntimeError as e:
        raise DicomError(f"{folder}: could not read the DICOM series ({str(e).strip().splitlines()[-1][:120]})") from None
    vol = Volume.from_sitk(img, source=str(folder), series_uid=uid)
    _check_size(vol, folder, max_voxels)
    return vol


def _check_size(vol: Volume, path, max_voxels: int) -> None:
    n = int(np.prod(vol.shape_zyx))
    if n > max_voxels:
        raise InputError(
            f"{path}: volume of {vol.shape_zyx} voxels exceeds the limit of {max_voxels} voxels; "
            "crop or downsample it first"
        )


def _looks_like_dicom(path: Path) -> bool:
    if path.suffix.lower() in (".dcm", ".dicom"):
        return True
    try:
        with open(path, "rb") as f:
            head = f.read(132)
        return head[128:132] == b"DICM"
    except OSError:
        return False


def write_volume(vol: Volume, path) -> Path:
    """Write a NIfTI/NRRD/MHA file atomically (format from the suffix)."""
    sitk = _sitk_quiet()
    img = vol.to_sitk()
    return atomic_write_via(path, lambda tmp: sitk.WriteImage(img, str(tmp), True))


def _new_uid() -> str:
    from pydicom.uid import generate_uid

    return generate_uid()


def write_ct_series(vol: Volume, out_dir, *, patient_name: str = "Phantom^Guidewire3D", patient_id: str = "GW3D",
                    study_uid: str | None = None, series_uid: str | None = None,
                    description: str = "guidewire3d phantom CTA") -> Path:
    """Write ``vol`` as a DICOM CT series (one file per slice, int16 HU, rescale 1/0).

    The files go to a temporary folder that is renamed to ``out_dir`` when complete.
    """
    sitk = _sitk_quiet()
    out_dir = require_empty_folder(out_dir)
    study_uid = study_uid or _new_uid()
    series_uid = series_uid or _new_uid()
    frame_uid = _new_uid()
    arr = np.clip(np.rint(vol.array_zyx), -32768, 32767).astype(np.int16)
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing(vol.spacing_mm)
    img.SetOrigin(vol.origin_lps_mm)
    D = np.asarray(vol.direction)
    img.SetDirection(tuple(D.ravel()))
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    iop = "\\".join(f"{v:.6f}" for v in (*D[:, 0], *D[:, 1]))
    common = {
        "0008|0060": "CT",
        "0008|0016": CT_IMAGE_STORAGE,
        "0008|103e": description,
        "0010|0010": patient_name,
        "0010|0020": patient_id,
        "0020|000d": study_uid,
        "0020|000e": series_uid,
        "0020|0052": frame_uid,
        "0020|0011": "1",
        "0020|0037": iop,
        "0018|0050": f"{vol.spacing_mm[2]:.6f}",
        "0028|1052": "0",
        "0028|1053": "1",
        "0028|1054": "HU",
        "0008|0008": "ORIGINAL\\PRIMARY\\AXIAL",
    }

    def write(tmp_dir: Path) -> None:
        for k in range(arr.shape[0]):
            sl = img[:, :, k]
            for tag, value in common.items():
                sl.SetMetaData(tag, value)
            pos = img.TransformIndexToPhysicalPoint((0, 0, k))
            sl.SetMetaData("0020|0032", "\\".join(f"{v:.6f}" for v in pos))
            sl.SetMetaData("0020|0013", str(k + 1))
            sl.SetMetaData("0020|1041", f"{float(np.dot(pos, np.cross(D[:, 0], D[:, 1]))):.6f}")
            sl.SetMetaData("0008|0018", _new_uid())
            writer.SetFileName(str(tmp_dir / f"CT{k + 1:04d}.dcm"))
            writer.Execute(sl)

    return write_folder_atomically(out_dir, write)


# --------------------------------------------------------------------------------------
# XA runs
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class XARun:
    """An X-ray angiography run: frames ``(T, rows, cols)`` float32 and its C-arm view."""

    frames: np.ndarray
    carm: CArm
    source: str = ""
    frame_time_ms: float | None = None

    def __post_init__(self):
        f = np.asarray(self.frames, dtype=np.float32)
        if f.ndim == 2:
            f = f[None]
        if f.ndim != 3:
            raise InputError(f"{self.source}: expected frames (T, rows, cols), got {f.shape}")
        if tuple(f.shape[1:]) != tuple(self.carm.shape):
            raise InputError(f"{self.source}: frame size {f.shape[1:]} does not match the C-arm shape {self.carm.shape}")
        f.setflags(write=False)
        object.__setattr__(self, "frames", f)

    @property
    def n_frames(self) -> int:
        return len(self.frames)


_XA_TAGS = {
    "primary_deg": ("PositionerPrimaryAngle", "(0018,1510)"),
    "secondary_deg": ("PositionerSecondaryAngle", "(0018,1511)"),
    "sid_mm": ("DistanceSourceToDetector", "(0018,1110)"),
    "sod_mm": ("DistanceSourceToPatient", "(0018,1111)"),
    "pixel_mm": ("ImagerPixelSpacing", "(0018,1164)"),
}


def read_xa(path, *, overrides: dict | None = None) -> XARun:
    """Read a single- or multi-frame XA/RF DICOM file and its C-arm geometry.

    ``overrides`` maps ``primary_deg``, ``secondary_deg``, ``sid_mm``, ``sod_mm``,
    ``pixel_mm`` to values that replace (or supply missing) tags.
    """
    path = Path(path)
    ds, frames = _read_xa_pixels(path)
    carm = _xa_carm(path, ds, {k: v for k, v in (overrides or {}).items() if v is not None})
    ft = getattr(ds, "FrameTime", None)
    return XARun(frames, carm, source=str(path), frame_time_ms=float(ft) if ft not in (None, "") else None)


def read_xa_frames(path) -> tuple[np.ndarray, CArm | None]:
    """The frames ``(T, rows, cols)`` float32 (MONOCHROME2) of an XA/RF DICOM file, and its C-arm
    view if the geometry tags are all present and valid (else None): for 2D analysis, which does
    not need the geometry."""
    path = Path(path)
    ds, frames = _read_xa_pixels(path)
    try:
        carm = _xa_carm(path, ds, {})
    except (DicomError, GeometryError):
        carm = None
    return frames, carm


def _read_xa_pixels(path: Path):
    """(dataset, frames float32 (T, rows, cols), rescaled, MONOCHROME1 inverted) of an XA/RF file."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.is_dir():
        raise InputError(f"{path}: is a directory, expected an XA DICOM file")
    try:
        ds = pydicom.dcmread(str(path))
    except InvalidDicomError:
        raise DicomError(f"{path}: not a DICOM file") from None
    except Exception as e:  # noqa: BLE001
        raise DicomError(f"{path}: unreadable DICOM ({e.__class__.__name__}: {str(e)[:100]})") from None
    modality = str(getattr(ds, "Modality", "")).strip()
    if modality not in ("XA", "RF"):
        raise DicomError(f"{path}: Modality (0008,0060) is {modality or 'missing'!r}, expected XA or RF")
    for tag in ("Rows", "Columns"):
        if tag not in ds:
            raise DicomError(f"{path}: missing {tag}")
    if "PixelData" not in ds:
        raise DicomError(f"{path}: missing PixelData (7FE0,0010)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            arr = ds.pixel_array
    except Exception as e:  # noqa: BLE001
        raise DicomError(f"{path}: PixelData cannot be decoded ({e.__class__.__name__}: {str(e)[:120]})") from None
    arr = np.asarray(arr)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise DicomError(f"{path}: PixelData must be monochrome frames, got array shape {arr.shape}")
    frames = arr.astype(np.float32)
    slope = float(getattr(ds, "RescaleSlope", 1.0) or 1.0)
    intercept = float(getattr(ds, "RescaleIntercept", 0.0) or 0.0)
    if slope != 1.0 or intercept != 0.0:
        frames = frames * slope + intercept
    if str(getattr(ds, "PhotometricInterpretation", "MONOCHROME2")).strip() == "MONOCHROME1":
        frames = frames.max() - frames
    return ds, frames


def _xa_carm(path: Path, ds, overrides: dict) -> CArm:
    """The C-arm view of an XA dataset from its tags (``overrides`` replace or supply them)."""
    vals = {}
    for key, (kw, tag) in _XA_TAGS.items():
        if key in overrides:
            vals[key] = float(overrides[key])
            continue
        if kw not in ds or ds.data_element(kw).value in (None, ""):
            raise DicomError(f"{path}: missing {kw} {tag} (supply it with --{key.split('_')[0]})")
        v = ds.data_element(kw).value
        try:
            vals[key] = float(v[0] if key == "pixel_mm" and hasattr(v, "__len__") and not isinstance(v, str) else v)
        except (TypeError, ValueError, IndexError):
            raise DicomError(f"{path}: {kw} {tag} is not a number: {v!r}") from None
    try:
        return CArm(shape=(int(ds.Rows), int(ds.Columns)), **vals)
    except GeometryError as e:
        raise GeometryError(f"{path}: {e}") from None


def write_xa(path, frames, carm: CArm, *, frame_time_ms: float = 66.7, patient_name: str = "Phantom^Guidewire3D",
             patient_id: str = "GW3D", study_uid: str | None = None, description: str = "guidewire3d phantom XA",
             extra: dict | None = None) -> Path:
    """Write frames ``(T, rows, cols)`` (values 0..65535) as one multi-frame XA DICOM file."""
    import pydicom
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian

    frames = np.asarray(frames)
    if frames.ndim == 2:
        frames = frames[None]
    if tuple(frames.shape[1:]) != tuple(carm.shape):
        raise InputError(f"{path}: frames {frames.shape[1:]} do not match C-arm shape {carm.shape}")
    data = np.clip(np.rint(frames), 0, 65535).astype(np.uint16)
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = XA_IMAGE_STORAGE
    sop_uid = _new_uid()
    meta.MediaStorageSOPInstanceUID = sop_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = pydicom.uid.PYDICOM_IMPLEMENTATION_UID
    ds = FileDataset(str(path), {}, file_meta=meta, preamble=b"\0" * 128)
    ds.SOPClassUID = XA_IMAGE_STORAGE
    ds.SOPInstanceUID = sop_uid
    ds.Modality = "XA"
    ds.PatientName = patient_name
    ds.PatientID = patient_id
    ds.StudyInstanceUID = study_uid or _new_uid()
    ds.SeriesInstanceUID = _new_uid()
    ds.SeriesDescription = description
    ds.SeriesNumber = 1
    ds.InstanceNumber = 1
    ds.ImageType = ["ORIGINAL", "PRIMARY", "SINGLE PLANE"]
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = int(carm.rows), int(carm.cols)
    ds.NumberOfFrames = int(data.shape[0])
    ds.FrameIncrementPointer = pydicom.tag.Tag(0x0018, 0x1063)
    ds.FrameTime = f"{frame_time_ms:.1f}"
    ds.BitsAllocated = 16
    ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 0
    ds.PositionerPrimaryAngle = f"{carm.primary_deg:.4f}"
    ds.PositionerSecondaryAngle = f"{carm.secondary_deg:.4f}"
    ds.DistanceSourceToDetector = f"{carm.sid_mm:.4f}"
    ds.DistanceSourceToPatient = f"{carm.sod_mm:.4f}"
    ds.ImagerPixelSpacing = [f"{carm.pixel_mm:.6f}", f"{carm.pixel_mm:.6f}"]
    ds.PatientOrientation = ["L", "F"] if abs(carm.primary_deg) < 1e-6 and abs(carm.secondary_deg) < 1e-6 else ""
    for k, v in (extra or {}).items():
        setattr(ds, k, v)
    ds.PixelData = data.tobytes()

    def _save(tmp):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds.save_as(tmp, enforce_file_format=True)

    return atomic_write_via(path, _save)


def read_image_sequence(path) -> XARun:
    """Read a folder of PNG/TIFF frames (sorted by name) or a video, with a JSON geometry sidecar.

    The sidecar is ``geometry.json`` inside the folder, or ``<video>.json`` beside a video, with
    the keys of ``CArm.to_dict`` (``shape`` may be omitted: it is taken from the frames).
    """
    import cv2

    path = Path(path)
    if path.is_dir():
        sidecar = path / "geometry.json"
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in (".png", ".tif", ".tiff", ".jpg", ".jpeg"))
        if not files:
            raise InputError(f"{path}: no PNG/TIFF/JPEG frames found")
        frames = []
        for f in files:
            im = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            if im is None:
                raise InputError(f"{f}: unreadable image")
            if im.ndim == 3:
                im = cv2.cvtColor(im, cv2.COLOR_BGR2GRAY)
            frames.append(im.astype(np.float32))
        if len({fr.shape for fr in frames}) != 1:
            raise InputError(f"{path}: frames have different sizes")
        frames = np.stack(frames)
    elif path.is_file():
        sidecar = path.with_suffix(path.suffix + ".json")
        if not sidecar.exists():
            sidecar = path.with_suffix(".json")
        cap = cv2.VideoCapture(str(path))
        frames = []
        while True:
            ok, im = cap.read()
            if not ok:
                break
            frames.append(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY).astype(np.float32))
        cap.release()
        if not frames:
            raise InputError(f"{path}: not a readable video")
        frames = np.stack(frames)
    else:
        raise InputError(f"{path}: no such file or directory")
    if not sidecar.exists():
        raise InputError(f"{sidecar}: geometry sidecar missing (JSON with primary_deg, secondary_deg, sid_mm, sod_mm, pixel_mm)")
    try:
        geo = json.loads(sidecar.read_text())
    except json.JSONDecodeError as e:
        raise InputError(f"{sidecar}: invalid JSON ({e.msg} at line {e.lineno})") from None
    geo = dict(geo)
    geo.setdefault("shape", list(frames.shape[1:]))
    try:
        carm = CArm.from_dict(geo)
    except GeometryError as e:
        raise GeometryError(f"{sidecar}: {e}") from None
    return XARun(frames, carm, source=str(path))
