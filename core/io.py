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
import socket
import tempfile
import time
import warnings
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from stat import S_ISREG

import numpy as np
from guidewire3d import __version__
from guidewire3d.errors import DicomError, GeometryError, InputError, OutputError
from guidewire3d.geometry import CArm

__all__ = [
    "Volume",
    "XARun",
    "read_volume",
    "volume_files",
    "file_fingerprints",
    "write_volume",
    "write_dicom_seg",
    "affine_of",
    "write_ct_series",
    "read_xa",
    "write_xa",
    "read_image_sequence",
    "atomic_write_bytes",
    "atomic_write_text",
    "require_empty_folder",
    "staged_folder",
    "write_folder_atomically",
    "clean_stale_staging",
    "CT_IMAGE_STORAGE",
    "XA_IMAGE_STORAGE",
    "XRAY_3D_STORAGE",
    "VOLUME_MODALITIES",
]

CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
XA_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.12.1"
RF_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.12.2"

#: SOP classes of an X-ray volume (a C-arm's 3D rotational angiogram, stored with Modality XA): X-Ray 3D Angiographic
#: and Craniofacial Image Storage. Read as a vessel volume, whatever their Modality.
XRAY_3D_STORAGE = ("1.2.840.10008.5.1.4.1.1.13.1.1", "1.2.840.10008.5.1.4.1.1.13.1.2")
#: the DICOM Modality values of a vessel volume: a CTA (or a 3DRA stored as CT), an MR angiogram
VOLUME_MODALITIES = ("CT", "MR")

MAX_VOXELS_DEFAULT = 512 * 512 * 1200
STAGING_OWNER = ".guidewire3d-owner.json"  # inside a staging folder: the pid of the run writing it
STALE_HOURS = 1.0  # a staging folder without an owner record is stale after this long
#: a stack of slices is even when no slice lies farther than this fraction of the mean step from an even stack between
#: the first and the last (as SimpleITK places them): positions written with few decimals are not uneven
SLICE_POSITION_TOLERANCE = 0.1


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


def _owner_record() -> dict:
    return {"pid": os.getpid(), "host": socket.gethostname(), "start": _process_start(os.getpid()),
            "time": time.time()}


def _process_start(pid: int) -> str | None:
    """The start time of process ``pid`` in clock ticks since boot (Linux), to tell a reused pid."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat[stat.rfind(")") + 2:].split()
    return fields[19] if len(fields) > 19 and fields[0] != "Z" else "zombie"


def _owner_alive(owner: dict) -> bool:
    """Whether the process that wrote ``owner`` (a staging folder's owner record) still runs.

    A record of another host counts as alive (its process cannot be checked from here)."""
    if owner.get("host") != socket.gethostname():
        return True
    pid = owner.get("pid")
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    start = _process_start(pid)
    if start == "zombie":
        return False
    return start is None or owner.get("start") in (None, start)


def _read_owner(folder: Path) -> dict | None:
    try:
        owner = json.loads((folder / STAGING_OWNER).read_text())
    except (OSError, ValueError):
        return None
    return owner if isinstance(owner, dict) else None


def _staging_path(out_abs: Path) -> Path:
    return out_abs.with_name(f".{out_abs.name}.staging")


def clean_stale_staging(out_dir) -> list[Path]:
    """Remove what killed runs left beside ``out_dir``: staging folders (``.<name>.staging``, and
    the ``.<name>.staging-XXXX`` of earlier versions) and replaced outputs (``.<name>.old-PID``).

    A folder is stale when the process recorded in it is gone, or, without a record, when it is
    older than ``STALE_HOURS``. Staging folders of other output names in the same parent are
    removed only on a record of a dead process. Returns the folders removed.
    """
    out_abs = Path(os.path.abspath(out_dir))
    parent = out_abs.parent
    removed = []
    try:
        entries = list(parent.iterdir())
    except OSError:
        return removed
    now = time.time()
    for p in entries:
        name = p.name
        if not name.startswith(".") or p.is_symlink() or not p.is_dir():
            continue
        ours = name.startswith(f".{out_abs.name}.")
        stale = False
        if name.endswith(".staging"):
            owner = _read_owner(p)
            if owner is not None:
                stale = not _owner_alive(owner)
            elif ours:
                try:
                    stale = now - p.stat().st_mtime > STALE_HOURS * 3600
                except OSError:
                    continue
        elif ours and ".staging-" in name:
            try:
                stale = now - p.stat().st_mtime > STALE_HOURS * 3600
            except OSError:
                continue
        elif ours and ".old-" in name:
            pid = name.rsplit("-", 1)[-1]
            stale = pid.isdigit() and not _owner_alive({"pid": int(pid), "host": socket.gethostname()})
        if stale:
            shutil.rmtree(p, ignore_errors=True)
            removed.append(p)
    return removed


def _busy_error(out_dir, owner: dict | None) -> OutputError:
    who = f"pid {owner.get('pid')} on {owner.get('host')}" if owner else "a process that is starting"
    return OutputError(f"{out_dir}: another guidewire3d run ({who}) is writing this output folder; "
                       f"wait for it, or choose another --out")


def _os_message(e: OSError) -> str:
    where = f": {e.filename}" if e.filename else ""
    return f"{e.strerror or e.__class__.__name__}{where}"


def require_empty_folder(out_dir, *, replace: bool = False, min_free_mb: float = 0.0) -> Path:
    """Check an output folder before any work; return ``out_dir`` as a Path.

    ``out_dir`` must be absent or an empty folder (or any folder, with ``replace``), a folder must
    be creatable where it goes (a probe is created and removed in the nearest existing parent),
    with at least ``min_free_mb`` MB free on its disk, and no other run may be writing it. Stale
    staging folders of killed runs are removed first (:func:`clean_stale_staging`).

    Raises
    ------
    OutputError
        Any of these does not hold.
    """
    out_dir = Path(out_dir)
    out_abs = Path(os.path.abspath(out_dir))
    if out_dir.is_symlink() and not out_dir.exists():
        raise OutputError(f"{out_dir}: output folder is a dangling symbolic link")
    if out_dir.exists():
        if not out_dir.is_dir():
            raise OutputError(f"{out_dir}: output folder exists and is not a folder")
        if not replace and any(out_dir.iterdir()):
            raise OutputError(f"{out_dir}: output folder exists and is not empty")
    if len(out_abs.name.encode()) + len(".staging-probe-xxxxxxxx") + 1 > 255:
        raise OutputError(f"{out_dir}: output folder name is too long")
    anc = out_abs.parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise OutputError(f"{out_dir}: cannot create the output folder, {anc} is a file, not a folder")
    try:
        Path(tempfile.mkdtemp(prefix=f".{out_abs.name}.probe-", dir=anc)).rmdir()
    except OSError as e:
        raise OutputError(f"{out_dir}: cannot create the output folder in {anc} ({e.strerror})") from None
    if min_free_mb > 0:
        free_mb = shutil.disk_usage(anc).free / 2**20
        if free_mb < min_free_mb:
            raise OutputError(f"{out_dir}: only {free_mb:.0f} MB free on the disk of {anc}, "
                              f"{min_free_mb:g} MB needed")
    if anc == out_abs.parent:
        clean_stale_staging(out_abs)
        staging = _staging_path(out_abs)
        if staging.exists():
            raise _busy_error(out_dir, _read_owner(staging))
    return out_dir


@contextmanager
def staged_folder(out_dir, *, replace: bool = False):
    """Hold ``out_dir`` for one run: yield a new staging folder, rename it to ``out_dir`` when the
    ``with`` block ends without error, remove it (and any parent folders it created) otherwise.

    The staging folder ``.<name>.staging`` beside ``out_dir`` is also the lock: it is created
    exclusively, with the owner's pid, so a second run into the same ``out_dir`` is refused while
    the first one works, and the staging folder of a killed run is recognised and removed. At
    the end ``out_dir`` must still be absent or empty, unless ``replace`` (then it is replaced).

    Raises
    ------
    OutputError
        Another run holds ``out_dir``, ``out_dir`` was filled meanwhile, or an OSError occurred
        while creating, filling or renaming the staging folder.
    """
    out_abs = Path(os.path.abspath(out_dir))
    created = []
    for d in reversed([out_abs.parent, *out_abs.parent.parents]):
        if not d.exists():
            try:
                d.mkdir()
            except FileExistsError:
                continue
            except OSError as e:
                _remove_created(created)
                raise OutputError(f"{out_dir}: cannot create {d} ({e.strerror})") from None
            created.append(d)
    staging = _staging_path(out_abs)
    clean_stale_staging(out_abs)
    try:
        staging.mkdir()
    except FileExistsError:
        _remove_created(created)
        raise _busy_error(out_dir, _read_owner(staging)) from None
    except OSError as e:
        _remove_created(created)
        raise OutputError(f"{out_dir}: cannot create a staging folder beside it ({e.strerror})") from None
    try:
        try:
            (staging / STAGING_OWNER).write_text(json.dumps(_owner_record()))
        except OSError as e:
            raise OutputError(f"{out_dir}: cannot write ({_os_message(e)})") from None
        yield staging
        try:
            (staging / STAGING_OWNER).unlink()
            if out_abs.is_dir() and any(out_abs.iterdir()):
                if not replace:
                    raise OutputError(f"{out_dir}: output folder was filled by something else during this run; "
                                      "nothing was written")
                old = out_abs.with_name(f".{out_abs.name}.old-{os.getpid()}")
                out_abs.rename(old)
                staging.rename(out_abs)
                shutil.rmtree(old, ignore_errors=True)
            else:
                staging.rename(out_abs)  # onto an empty folder too (POSIX rename)
        except OSError as e:
            raise OutputError(f"{out_dir}: cannot move the finished output into place ({_os_message(e)})") from None
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        _remove_created(created)
        raise


def _remove_created(created: list[Path]) -> None:
    for d in reversed(created):
        try:
            d.rmdir()
        except OSError:
            break


def write_folder_atomically(out_dir, writer, *, replace: bool = False) -> Path:
    """Call ``writer(staging)`` inside :func:`staged_folder`: ``out_dir`` appears complete or not
    at all. An OSError of the writer (no space left, ...) becomes an ``OutputError`` naming
    ``out_dir``, and nothing is left behind."""
    with staged_folder(out_dir, replace=replace) as staging:
        write_into(out_dir, staging, writer)
    return Path(out_dir)


def write_into(out_dir, staging: Path, writer) -> None:
    """``writer(staging)``, with an OSError turned into an ``OutputError`` naming ``out_dir``."""
    try:
        writer(staging)
    except OSError as e:
        raise OutputError(f"{out_dir}: cannot write the output ({_os_message(e)})") from None


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


def _quiet(fn):
    """Run ``fn`` with warnings silenced: pydicom warns (on stderr) about each odd value it reads,
    and the checks here turn those values into one error naming the file and the tag."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return fn(*args, **kwargs)

    return wrapper


def _floats(path, ds, kw: str, tag: str, n: int) -> np.ndarray:
    """``n`` finite numbers of a multi-valued tag, or a DicomError naming the file and the tag."""
    if kw not in ds or ds.data_element(kw).value in (None, ""):
        raise DicomError(f"{path}: missing {kw} {tag}")
    v = ds.data_element(kw).value
    vals = list(v) if isinstance(v, Sequence) and not isinstance(v, (str, bytes)) else [v]
    try:
        a = np.array([float(x) for x in vals])
    except (TypeError, ValueError):
        raise DicomError(f"{path}: {kw} {tag} is not {n} numbers: {vals!r}") from None
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise DicomError(f"{path}: {kw} {tag} must be {n} finite numbers, got {[str(x) for x in vals]}")
    return a


def _orientation(where, ds, what: str = "ImageOrientationPatient") -> np.ndarray:
    """ImageOrientationPatient of ``ds`` (6 numbers: two orthogonal unit vectors), or a DicomError naming ``where``
    and ``what`` (the tag's place)."""
    iop = _floats(where, ds, "ImageOrientationPatient", "(0020,0037)", 6)
    row, col = iop[:3], iop[3:]
    if abs(np.linalg.norm(row) - 1) > 1e-2 or abs(np.linalg.norm(col) - 1) > 1e-2 or abs(row @ col) > 1e-2:
        raise DicomError(f"{where}: {what} (0020,0037) is not two orthogonal unit vectors: {iop.tolist()}")
    return iop


def _pixel_spacing(where, ds, what: str = "PixelSpacing") -> np.ndarray:
    ps = _floats(where, ds, "PixelSpacing", "(0028,0030)", 2)
    if np.any(ps <= 0):
        raise DicomError(f"{where}: {what} (0028,0030) must be two positive numbers (mm), got {ps.tolist()}")
    return ps


@_quiet
def _check_slice_geometry(files: list[str], folder: Path) -> None:
    """Check every slice of a CT series (complete, PixelSpacing, positions, same size) and refuse
    gantry tilt and uneven slice spacing instead of misplacing slices."""
    ipps, iop, size = [], None, None
    for f in map(Path, files):
        ds = _read_dicom_header(f, "a CT DICOM slice")
        ipps.append(_floats(f, ds, "ImagePositionPatient", "(0020,0032)", 3))
        iop_f = _orientation(f, ds)
        if iop is None:
            iop, first = iop_f, f
        elif np.abs(iop_f - iop).max() > 1e-3:  # a radial MIP or localizer series: no volume
            raise DicomError(f"{f}: ImageOrientationPatient (0020,0037) {iop_f.round(4).tolist()} differs from "
                             f"{first.name}'s {iop.round(4).tolist()}: the slices are not one stack (a MIP or "
                             f"localizer series?); give --series-uid")
        _pixel_spacing(f, ds)
        if size is None:
            size = (ds.Rows, ds.Columns, files[0])
        elif (ds.Rows, ds.Columns) != size[:2]:
            raise DicomError(f"{f}: Rows x Columns {ds.Rows} x {ds.Columns} differ from {size[0]} x {size[1]} "
                             f"of {size[2]}")
    if len(files) < 2:
        raise DicomError(f"{folder}: a CT series needs at least 2 slices, found {len(files)}")
    _check_stack(np.array(ipps), iop, folder)


def _check_stack(ipps: np.ndarray, iop: np.ndarray, where, *, frames: bool = False) -> None:
    """Refuse slice positions ``ipps`` (n, 3; ImagePositionPatient, LPS mm) that are not one evenly spaced stack
    along the normal of ``iop``: duplicates (``frames``: frames of a multi-frame file, several at one position),
    uneven steps, gantry tilt."""
    row, col = np.array(iop[:3]), np.array(iop[3:])
    normal = np.cross(row, col)
    pos = ipps @ normal
    order = np.argsort(pos)
    ipps, pos = ipps[order], pos[order]
    steps = np.diff(pos)
    if np.any(steps < 1e-6):
        if frames:
            n_pos = int(np.sum(steps >= 1e-6)) + 1
            raise DicomError(f"{where}: {len(pos)} frames at only {n_pos} slice positions (PlanePositionSequence "
                             f"ImagePositionPatient): a time series, several echoes or several stacks in one file; "
                             f"export one volume as its own series")
        raise DicomError(f"{where}: duplicate slice positions (ImagePositionPatient) in the series")
    # each slice against an even stack from the first to the last: a series of 0.625 mm slices whose positions are
    # written with two decimals steps 0.62 and 0.63 mm, and was refused (steps within 1 % of each other were asked)
    step = (pos[-1] - pos[0]) / (len(pos) - 1)
    off = float(np.abs(pos - np.linspace(pos[0], pos[-1], len(pos))).max())
    if off > SLICE_POSITION_TOLERANCE * step:
        raise DicomError(
            f"{where}: uneven slice spacing (ImagePositionPatient steps {steps.min():.3f}..{steps.max():.3f} mm; a "
            f"slice {off:.3f} mm off an even stack of {step:.3f} mm steps, at most "
            f"{100 * SLICE_POSITION_TOLERANCE:.0f}% of a step expected); resample the series to even spacing first"
        )
    # gantry tilt: consecutive positions must move along the slice normal
    d = ipps[-1] - ipps[0]
    off_axis = np.linalg.norm(d - (d @ normal) * normal)
    if off_axis > 0.01 * np.linalg.norm(d) + 1e-3:
        raise DicomError(
            f"{where}: gantry tilt detected (slices not stacked along ImageOrientationPatient normal); "
            "resample the series first"
        )


@_quiet
def _check_unlisted_files(folder: Path, series: dict[str, list[str]]) -> None:
    """A DICOM CT file of ``folder`` that the series reader skipped (truncated, corrupt) is an
    error naming it, instead of a slice silently missing from the volume. Other files (notes,
    DICOMDIR, reports) are ignored."""
    import pydicom

    listed = {os.path.abspath(f) for fs in series.values() for f in fs}
    for p in sorted(folder.iterdir()):
        if p.name.startswith(".") or not p.is_file() or os.path.abspath(p) in listed or not _has_dicm(p):
            continue
        try:
            _read_dicom_header(p, "a CT DICOM slice")
            continue  # complete: the series reader had another reason (a non-image object)
        except DicomError as e:
            err = e
        try:
            ds = pydicom.dcmread(str(p), stop_before_pixels=True)
        except Exception:  # noqa: BLE001
            raise err from None
        sop = str(getattr(getattr(ds, "file_meta", None), "MediaStorageSOPClassUID", "") or ds.get("SOPClassUID", ""))
        if str(ds.get("Modality", "")).strip() == "CT" or sop.startswith(CT_IMAGE_STORAGE):
            raise DicomError(f"{err} (a CT file left out of the series)") from None


def _has_dicm(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(132)[128:132] == b"DICM"
    except OSError:
        return False


def _one_orientation(files: list[str]) -> bool:
    """Whether the first, middle and last files of a series share ImageOrientationPatient (a stack of slices, not
    the images of a radial MIP or a localizer): what :func:`_choose_series` prefers among several series."""
    import pydicom

    seen = []
    for f in {files[0], files[len(files) // 2], files[-1]}:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                v = pydicom.dcmread(f, stop_before_pixels=True, specific_tags=["ImageOrientationPatient"]).get(
                    "ImageOrientationPatient")
            seen.append(np.array([float(x) for x in v]))
        except Exception:  # noqa: BLE001  (a multi-frame file has it in its functional groups; checked later)
            return True
    return all(len(a) == 6 and np.abs(a - seen[0]).max() <= 1e-3 for a in seen)


def _choose_series(path: Path, series: dict[str, list[str]], *, series_uid: str | None,
                   modalities: tuple[str, ...]) -> str:
    """The series of ``series`` (the DICOM series of ``path``'s folder) that :func:`read_volume` reads:
    ``series_uid`` if given, else the series of ``modalities`` with the most slices."""
    folder = path if path.is_dir() else path.parent
    if not series:
        if path.is_dir() and not any(folder.iterdir()):
            raise InputError(f"{folder}: empty directory, expected a DICOM CT series")
        raise DicomError(f"{folder}: no readable DICOM series found")
    if series_uid is not None:
        if series_uid not in series:
            raise DicomError(f"{folder}: SeriesInstanceUID {series_uid} not found (have {', '.join(series)})")
        return series_uid
    import pydicom

    cands = []
    for uid, files in series.items():
        try:
            ds = pydicom.dcmread(files[0], stop_before_pixels=True)
        except Exception:  # noqa: BLE001
            continue
        modality = str(getattr(ds, "Modality", "")).strip()
        volume = modality in modalities or str(ds.get("SOPClassUID", "")) in XRAY_3D_STORAGE
        # a multi-frame CT / MR: a volume in one file (its header, read above, has NumberOfFrames)
        slices = len(files) if len(files) > 1 else max(_int_or(ds.get("NumberOfFrames", 1), 1), 1)
        stack = len(series) == 1 or _one_orientation(files)
        cands.append((volume, stack, slices, uid, modality))
    if not cands:
        raise DicomError(f"{folder}: no readable DICOM series found")
    cands.sort(reverse=True)
    is_volume, _, _, uid, modality = cands[0]
    if not is_volume:
        want = " or ".join(modalities)
        raise DicomError(f"{path}: no {want} series found (Modality (0008,0060) is {modality or 'missing'}), "
                         f"expected a {'CTA' if modalities == ('CT',) else 'CTA, MRA or 3DRA volume'}")
    return uid


@_quiet
def volume_files(path, *, series_uid: str | None = None,
                 modalities: tuple[str, ...] = VOLUME_MODALITIES) -> tuple[str, list[Path]]:
    """The files :func:`read_volume` reads for the CTA ``path``, without reading their pixels:
    ``(series_uid, files)``, the uid ``""`` for a NIfTI/NRRD/MHA file (read alone). A DICOM folder
    (or one of its files) gives the series ``read_volume`` chooses, by the same rule.

    Raises
    ------
    InputError, DicomError
        As :func:`read_volume` for a missing path or a folder without the series.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or directory")
    if not path.is_dir():
        _require_file(path, "a CTA (a DICOM series folder, or a NIfTI, NRRD or MHA file)")
        if not _looks_like_dicom(path):
            return "", [path]
    folder = path if path.is_dir() else path.parent
    series = _dicom_series_in(folder)
    uid = _choose_series(path, series, series_uid=series_uid, modalities=modalities)
    return uid, [Path(f) for f in series[uid]]


def file_fingerprints(files, *, root=None, threads: int = 4) -> list[dict]:
    """``{"name", "size", "sha256"}`` of each of ``files``, sorted by name: ``name`` relative to the
    folder ``root`` (default: each file's own name), ``size`` in bytes, ``sha256`` of the bytes.

    What ``report.json`` records of a run's input files, so that a later run can tell whether they
    changed (the content, wherever they now lie). Hashed in up to ``threads`` threads (hashlib
    releases the GIL); ``scripts/bench_fingerprint.py`` measures it.

    Raises
    ------
    InputError
        A file cannot be read; the message names it.
    """
    import hashlib
    from concurrent.futures import ThreadPoolExecutor

    paths = [Path(f) for f in files]

    def one(p: Path) -> dict:
        try:
            # O_NONBLOCK: a FIFO or a device opens without waiting for a writer, and is refused below
            fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
            if not S_ISREG(os.fstat(fd).st_mode):
                os.close(fd)
                raise InputError(f"{p}: not a regular file, cannot fingerprint it")
            with os.fdopen(fd, "rb") as f:
                digest = hashlib.file_digest(f, "sha256")
                size = f.tell()  # the bytes hashed
        except OSError as e:
            raise InputError(f"{p}: cannot read it to fingerprint it ({e.strerror or e})") from None
        name = os.path.relpath(p, root) if root is not None else p.name
        return {"name": Path(name).as_posix(), "size": int(size), "sha256": digest.hexdigest()}

    if len(paths) <= 1 or threads <= 1:
        out = [one(p) for p in paths]
    else:
        with ThreadPoolExecutor(max_workers=min(int(threads), len(paths))) as pool:
            out = list(pool.map(one, paths))
    return sorted(out, key=lambda d: d["name"])


@_quiet
def read_volume(path, *, series_uid: str | None = None, max_voxels: int = MAX_VOXELS_DEFAULT, log=None,
                modalities: tuple[str, ...] = VOLUME_MODALITIES) -> Volume:
    """Read a vessel volume (a CTA, an MR angiogram, a 3DRA): a DICOM series folder (or one of its files), one
    multi-frame DICOM file (Enhanced CT / MR, X-Ray 3D Angiographic), or a NIfTI/NRRD/MHA file.

    ``modalities`` are the DICOM Modality (0008,0060) values accepted (``VOLUME_MODALITIES``: CT and MR); an X-ray
    volume (``XRAY_3D_STORAGE``, Modality XA) is always accepted.

    If a folder holds several series, the one with the most slices is read (a stack of one orientation before one
    that is not, and ``log`` is told); ``series_uid`` chooses one explicitly. Every file is checked first (complete,
    geometry tags present and sane, finite voxels); a bad one is named in the error.
    """
    path = Path(path)
    sitk = _sitk_quiet()
    if path.is_symlink() and not path.exists():
        raise InputError(f"{path}: dangling symbolic link (its target {os.readlink(path)} does not exist)")
    if not path.exists():
        raise InputError(f"{path}: no such file or directory")
    if not path.is_dir():
        _require_file(path, "a CTA (a DICOM series folder, or a NIfTI, NRRD or MHA file)")
    if path.is_file() and not _looks_like_dicom(path):
        try:
            info = sitk.ImageFileReader()
            info.SetFileName(str(path))
            info.ReadImageInformation()
            n = int(np.prod(info.GetSize(), dtype=np.int64)) if info.GetDimension() == 3 else 0
            if n > max_voxels:
                raise InputError(f"{path}: volume of {info.GetSize()} voxels (header) exceeds the limit of "
                                 f"{max_voxels} voxels; crop or downsample it first")
            img = sitk.ReadImage(str(path), sitk.sitkFloat32)
        except RuntimeError:
            raise InputError(f"{path}: not a readable volume (expected DICOM, NIfTI, NRRD or MHA)") from None
        vol = Volume.from_sitk(img, source=str(path))
        _check_size(vol, path, max_voxels)
        _check_finite(vol, path)
        bad = _nifti_nonfinite(path)
        if bad:
            raise InputError(f"{path}: {bad} voxels are NaN or infinite in the file")
        return vol
    folder = path if path.is_dir() else path.parent
    series = _dicom_series_in(folder)
    _check_unlisted_files(folder, series)
    uid = _choose_series(path, series, series_uid=series_uid, modalities=modalities)
    files = series[uid]
    frames = _frames_of(files[0]) if len(files) == 1 else 1
    if series_uid is None and len(series) > 1 and log is not None:
        log(f"{folder}: {len(series)} series found, using the largest volume series {uid} "
            f"({max(len(files), frames)} slices)")
    if frames > 1:
        return _read_multiframe_volume(Path(files[0]), uid, max_voxels)
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
    _check_finite(vol, folder)
    return vol


def _int_or(value, default: int) -> int:
    try:
        return int(value or default)
    except (TypeError, ValueError):
        return default


def _frames_of(path) -> int:
    """NumberOfFrames of the DICOM file ``path`` (1 when absent or unreadable: the full checks come later)."""
    import pydicom

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(str(path), stop_before_pixels=True, specific_tags=["NumberOfFrames"])
    except Exception:  # noqa: BLE001
        return 1
    return max(_int_or(ds.get("NumberOfFrames", 1), 1), 1)


def _functional_group(ds, frame: int, sequence: str):
    """The item of ``sequence`` (e.g. ``PlanePositionSequence``) that applies to ``frame`` of a multi-frame
    dataset: in its per-frame functional group, else in the shared one; None when neither has it."""
    for groups, i in (("PerFrameFunctionalGroupsSequence", frame), ("SharedFunctionalGroupsSequence", 0)):
        seq = ds.get(groups)
        if seq is not None and len(seq) > i and sequence in seq[i] and len(seq[i].get(sequence) or ()) > 0:
            return seq[i].get(sequence)[0]
    return None


def _multiframe_geometry(path: Path, ds, n_frames: int) -> None:
    """Check the geometry a multi-frame CT/MR keeps in its functional groups (every frame's
    ImagePositionPatient, the orientation, the pixel spacing: one evenly spaced stack) and name the first
    missing or wrong tag with the frame it belongs to."""
    if "PerFrameFunctionalGroupsSequence" not in ds and "SharedFunctionalGroupsSequence" not in ds:
        raise DicomError(f"{path}: a multi-frame image without PerFrameFunctionalGroupsSequence (5200,9230): the "
                         f"position of each of its {n_frames} frames is unknown, expected an enhanced CT or MR")
    per_frame = ds.get("PerFrameFunctionalGroupsSequence") or ()
    if len(per_frame) != n_frames:
        raise DicomError(f"{path}: PerFrameFunctionalGroupsSequence (5200,9230) has {len(per_frame)} items for "
                         f"NumberOfFrames {n_frames}")
    ipps, iop = [], None
    for k in range(n_frames):
        where = f"{path}: frame {k + 1}"
        pos = _functional_group(ds, k, "PlanePositionSequence")
        if pos is None:
            raise DicomError(f"{where}: missing PlanePositionSequence (0020,9113) ImagePositionPatient")
        ipps.append(_floats(where, pos, "ImagePositionPatient", "(0020,0032)", 3))
        ori = _functional_group(ds, k, "PlaneOrientationSequence")
        if ori is None:
            raise DicomError(f"{where}: missing PlaneOrientationSequence (0020,9116) ImageOrientationPatient")
        iop_k = _orientation(where, ori)
        if iop is None:
            iop = iop_k
        elif np.abs(iop_k - iop).max() > 1e-3:
            raise DicomError(f"{where}: ImageOrientationPatient (0020,0037) {iop_k.round(4).tolist()} differs from "
                             f"frame 1's {iop.round(4).tolist()}: several stacks in one file; export one volume")
        meas = _functional_group(ds, k, "PixelMeasuresSequence")
        if meas is None:
            raise DicomError(f"{where}: missing PixelMeasuresSequence (0028,9110) PixelSpacing")
        _pixel_spacing(where, meas)
    if n_frames < 2:
        raise DicomError(f"{path}: a volume needs at least 2 slices, found {n_frames} frame")
    _check_stack(np.array(ipps), iop, path, frames=True)


@_quiet
def _read_multiframe_volume(path: Path, uid: str, max_voxels: int) -> Volume:
    """A multi-frame CT or MR file (Enhanced CT / MR Image Storage and their Legacy Converted forms: one frame per
    slice, the geometry in functional groups) as a Volume, through highdicom (``Image.get_volume``): its stored
    values through the modality transform (Rescale Slope / Intercept: HU for a CT), not a real-world value map."""
    import highdicom as hd

    ds = _read_dicom_header(path, "a multi-frame CT or MR DICOM file")
    n = _number_of_frames(path, ds)
    if n * ds.Rows * ds.Columns > max_voxels:
        raise InputError(f"{path}: volume of {n} frames of {ds.Rows} x {ds.Columns} voxels exceeds the limit of "
                         f"{max_voxels} voxels; crop or downsample it first")
    _multiframe_geometry(path, ds, n)
    try:
        vol = hd.imread(str(path)).get_volume(dtype=np.float32, apply_real_world_transform=False)
        arr = np.ascontiguousarray(vol.array, dtype=np.float32)
    except Exception as e:  # noqa: BLE001  (highdicom's and the pixel decoders' errors)
        ts = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
        raise DicomError(f"{path}: its {n} frames could not be read as one volume (transfer syntax "
                         f"{getattr(ts, 'name', None) or ts}; {e.__class__.__name__}: "
                         f"{str(e).strip().splitlines()[0][:120] if str(e).strip() else ''})") from None
    if arr.ndim != 3 or arr.shape[0] != n:
        raise DicomError(f"{path}: its {n} frames make a {arr.shape} array, expected one slice per frame")
    A = np.asarray(vol.affine, dtype=float)  # columns: the slice, row and column steps (LPS mm), the origin
    steps = A[:3, [2, 1, 0]]  # x (column), y (row), z (slice)
    spacing = np.linalg.norm(steps, axis=0)
    out = Volume(arr, tuple(spacing), tuple(A[:3, 3]), steps / spacing, source=str(path), series_uid=uid)
    _check_finite(out, path)
    return out


def _nifti_nonfinite(path: Path) -> int:
    """The number of NaN / infinite voxels stored in a float NIfTI-1/2 file (``.nii``, ``.nii.gz``).

    ITK's NIfTI reader turns them into 0 without a word, so the stored values are read here.
    0 for integer data and for other formats."""
    import gzip

    name = path.name.lower()
    if not (name.endswith(".nii") or name.endswith(".nii.gz")):
        return 0
    try:
        with (gzip.open if name.endswith(".gz") else open)(path, "rb") as f:
            hdr = f.read(540)
            for order in "<>":
                size = int(np.frombuffer(hdr[:4], f"{order}i4")[0])
                if size in (348, 540):
                    break
            else:
                return 0
            if size == 348:
                datatype = int(np.frombuffer(hdr[70:72], f"{order}i2")[0])
                offset = int(np.frombuffer(hdr[108:112], f"{order}f4")[0])
            else:
                datatype = int(np.frombuffer(hdr[12:14], f"{order}i2")[0])
                offset = int(np.frombuffer(hdr[168:176], f"{order}i8")[0])
            dtype = {16: f"{order}f4", 64: f"{order}f8"}.get(datatype)
            if dtype is None:
                return 0
            f.seek(max(offset, size))
            bad, chunk = 0, 1 << 24
            while block := f.read(chunk):
                n = len(block) // np.dtype(dtype).itemsize
                bad += int(np.count_nonzero(~np.isfinite(np.frombuffer(block[:n * np.dtype(dtype).itemsize], dtype))))
            return bad
    except (OSError, EOFError, ValueError):
        return 0  # unreadable: ITK's reader reports it


def _check_finite(vol: Volume, path) -> None:
    bad = ~np.isfinite(vol.array_zyx)
    if bad.any():
        z, y, x = np.argwhere(bad)[0]
        raise InputError(f"{path}: {int(bad.sum())} voxels are NaN or infinite (the first at x,y,z = {x},{y},{z})")


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


def affine_of(vol: Volume) -> np.ndarray:
    """The 4 x 4 matrix taking a voxel's ``(z, y, x)`` index (slice, row, column) of ``vol`` to LPS mm: highdicom's
    convention (columns: the slice, row and column steps, then the origin)."""
    steps = np.asarray(vol.direction, float) * np.asarray(vol.spacing_mm, float)  # columns x, y, z (mm per index)
    A = np.eye(4)
    A[:3, 0], A[:3, 1], A[:3, 2], A[:3, 3] = steps[:, 2], steps[:, 1], steps[:, 0], vol.origin_lps_mm
    return A


def write_dicom_seg(labels_zyx: np.ndarray, vol: Volume, source_files, path, *, segment_names: list[str],
                    description: str = "guidewire3d vessels") -> Path:
    """Write ``labels_zyx`` (0 background, ``k`` the ``k``-th of ``segment_names``; on ``vol``'s grid) as a DICOM
    Segmentation (binary, one segment per name) referencing the DICOM images ``source_files`` that ``vol`` was read
    from, so that a PACS or 3D Slicer's DICOM module shows it over the study. highdicom places each frame by its own
    position (the grid need not follow the files' order). Atomic."""
    import highdicom as hd
    import pydicom
    from pydicom.sr.codedict import codes

    labels_zyx = np.asarray(labels_zyx)
    if labels_zyx.shape != vol.shape_zyx:
        raise ValueError(f"labels of shape {labels_zyx.shape} on a volume of {vol.shape_zyx}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sources = [pydicom.dcmread(str(f), stop_before_pixels=True) for f in source_files]
    frame_uid = str(sources[0].get("FrameOfReferenceUID", "")) or None
    algorithm = hd.AlgorithmIdentificationSequence(name="guidewire3d vessels", version=__version__,
                                                   family=codes.cid7162.ArtificialIntelligence)
    segments = [hd.seg.SegmentDescription(
        segment_number=k + 1, segment_label=name[:64], segmented_property_category=codes.SCT.AnatomicalStructure,
        segmented_property_type=codes.SCT.BloodVessel, algorithm_type=hd.seg.SegmentAlgorithmTypeValues.AUTOMATIC,
        algorithm_identification=algorithm) for k, name in enumerate(segment_names)]
    # a label map: highdicom reads values 1..n of an unsigned array as the segments' numbers
    grid = hd.Volume(labels_zyx.astype(np.uint8), affine_of(vol), coordinate_system="PATIENT",
                     frame_of_reference_uid=frame_uid)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        seg = hd.seg.Segmentation(
            source_images=sources, pixel_array=grid, segmentation_type=hd.seg.SegmentationTypeValues.BINARY,
            segment_descriptions=segments, series_instance_uid=_new_uid(), series_number=990,
            sop_instance_uid=_new_uid(), instance_number=1, manufacturer="guidewire3d",
            manufacturer_model_name="guidewire3d vessels", software_versions=__version__, device_serial_number="0",
            series_description=description[:64])
    return atomic_write_via(path, lambda tmp: seg.save_as(str(tmp)))


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
    try:
        ft = float(ds.FrameTime) if ds.get("FrameTime") not in (None, "") else None
    except (TypeError, ValueError):
        ft = None  # the frame time is informative only
    return XARun(frames, carm, source=str(path), frame_time_ms=ft)


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


def _require_file(path: Path, what: str) -> None:
    """``path`` must be a readable regular file that is not empty (else an InputError naming it)."""
    if path.is_symlink() and not path.exists():
        raise InputError(f"{path}: dangling symbolic link (its target {os.readlink(path)} does not exist)")
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, expected {what}")
    if not path.is_file():
        raise InputError(f"{path}: not a regular file (a pipe, socket or device), expected {what}")
    if path.stat().st_size == 0:
        raise InputError(f"{path}: empty file (0 bytes), expected {what}")
    if not os.access(path, os.R_OK):
        raise InputError(f"{path}: permission denied (cannot read it)")


@_quiet
def _read_dicom_header(path: Path, what: str):
    """The dataset of a DICOM file with its pixel data left on disk (read later by
    ``pixel_array``), after checking that the file is complete: PixelData present, as long as
    the header says, and (uncompressed) as long as Rows x Columns x frames need."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    _require_file(path, what)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(str(path), defer_size=1024)
    except InvalidDicomError:
        raise DicomError(f"{path}: not a DICOM file (no 'DICM' marker), expected {what}") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read it ({e.strerror})") from None
    except Exception as e:  # noqa: BLE001
        # pydicom's parse errors (struct.error 'unpack requires a buffer of 4 bytes', EOFError ...) come from a
        # header that ends inside an element: a truncated file, or a corrupt length. Which one depends on where the
        # cut falls in the file meta group, whose UIDs vary in length from file to file
        raise DicomError(f"{path}: truncated or corrupt DICOM header, unreadable ({e.__class__.__name__}: "
                         f"{str(e)[:100]})") from None
    if "PixelData" not in ds:
        ts = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
        raise DicomError(f"{path}: truncated or not an image DICOM file: no PixelData (7FE0,0010) "
                         f"(or its transfer syntax {getattr(ts, 'name', None) or ts} does not match its encoding)")
    for tag, kw in (("(0028,0010)", "Rows"), ("(0028,0011)", "Columns")):
        v = ds.get(kw)
        if not isinstance(v, int) or v < 1:
            raise DicomError(f"{path}: {kw} {tag} is {'missing' if v is None else repr(v)}, expected a positive number")
    ts = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
    raw = ds.get_item("PixelData")
    size = path.stat().st_size
    length = getattr(raw, "length", None)
    if length is not None and length != 0xFFFFFFFF and not _ts_is(ts, "is_deflated", True) \
            and raw.value_tell + length > size:
        raise DicomError(f"{path}: truncated file: PixelData (7FE0,0010) declares {length} bytes, the file ends "
                         f"{raw.value_tell + length - size} bytes short")
    if not _ts_is(ts, "is_compressed", True):
        n_frames = _number_of_frames(path, ds)
        bits = int(ds.get("BitsAllocated", 16) or 16)
        spp = int(ds.get("SamplesPerPixel", 1) or 1)
        n_px = ds.Rows * ds.Columns * n_frames * spp
        need = (n_px * bits + 7) // 8
        have = length if length not in (None, 0xFFFFFFFF) else len(ds.PixelData)
        if have < need:
            raise DicomError(f"{path}: truncated: PixelData (7FE0,0010) has {have} bytes, Rows x Columns x "
                             f"NumberOfFrames x SamplesPerPixel ({ds.Rows} x {ds.Columns} x {n_frames} x {spp}, "
                             f"{bits}-bit) need {need}")
    return ds


def _ts_is(ts, prop: str, unknown: bool) -> bool:
    """``ts.is_compressed`` / ``ts.is_deflated`` of a transfer syntax UID (``unknown`` for a UID
    pydicom does not know; False without a UID: pydicom then assumes implicit VR little endian)."""
    if ts is None:
        return False
    try:
        return bool(getattr(ts, prop))
    except ValueError:
        return unknown


def _number_of_frames(path: Path, ds) -> int:
    v = ds.get("NumberOfFrames", 1)
    try:
        n = int(v if v not in (None, "") else 1)
    except (TypeError, ValueError):
        raise DicomError(f"{path}: NumberOfFrames (0028,0008) is not a number: {v!r}") from None
    if n < 1:
        raise DicomError(f"{path}: NumberOfFrames (0028,0008) is {n}, expected at least 1")
    return n


MAX_XA_PIXELS = 2**29  # frames x rows x cols of one XA file (2 GB as float32)


@_quiet
def _read_xa_pixels(path: Path):
    """(dataset, frames float32 (T, rows, cols), rescaled, MONOCHROME1 inverted, colour reduced
    to luminance) of an XA/RF file."""
    ds = _read_dicom_header(path, "an XA DICOM file")
    modality = str(getattr(ds, "Modality", "")).strip()
    if modality not in ("XA", "RF"):
        raise DicomError(f"{path}: Modality (0008,0060) is {modality or 'missing'!r}, expected XA or RF")
    n_frames = _number_of_frames(path, ds)
    if n_frames * ds.Rows * ds.Columns > MAX_XA_PIXELS:
        raise DicomError(f"{path}: NumberOfFrames x Rows x Columns = {n_frames} x {ds.Rows} x {ds.Columns} exceeds "
                         f"the limit of {MAX_XA_PIXELS} pixels")
    spp = int(ds.get("SamplesPerPixel", 1) or 1)
    photometric = str(ds.get("PhotometricInterpretation", "MONOCHROME2")).strip()
    ts = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            arr = np.asarray(ds.pixel_array)
            if photometric == "PALETTE COLOR":
                from pydicom.pixels import apply_color_lut

                arr, spp = apply_color_lut(arr, ds), 3
    except Exception as e:  # noqa: BLE001
        name = getattr(ts, "name", None) or str(ts)
        raise DicomError(f"{path}: PixelData cannot be decoded (transfer syntax {name}; "
                         f"{e.__class__.__name__}: {str(e)[:120]})") from None
    if spp == 3 and arr.shape[-1] == 3:  # RGB (pydicom converts YBR): luminance, ITU-R BT.601
        arr = arr[..., :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    elif spp != 1:
        raise DicomError(f"{path}: SamplesPerPixel (0028,0002) is {spp}, expected 1 (grey) or 3 (colour)")
    if arr.ndim == 2:
        arr = arr[None]
    if arr.shape != (n_frames, ds.Rows, ds.Columns):
        raise DicomError(f"{path}: PixelData decodes to shape {arr.shape}, expected NumberOfFrames x Rows x "
                         f"Columns = ({n_frames}, {ds.Rows}, {ds.Columns})")
    frames = arr.astype(np.float32)
    try:
        slope = float(ds.get("RescaleSlope", 1.0) or 1.0)
        intercept = float(ds.get("RescaleIntercept", 0.0) or 0.0)
    except (TypeError, ValueError):
        raise DicomError(f"{path}: RescaleSlope / RescaleIntercept (0028,1053 / 0028,1052) are not numbers") from None
    if slope != 1.0 or intercept != 0.0:
        frames = frames * slope + intercept
    if not np.all(np.isfinite(frames)):
        raise DicomError(f"{path}: PixelData (7FE0,0010) holds NaN or infinite values")
    if photometric == "MONOCHROME1":
        frames = frames.max() - frames
    return ds, frames


# where an enhanced (functional-group) XA keeps what a classic XA has at the top level
_FUNCTIONAL_GROUPS = ("SharedFunctionalGroupsSequence", "PerFrameFunctionalGroupsSequence")


def _find_element(ds, keywords, depth: int = 0):
    """The first data element with one of ``keywords``: at the top level, else (enhanced
    multi-frame objects) in the shared or first per-frame functional group."""
    for kw in keywords:
        if kw in ds and ds.data_element(kw).value not in (None, ""):
            return ds.data_element(kw)
    if depth > 3:
        return None
    seqs = _FUNCTIONAL_GROUPS if depth == 0 else [e.keyword for e in ds if e.VR == "SQ"]
    for s in seqs:
        items = ds.get(s) if s else None
        if items:
            found = _find_element(items[0], keywords, depth + 1)
            if found is not None:
                return found
    return None


_OVERRIDE_OPTIONS = {"sid_mm": "--sid", "sod_mm": "--sod", "pixel_mm": "--pixel", "primary_deg": "--primary",
                     "secondary_deg": "--secondary"}


def check_geometry_overrides(overrides: dict | None) -> dict:
    """The given (not None) C-arm overrides as floats; GeometryError naming the command-line option
    (``--sid`` ...) of a value that is not finite, not positive (distances, pixel) or out of range
    (angles), or ``--sid`` not above ``--sod``."""
    out = {}
    for key, v in (overrides or {}).items():
        if v is None:
            continue
        opt = _OVERRIDE_OPTIONS.get(key, key)
        try:
            v = float(v)
        except (TypeError, ValueError):
            raise GeometryError(f"{opt} {v!r}: expected a number") from None
        if not np.isfinite(v):
            raise GeometryError(f"{opt} {v}: expected a finite number")
        if key in ("sid_mm", "sod_mm", "pixel_mm") and v <= 0:
            raise GeometryError(f"{opt} {v:g}: must be positive")
        limit = {"primary_deg": 180, "secondary_deg": 90}.get(key)
        if limit is not None and abs(v) > limit:
            raise GeometryError(f"{opt} {v:g}: out of range (|angle| <= {limit} degrees)")
        out[key] = v
    if "sid_mm" in out and "sod_mm" in out and out["sid_mm"] <= out["sod_mm"]:
        raise GeometryError(f"--sid {out['sid_mm']:g} must exceed --sod {out['sod_mm']:g} (source to detector "
                            "is longer than source to isocentre)")
    return out


@_quiet
def _xa_carm(path: Path, ds, overrides: dict) -> CArm:
    """The C-arm view of an XA dataset from its tags (``overrides`` replace or supply them)."""
    overrides = check_geometry_overrides(overrides)
    vals, origin = {}, {}
    for key, (kw, tag) in _XA_TAGS.items():
        if key in overrides:
            vals[key] = overrides[key]
            origin[key] = f"{_OVERRIDE_OPTIONS[key]} {overrides[key]:g}"
            continue
        el = _find_element(ds, (kw, "DistanceSourceToIsocenter") if key == "sod_mm" else (kw,))
        if el is None:
            raise DicomError(f"{path}: missing {kw} {tag} (supply it with {_OVERRIDE_OPTIONS[key]})")
        v = el.value
        try:
            vals[key] = float(v[0] if key == "pixel_mm" and hasattr(v, "__len__") and not isinstance(v, str) else v)
        except (TypeError, ValueError, IndexError):
            raise DicomError(f"{path}: {kw} {tag} is not a number: {v!r}") from None
        if not np.isfinite(vals[key]):
            raise DicomError(f"{path}: {kw} {tag} is not finite: {vals[key]}")
        origin[key] = f"{el.keyword} {vals[key]:g} from the file"
    try:
        return CArm(shape=(int(ds.Rows), int(ds.Columns)), **vals)
    except GeometryError as e:
        note = ""
        if overrides:  # say which of the values involved came from the command line
            words = {"sid_mm": "DistanceSourceToDetector", "sod_mm": "DistanceSourceToPatient",
                     "pixel_mm": "ImagerPixelSpacing", "primary_deg": "primary", "secondary_deg": "secondary"}
            keys = [k for k, w in words.items() if w in str(e)] or list(words)
            note = " (" + ", ".join(origin[k] for k in keys) + ")"
        raise GeometryError(f"{path}: {e}{note}") from None


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
    the keys of ``CArm.to_dict`` (``shape`` may be omitted: it is taken from the frames). The
    sidecar is checked before the frames are read.
    """
    import cv2

    path = Path(path)
    if path.is_symlink() and not path.exists():
        raise InputError(f"{path}: dangling symbolic link (its target {os.readlink(path)} does not exist)")
    if path.is_dir():
        sidecar = path / "geometry.json"
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in (".png", ".tif", ".tiff", ".jpg", ".jpeg"))
        if not files:
            raise InputError(f"{path}: no PNG/TIFF/JPEG frames found")
    elif path.exists():
        _require_file(path, "a video")
        sidecar = path.with_suffix(path.suffix + ".json")
        if not sidecar.exists():
            sidecar = path.with_suffix(".json")
    else:
        raise InputError(f"{path}: no such file or directory")
    geo = _read_sidecar(sidecar)
    if path.is_dir():
        frames = []
        for f in files:
            im = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            if im is None:
                raise InputError(f"{f}: unreadable image")
            if im.ndim == 3:
                im = cv2.cvtColor(im, cv2.COLOR_BGRA2GRAY if im.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
            frames.append(im.astype(np.float32))
        shapes = {fr.shape for fr in frames}
        if len(shapes) != 1:
            odd = next(f for f, fr in zip(files, frames) if fr.shape != frames[0].shape)
            raise InputError(f"{odd}: frame size {frames[files.index(odd)].shape} differs from {frames[0].shape} "
                             f"of {files[0].name}")
        frames = np.stack(frames)
    else:
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
    geo.setdefault("shape", list(frames.shape[1:]))
    try:
        carm = CArm.from_dict(geo)
    except GeometryError as e:
        raise GeometryError(f"{sidecar}: {e}") from None
    except (TypeError, ValueError) as e:
        raise GeometryError(f"{sidecar}: invalid geometry ({e})") from None
    if tuple(carm.shape) != tuple(frames.shape[1:]):
        raise GeometryError(f"{sidecar}: shape {list(carm.shape)} does not match the frames' "
                            f"{list(frames.shape[1:])} of {path}")
    return XARun(frames, carm, source=str(path))


def _read_sidecar(sidecar: Path) -> dict:
    """The JSON object of a geometry sidecar, or an InputError naming it."""
    if not sidecar.exists():
        raise InputError(f"{sidecar}: geometry sidecar missing (JSON with primary_deg, secondary_deg, sid_mm, sod_mm, "
                         "pixel_mm)")
    _require_file(sidecar, "a JSON geometry sidecar")
    try:
        geo = json.loads(sidecar.read_text())
    except json.JSONDecodeError as e:
        raise InputError(f"{sidecar}: invalid JSON ({e.msg} at line {e.lineno})") from None
    except UnicodeDecodeError:
        raise InputError(f"{sidecar}: not a text file (invalid UTF-8), expected JSON") from None
    if not isinstance(geo, dict):
        raise InputError(f"{sidecar}: expected a JSON object with primary_deg, secondary_deg, sid_mm, sod_mm, "
                         f"pixel_mm, got a {type(geo).__name__}")
    return dict(geo)
