"""Many studies at once: ``guidewire3d batch MANIFEST --out DIR`` on ``dask.distributed``.

A study is one ``reconstruct`` run (the same library call, :func:`pipeline.run_to_outdir`) writing
``DIR/<study>/`` exactly as ``reconstruct`` writes it: staged, so a study folder appears complete or
not at all. The studies come from a CSV manifest (:func:`read_manifest`) or from a DICOM folder tree
grouped by StudyInstanceUID (:func:`group_dicom_tree`). Each study is one task on a Dask cluster: a
local cluster of worker processes bound to 127.0.0.1, or an existing scheduler. A task that raises
unexpectedly (a crash, a killed worker) is retried; a study with bad input fails at once (the same
input would fail again). Either way it is recorded in ``DIR/summary.csv`` and the batch goes on.
A study whose folder already holds a ``report.json`` is skipped when it was made with the options
this run asks for and from input files with the same bytes (``report.json``'s ``inputs.files``:
:func:`finished_row`), and refused (``failed``, its folder untouched) otherwise.
"""
from __future__ import annotations

import csv
import io as _stdio
import os
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from guidewire3d import io
from guidewire3d.app import pipeline
from guidewire3d.errors import Guidewire3DError, InputError, OutputError
from guidewire3d.methods import ReconMethod, SegMethod, choices
from guidewire3d.vesseltree import check_access

__all__ = ["StudySpec", "read_manifest", "group_dicom_tree", "load_studies", "run_study", "run_batch",
           "write_summary", "read_summary", "finished_row", "made_otherwise", "input_changes", "SUMMARY_COLUMNS",
           "MANIFEST_COLUMNS", "OPTION_COLUMNS"]

MANIFEST_COLUMNS = ("study", "cta", "roadmap", "frames")
# optional manifest columns: the `reconstruct` options they set (other columns are ignored)
OPTION_COLUMNS = ("series_uid", "roadmap_frame", "method", "segmenter", "force", "track_motion", "access_lps")
# the manifest's access_lps that keeps a study's automatic root when the batch has a --access-lps
NO_ACCESS = "none"
# then the option columns: the options a study was made with (its report.json), or, failed without a
# folder, the ones it asked for (empty roadmap_frame, series_uid: the automatic choice)
SUMMARY_COLUMNS = ("study", "status", "verdict", "residual_px", "frames_reconstructed", "frames_total", "seconds",
                   "peak_rss_mb", "worker", "error", *OPTION_COLUMNS)
SUMMARY_NAME = "summary.csv"
REPORT_NAME = "report.json"

# the statuses of a study in summary.csv
DONE = "done"                       # output written, frames reconstructed
# output written, but the registration failed or is uncertain: frames not reconstructed (reconstruct's exit 1)
NOT_RECONSTRUCTED = "not_reconstructed"
FAILED = "failed"                   # no output: the error column says why
SKIPPED = "skipped"                 # the output existed before this run (values read from its report.json)
STATUSES = (DONE, NOT_RECONSTRUCTED, FAILED, SKIPPED)

# the XA run used as the roadmap in a DICOM tree: a SeriesDescription with one of these words
ROADMAP_WORDS = ("roadmap", "dsa", "subtract")
SAME_VIEW_DEG = 1.0  # two XA runs whose positioner angles differ by less than this are the same view

_TRUE = {"1", "true", "yes", "y"}
_FALSE = {"0", "false", "no", "n", ""}


@dataclass(frozen=True)
class StudySpec:
    """One study of a batch: the inputs and options of one ``reconstruct`` run.

    ``access_lps_mm`` (LPS mm) is ``reconstruct --access-lps``: where the wire enters the vessels;
    ``access_option`` names where it came from in the errors (``--access-lps``, or the manifest's
    ``access_lps`` cell). ``error`` is set for a study that could not be assembled from a DICOM tree
    (no CT series, no XA run): it is recorded as failed without running.
    """

    study: str
    cta: str
    roadmap: str
    frames: str
    series_uid: str | None = None
    roadmap_frame: int | None = None
    method: str = "vessel"
    segmenter: str = "unet"
    force: bool = False
    track_motion: bool = False
    access_lps_mm: tuple[float, float, float] | None = None
    access_option: str = "--access-lps"  # what the errors call the access point: the option or the manifest cell
    source: str = ""
    error: str | None = None


# --------------------------------------------------------------------------------------
# the manifest
# --------------------------------------------------------------------------------------
def check_study_name(name: str, where: str) -> str:
    """``name`` if it can be a folder name under the batch output folder, else an InputError naming ``where``."""
    name = name.strip()
    if not name:
        raise InputError(f"{where}: empty 'study'")
    if name in (".", "..") or name.startswith(".") or "/" in name or "\\" in name or "\0" in name:
        raise InputError(f"{where}: study {name!r} cannot be a folder name (no '/', '\\', or leading '.')")
    if name == SUMMARY_NAME:
        raise InputError(f"{where}: study {name!r} clashes with the batch's {SUMMARY_NAME}")
    if len(name.encode()) > 200:
        raise InputError(f"{where}: study name is too long ({len(name.encode())} bytes, at most 200)")
    return name


def _renamed_access(message: str, option: str) -> str:
    """``message`` with the access point named ``option``: the errors of ``check_access`` and of the
    pipeline start with ``--access-lps=x,y,z``; a point from a manifest is its ``access_lps`` cell."""
    if option != "--access-lps" and message.startswith("--access-lps="):
        return f"{option}={message[len('--access-lps='):]}"
    return message


def parse_access(value: str, where: str) -> tuple[float, float, float] | None:
    """A manifest's ``access_lps`` cell: ``"x,y,z"`` in LPS mm (quoted in the CSV; ``;`` or spaces
    may separate the numbers too) -> ``(x, y, z)``; ``""`` -> None; an InputError naming ``where``
    and the column otherwise. ``NO_ACCESS`` is handled by the caller."""
    v = value.strip()
    if not v:
        return None
    parts = [t for t in re.split(r"[,;\s]+", v) if t]
    try:
        xyz = [float(t) for t in parts]
    except ValueError:
        xyz = []
    if len(xyz) != 3:
        raise InputError(f"{where}: access_lps: expected x,y,z in LPS mm (quoted: \"x,y,z\"), or {NO_ACCESS}, "
                         f"got {v!r}")
    try:
        return tuple(float(c) for c in check_access(xyz))
    except InputError as e:  # named as the manifest's cell, as run_study names the pipeline's refusals
        raise InputError(_renamed_access(str(e), f"{where}: access_lps")) from None


def _option(value: str, column: str, where: str):
    v = value.strip()
    if column == "access_lps":
        return parse_access(v, where)
    if column == "series_uid":
        return v or None
    if column == "roadmap_frame":
        if not v:
            return None
        try:
            k = int(v)
        except ValueError:
            raise InputError(f"{where}: roadmap_frame: expected an integer, got {v!r}") from None
        if k < 0:
            raise InputError(f"{where}: roadmap_frame: expected a non-negative integer, got {k}")
        return k
    if column in ("method", "segmenter"):
        allowed = choices(ReconMethod) if column == "method" else choices(SegMethod)
        if not v:
            return allowed[0]
        if v not in allowed:
            raise InputError(f"{where}: {column}: expected one of {', '.join(allowed)}, got {v!r}")
        return v
    if v.lower() in _TRUE:
        return True
    if v.lower() in _FALSE:
        return False
    raise InputError(f"{where}: {column}: expected true or false, got {v!r}")


def read_manifest(path, *, access_lps_mm=None) -> list[StudySpec]:
    """The studies of a CSV manifest with the columns ``study,cta,roadmap,frames``.

    Optional columns set ``reconstruct`` options per study: ``series_uid``, ``roadmap_frame``,
    ``method``, ``segmenter``, ``force``, ``track_motion``, ``access_lps``; other columns are
    ignored. Relative paths are relative to the manifest's folder. Every row is checked before
    anything runs.

    ``access_lps_mm`` ((3,) LPS mm, optional: the batch's ``--access-lps``) is every study's access
    point; a study's ``access_lps`` cell overrides it: ``"x,y,z"`` (quoted) another point, ``none``
    the automatic root, empty the batch's point.

    Raises
    ------
    InputError
        The manifest is missing or unreadable, lacks a column, has no rows, or a row has an empty
        or duplicate study name, a file that does not exist, or a bad option value; the message
        names the manifest, the line and the field.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such manifest (expected a CSV file or a DICOM folder)")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text CSV manifest (it is not UTF-8)") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read the manifest ({e.strerror})") from None
    try:
        rows = list(csv.reader(_stdio.StringIO(text)))
    except csv.Error as e:
        raise InputError(f"{path}: malformed CSV ({e})") from None
    rows = [(i + 1, r) for i, r in enumerate(rows) if any(c.strip() for c in r)]
    if not rows:
        raise InputError(f"{path}: empty manifest (expected a header with {','.join(MANIFEST_COLUMNS)})")
    header_line, header = rows[0]
    header = [h.strip().lower() for h in header]
    for col in MANIFEST_COLUMNS:
        if col not in header:
            raise InputError(f"{path}: missing column '{col}' (the header must name {','.join(MANIFEST_COLUMNS)}; "
                             f"it has {','.join(h for h in header if h) or 'nothing'})")
    dup = sorted({h for h in header if h and header.count(h) > 1})
    if dup:
        raise InputError(f"{path}: column '{dup[0]}' appears twice in the header")
    if len(rows) == 1:
        raise InputError(f"{path}: no studies (only a header)")
    base = path.resolve().parent
    default_access = None if access_lps_mm is None else tuple(float(c) for c in check_access(access_lps_mm))
    studies, seen = [], {}
    for line, r in rows[1:]:
        where = f"{path} line {line}"
        if len(r) > len(header) and any(c.strip() for c in r[len(header):]):
            hint = ' (quote the access_lps cell: "x,y,z")' if "access_lps" in header else ""
            raise InputError(f"{where}: {len(r)} fields, the header has {len(header)}{hint}")
        rec = {h: (r[i] if i < len(r) else "") for i, h in enumerate(header) if h}
        name = check_study_name(rec["study"], where)
        if name in seen:
            raise InputError(f"{where}: study {name!r} already on line {seen[name]}")
        seen[name] = line
        where = f"{where} (study {name})"
        files = {}
        for col in ("cta", "roadmap", "frames"):
            v = rec[col].strip()
            if not v:
                raise InputError(f"{where}: empty '{col}'")
            p = Path(os.path.expanduser(v))
            p = p if p.is_absolute() else base / p
            if not p.exists():
                raise InputError(f"{where}: {col}: {p}: no such file or folder")
            files[col] = str(p)
        cell = rec.get("access_lps", "").strip()
        opts = {c: _option(rec[c], c, where) for c in OPTION_COLUMNS
                if c in rec and not (c == "access_lps" and cell.lower() == NO_ACCESS)}
        opts = {k: v for k, v in opts.items() if v is not None}
        access = opts.pop("access_lps", None)
        if access is not None:
            opts.update(access_lps_mm=access, access_option=f"{where}: access_lps")
        elif cell.lower() != NO_ACCESS:
            opts.update(access_lps_mm=default_access)
        studies.append(StudySpec(name, files["cta"], files["roadmap"], files["frames"], source=where, **opts))
    return studies


# --------------------------------------------------------------------------------------
# a DICOM folder tree
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _XARun:
    path: str
    n_frames: int
    description: str
    when: str
    order: tuple
    angles_deg: tuple | None


def _header(path: Path):
    import pydicom

    try:
        with open(path, "rb") as f:
            if f.read(132)[128:132] != b"DICM":
                return None
        return pydicom.dcmread(str(path), stop_before_pixels=True,
                               specific_tags=["StudyInstanceUID", "SeriesInstanceUID", "Modality", "SOPClassUID",
                                              "NumberOfFrames",
                                              "SeriesDescription", "AcquisitionDateTime", "AcquisitionDate",
                                              "AcquisitionTime", "ContentDate", "ContentTime", "SeriesNumber",
                                              "InstanceNumber", "PositionerPrimaryAngle", "PositionerSecondaryAngle",
                                              "PatientID"])
    except Exception:  # noqa: BLE001 - not a readable DICOM file: not part of any study
        return None


def _text(ds, kw: str) -> str:
    v = ds.get(kw, "")
    return str(v if v is not None else "").strip()


def _angles(ds):
    try:
        return (float(ds.PositionerPrimaryAngle), float(ds.PositionerSecondaryAngle))
    except (AttributeError, TypeError, ValueError):
        return None


def choose_xa_runs(runs) -> tuple[str, str]:
    """The roadmap and the live frames of a study's XA runs (the rule of the README, 'batch').

    Roadmap: the run whose SeriesDescription names it (``ROADMAP_WORDS``), else the run with the
    fewest frames; ties go to the earliest acquisition. Live frames: of the other runs, the longest
    in the roadmap's view (positioner angles within ``SAME_VIEW_DEG``), else the longest of any
    view; ties go to the latest acquisition. A study with one run uses it for both (``reconstruct``
    then takes its most contrast-filled frame as the roadmap).
    """
    runs = sorted(runs, key=lambda r: (r.when, r.order))
    named = [r for r in runs if any(w in r.description.lower() for w in ROADMAP_WORDS)]
    road = named[0] if named else min(runs, key=lambda r: r.n_frames)  # min keeps the earliest of a tie
    others = [r for r in runs if r is not road]
    if not others:
        return road.path, road.path

    def same_view(r):
        return (r.angles_deg is not None and road.angles_deg is not None
                and max(abs(a - b) for a, b in zip(r.angles_deg, road.angles_deg)) < SAME_VIEW_DEG)

    pool = [r for r in others if same_view(r)] or others
    live = max(reversed(pool), key=lambda r: r.n_frames)  # max keeps the first: the latest of a tie
    return road.path, live.path


def group_dicom_tree(root, *, access_lps_mm=None, log=None) -> list[StudySpec]:
    """The studies of a DICOM folder tree, one per StudyInstanceUID, named by it.

    The CTA is the study's CT, MR or X-ray 3D (3DRA) series with the most slices (its files must lie in one folder); every
    XA or RF file is one run, and :func:`choose_xa_runs` picks the roadmap and the live frames.
    Files that are not DICOM, hidden files and other modalities are ignored. A study without a CT
    series or without an XA run is returned with ``error`` set (recorded as failed, not run).
    ``access_lps_mm`` ((3,) LPS mm, optional: ``--access-lps``) is every study's access point.

    Raises
    ------
    InputError
        ``root`` is not a folder, or holds no DICOM study at all; or ``access_lps_mm`` is not a point.
    """
    root = Path(root)
    access = None if access_lps_mm is None else tuple(float(c) for c in check_access(access_lps_mm))
    if not root.is_dir():
        raise InputError(f"{root}: not a folder")
    ct: dict[str, dict[str, list[Path]]] = {}
    xa: dict[str, list[_XARun]] = {}
    slices: dict[str, int] = {}  # per volume series: its slices (a multi-frame file's frames)
    seen_studies: list[str] = []
    n_files = 0
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for fn in sorted(filenames):
            if fn.startswith("."):
                continue
            p = Path(dirpath) / fn
            ds = _header(p)
            if ds is None:
                continue
            study = _text(ds, "StudyInstanceUID")
            modality = _text(ds, "Modality").upper()
            volume = modality in io.VOLUME_MODALITIES or _text(ds, "SOPClassUID") in io.XRAY_3D_STORAGE
            if not study or not (volume or modality in ("XA", "RF")):
                continue
            n_files += 1
            if study not in seen_studies:
                seen_studies.append(study)
            try:
                n = int(ds.get("NumberOfFrames", 1) or 1)
            except (TypeError, ValueError):
                n = 1
            if volume:  # the CTA (or MRA, 3DRA)
                uid = _text(ds, "SeriesInstanceUID")
                ct.setdefault(study, {}).setdefault(uid, []).append(p)
                slices[uid] = slices.get(uid, 0) + max(n, 1)
            else:
                when = (_text(ds, "AcquisitionDateTime")
                        or _text(ds, "AcquisitionDate") + _text(ds, "AcquisitionTime")
                        or _text(ds, "ContentDate") + _text(ds, "ContentTime"))
                order = (int(ds.get("SeriesNumber", 0) or 0), int(ds.get("InstanceNumber", 0) or 0), str(p))
                xa.setdefault(study, []).append(_XARun(str(p), n, _text(ds, "SeriesDescription"), when, order,
                                                       _angles(ds)))
    if not seen_studies:
        raise InputError(f"{root}: no DICOM CT or XA files found (expected a CSV manifest or a DICOM folder tree)")
    out = []
    for study in seen_studies:
        name = check_study_name(study, f"{root}: StudyInstanceUID")
        where = f"{root}: study {study}"
        series = ct.get(study, {})
        runs = xa.get(study, [])
        error = None
        cta = road = live = ""
        uid = None
        if not series:
            error = f"{where}: no CT, MR or X-ray 3D series (expected the CTA)"
        elif not runs:
            error = f"{where}: no XA run (expected a roadmap and live frames)"
        else:
            uid, files = max(series.items(), key=lambda kv: slices[kv[0]])
            folders = sorted({str(f.parent) for f in files})
            if len(folders) > 1:
                error = f"{where}: volume series {uid} is spread over {len(folders)} folders ({folders[0]}, ...); " \
                        "put its files in one folder"
            else:
                cta = folders[0]
                road, live = choose_xa_runs(runs)
        if log is not None:
            log(f"{name}: " + (error or f"CT {uid} ({slices[uid]} slices), roadmap {road}, frames {live}"))
        out.append(StudySpec(name, cta, road, live, series_uid=uid, access_lps_mm=access, source=where, error=error))
    return out


def load_studies(manifest, *, access_lps_mm=None, log=None) -> list[StudySpec]:
    """A CSV manifest (:func:`read_manifest`) or a DICOM folder tree (:func:`group_dicom_tree`);
    ``access_lps_mm``: the batch's ``--access-lps`` (a manifest's ``access_lps`` column overrides it)."""
    p = Path(manifest)
    if p.is_dir():
        return group_dicom_tree(p, access_lps_mm=access_lps_mm, log=log)
    return read_manifest(p, access_lps_mm=access_lps_mm)


# --------------------------------------------------------------------------------------
# one study (runs on a worker)
# --------------------------------------------------------------------------------------
def _reset_peak_rss() -> bool:
    """Reset the process's peak resident set (Linux: VmHWM), so that it measures one study."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _peak_rss_mb() -> float:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024.0 if sys.platform != "darwin" else kb / 2**20


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _xyz(point) -> str:
    """``"x,y,z"`` to 1e-3 mm (as report.json rounds a point), without trailing zeros."""
    return ",".join(f"{round(float(c), 3) + 0.0:.3f}".rstrip("0").rstrip(".") for c in point)


def _option_cells(*, series_uid, roadmap_frame, method, segmenter, force, track_motion, access_lps_mm) -> dict:
    """The option columns of a summary row (``OPTION_COLUMNS``), as a manifest would write them."""
    def flag(v):
        return "" if v is None else ("true" if v else "false")

    return {"series_uid": series_uid or "", "roadmap_frame": "" if roadmap_frame is None else int(roadmap_frame),
            "method": method or "", "segmenter": segmenter or "", "force": flag(force),
            "track_motion": flag(track_motion), "access_lps": "" if access_lps_mm is None else _xyz(access_lps_mm)}


def _asked_cells(spec: StudySpec) -> dict:
    return _option_cells(series_uid=spec.series_uid, roadmap_frame=spec.roadmap_frame, method=spec.method,
                         segmenter=spec.segmenter, force=spec.force, track_motion=spec.track_motion,
                         access_lps_mm=spec.access_lps_mm)


def _row_from_report(study: str, report: dict) -> dict:
    reg = report.get("registration", {})
    frames = report.get("frames", [])
    n_ok = sum(1 for f in frames if f.get("success"))
    inputs = report.get("inputs") or {}
    return {
        "study": study,
        "verdict": reg.get("verdict", ""),
        "residual_px": reg.get("mean_residual_px", ""),
        "frames_reconstructed": n_ok,
        "frames_total": len(frames) if frames else "",
        **_option_cells(series_uid=inputs.get("series_uid"), roadmap_frame=inputs.get("roadmap_frame"),
                        method=inputs.get("method"), segmenter=inputs.get("segmenter"), force=inputs.get("forced"),
                        track_motion=inputs.get("track_motion"), access_lps_mm=inputs.get("access_lps_mm")),
    }


def _worker_name() -> str:
    import socket

    return f"{socket.gethostname()}:{os.getpid()}"


def run_study(spec: StudySpec, out_root, *, images: bool = True, replace: bool = False) -> dict:
    """Reconstruct one study into ``out_root/<study>/`` (``pipeline.run_to_outdir``); its summary row.

    Bad input (a ``Guidewire3DError``) gives a ``failed`` row; any other exception propagates, so
    that the scheduler retries the task. ``seconds`` is the wall time of the study, ``peak_rss_mb``
    the peak resident memory of the process while it ran (Linux; elsewhere the process's peak).
    """
    row = {"study": spec.study, "worker": _worker_name(), **_asked_cells(spec)}
    if spec.error:  # not run
        return {**row, "status": FAILED, "error": _one_line(spec.error), "seconds": 0.0, "worker": ""}
    t0 = time.perf_counter()
    row["started"] = time.time()  # not in summary.csv: for scripts/bench_batch.py (a worker's first study)
    _reset_peak_rss()
    out = Path(out_root) / spec.study
    try:
        result = pipeline.run_to_outdir(spec.cta, spec.roadmap, spec.frames, out, series_uid=spec.series_uid,
                                        roadmap_frame=spec.roadmap_frame, method=spec.method,
                                        segmenter=spec.segmenter, force=spec.force, images=images,
                                        progress=False, replace=replace, track_motion=spec.track_motion,
                                        access_lps_mm=spec.access_lps_mm)
    except Guidewire3DError as e:
        return {**row, "status": FAILED, "error": _renamed_access(_one_line(e), spec.access_option),
                "seconds": round(time.perf_counter() - t0, 2), "peak_rss_mb": round(_peak_rss_mb(), 1)}
    reg = result.registration
    n_ok = sum(1 for w in result.wires3d if w.success)
    row.update(series_uid=result.volume.series_uid or "", roadmap_frame=int(result.roadmap_frame_index))  # as made
    return {**row, "status": DONE if result.reconstructed else NOT_RECONSTRUCTED,
            "verdict": reg.verdict.value, "residual_px": round(float(reg.mean_residual_px), 4),
            "frames_reconstructed": n_ok, "frames_total": len(result.frame_indices),
            "seconds": round(time.perf_counter() - t0, 2), "peak_rss_mb": round(_peak_rss_mb(), 1),
            "error": "" if result.reconstructed else _one_line(f"registration {reg.verdict.value}: {reg.message}; "
                                                               "frames were not reconstructed")}


def _automatic_roadmap_frame(roadmap) -> int | str:
    """The roadmap frame ``reconstruct`` chooses in ``roadmap`` without ``--roadmap-frame``, or why it
    cannot choose one (one line)."""
    try:
        return pipeline.choose_roadmap_frame(pipeline.read_xa_input(roadmap))
    except Guidewire3DError as e:
        return _one_line(e)


def _automatic_series(cta) -> str:
    """The series ``reconstruct`` reads from ``cta`` without ``--series-uid`` ("" for a NIfTI/NRRD/MHA
    file), or why it cannot read one (one line)."""
    try:
        return io.volume_files(cta)[0]
    except Guidewire3DError as e:
        return _one_line(e)


def _fingerprint_list(value) -> list[dict] | None:
    """``report.json``'s record of one input's files, None when it is not one."""
    if not isinstance(value, list) or not all(isinstance(d, dict) and {"name", "size", "sha256"} <= d.keys()
                                              for d in value):
        return None
    return value


def _changed_files(role: str, made_path: str, made: list[dict], path: Path, now: list[dict]) -> tuple[str, str] | None:
    """``(made with, asked for)`` naming the first file of input ``role`` whose content differs
    between ``made`` (recorded under ``made_path``) and ``now`` (read at ``path``); None when the two
    hold the same bytes (wherever the files lie now)."""
    def content(files):
        return sorted((int(d["size"]), str(d["sha256"])) for d in files)

    if content(made) == content(now):
        return None
    old, new = ({d["name"]: (int(d["size"]), str(d["sha256"])) for d in fs} for fs in (made, now))
    changed = [n for n in new if n in old and new[n] != old[n]]
    added = [n for n in new if n not in old]
    gone = [n for n in old if n not in new]
    base = path if path.is_dir() else path.parent  # the names are relative to it

    def at(name):
        return base / name

    def more(names, verb):
        return "" if len(names) < 2 else f" and {len(names) - 1} more {verb}"

    if changed:
        n = changed[0]
        return (f"the {role} file {at(n)} before it changed{more(changed, 'changed')}",
                f"the {role} file {at(n)} as it is now")
    if len(old) == len(new) == 1:  # one file, another name: the manifest names another file
        return f"the {role} file {made_path}", f"the {role} file {at(next(iter(new)))} (other bytes)"
    if added:
        n = added[0]
        return (f"the {role} {path} without {at(n)}{more(added, 'added')}", f"the {role} {path} with it (added)")
    n = gone[0]
    return f"the {role} {path} with {at(n)}{more(gone, 'gone')}", f"the {role} {path} without it (gone)"


def input_changes(spec: StudySpec, report: dict) -> list[tuple[str, str]] | None:
    """How the input files of ``spec`` differ from the ones the finished study (its ``report.json``
    read as ``report``) was made from: ``(made with, asked for)`` pairs naming the first file that
    changed, was added or is gone per input, [] when every file holds the same bytes (by size and
    SHA-256, wherever the files lie now), None when the report has no record of its files (made
    before ``report.json`` kept them: not comparable). The CTA's files are those of the series the
    study was made with (whether that is the series asked for is :func:`made_otherwise`'s question).
    """
    inputs = report.get("inputs") or {}
    record = inputs.get("files")
    if not isinstance(record, dict):
        return None
    made = {role: _fingerprint_list(record.get(role)) for role in ("cta", "roadmap", "frames")}
    if any(v is None for v in made.values()):
        return None
    try:
        now = pipeline.input_files(spec.cta, spec.roadmap, spec.frames, series_uid=inputs.get("series_uid") or None)
    except Guidewire3DError as e:
        return [("its input files as they were", f"input files that cannot be read now ({_one_line(e)})")]
    pairs = []
    for role in ("cta", "roadmap", "frames"):
        path = Path(getattr(spec, role))
        pair = _changed_files(role, str(inputs.get(role, path)), made[role], path, now[role])
        if pair is not None:
            pairs.append(pair)
    return pairs


NO_RECORD = ("no record of its input files (made before report.json kept them)",
             "input files it can compare with the ones the study was made from")


def made_otherwise(spec: StudySpec, folder, report: dict, *, images: bool = True,
                   files: bool = True) -> list[tuple[str, str]]:
    """What the finished study in ``folder`` (its ``report.json`` read as ``report``) was made with
    that ``spec`` does not ask for: ``(made with, asked for)`` pairs, [] when it is the study asked for.

    Compared: the access point (to 1e-3 mm, as the report rounds it), ``method``, ``segmenter``,
    ``track_motion``, ``series_uid`` (empty: the series ``reconstruct`` chooses, read from the CTA
    folder now), ``roadmap_frame`` (empty: the frame ``reconstruct`` chooses, read from the roadmap
    now), ``force`` only where it changes the result (the registration failed: forced, the frames
    were reconstructed anyway), ``images``: a study with reconstructed frames made without its PNGs
    (``--no-images``) is not the study a run with images asks for; one with PNGs serves a
    ``--no-images`` run; and with ``files``, the input files' bytes (:func:`input_changes`; a report
    without their record is not comparable: ``NO_RECORD``). A study whose inputs cannot be assembled
    now (``spec.error``: its DICOM tree lost the CT series, say) is not the study it was.
    """
    if spec.error:
        return [("its input files", f"a study without them ({_one_line(spec.error)})")]
    inputs = report.get("inputs") or {}
    stale = []
    had, want = (None if p is None else tuple(round(float(c), 3) for c in p)
                 for p in (inputs.get("access_lps_mm"), spec.access_lps_mm))
    if had != want:  # its tree was rooted elsewhere
        said = "no access point" if had is None else f"--access-lps={_xyz(had)}"
        asked = "none" if want is None else f"{spec.access_option}={_xyz(want)}"
        stale.append((said, asked))
    for key in ("method", "segmenter", "track_motion"):  # the options that change what a reconstruction gives
        if key in inputs and inputs[key] != getattr(spec, key):
            stale.append((f"{key} {inputs[key]}", f"{key} {getattr(spec, key)}"))
    uid = inputs.get("series_uid")
    if spec.series_uid is not None and uid is not None and uid != spec.series_uid:  # None: not a DICOM series
        stale.append((f"series_uid {uid}", f"series_uid {spec.series_uid}"))
    elif spec.series_uid is None and uid:  # made from a DICOM series: is it the one chosen now?
        auto = _automatic_series(spec.cta)
        if auto != uid:
            stale.append((f"series_uid {uid}", f"the automatic series_uid ({auto or 'none: not a DICOM series'})"))
    frame = inputs.get("roadmap_frame")
    if frame is not None:
        asked = spec.roadmap_frame if spec.roadmap_frame is not None else _automatic_roadmap_frame(spec.roadmap)
        if asked != frame:
            stale.append((f"roadmap_frame {frame}", f"roadmap_frame {asked}" if spec.roadmap_frame is not None
                          else f"the automatic roadmap_frame ({asked})"))
    if "forced" in inputs and not (report.get("registration") or {}).get("success", False) \
            and bool(inputs["forced"]) != spec.force:  # a registration that succeeded reconstructs either way
        stale.append((f"force {bool(inputs['forced'])} (the registration failed)", f"force {spec.force}"))
    if images and report.get("frames") and not any(Path(folder).glob("overlay_*.png")):
        stale.append(("--no-images", "images"))
    if files:
        changes = input_changes(spec, report)
        stale.extend([NO_RECORD] if changes is None else changes)
    return stale


def read_report(folder) -> dict | None:
    """The ``report.json`` of the output folder ``folder`` as a dict; None when the folder has none
    (not a finished study); an InputError naming it when it cannot be read as one."""
    import json

    rep = Path(folder) / REPORT_NAME
    if not rep.is_file():
        return None
    try:
        report = json.loads(rep.read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"{rep}: unreadable ({_one_line(getattr(e, 'strerror', None) or e)})") from None
    if not isinstance(report, dict):
        raise InputError(f"{rep}: unreadable (not a JSON object)")
    return report


def finished_row(spec: StudySpec, out_root, previous: dict | None = None, *, images: bool = True,
                 files: bool = True) -> dict | None:
    """The row of a study whose output folder exists with a report, else None: ``skipped`` (its
    values read from the report, the measures from ``previous``, its last summary row) when it was
    made as ``spec`` asks (:func:`made_otherwise`; ``files=False`` leaves the input files out, for a
    caller that compared them), else ``failed`` with why, the folder untouched. A report that cannot
    be read cannot be compared: ``failed`` too."""
    folder = Path(out_root) / spec.study
    prev = previous or {}
    try:
        report = read_report(folder)
    except InputError as e:
        return {"study": spec.study, **{k: prev.get(k, "") for k in ("seconds", "peak_rss_mb", "worker")},
                "status": FAILED, "error": f"{e}: remove the folder to reconstruct it again", **_asked_cells(spec)}
    if report is None:
        return None
    row = {**{k: prev.get(k, "") for k in ("seconds", "peak_rss_mb", "worker")},
           **_row_from_report(spec.study, report), "status": SKIPPED, "error": ""}
    stale = made_otherwise(spec, folder, report, images=images, files=files)
    if stale:
        # not the study this run asks for: never reuse it silently
        row.update(status=FAILED, error=refusal(folder, stale))
    return row


def refusal(folder, stale) -> str:
    """The one-line error of a finished study in ``folder`` made otherwise than asked (``stale``: the
    ``(made with, asked for)`` pairs of :func:`made_otherwise`)."""
    return (f"{folder}: it was made with {', '.join(a for a, _ in stale)}, this run asks for "
            f"{', '.join(b for _, b in stale)}: remove the folder to reconstruct it again")


# --------------------------------------------------------------------------------------
# summary.csv
# --------------------------------------------------------------------------------------
def read_summary(path) -> dict[str, dict]:
    """The rows of a ``summary.csv`` by study ({} if there is none or it is unreadable)."""
    try:
        with open(path, newline="") as f:
            return {r["study"]: r for r in csv.DictReader(f) if r.get("study")}
    except (OSError, csv.Error, KeyError, UnicodeDecodeError):
        return {}


def write_summary(path, rows) -> Path:
    """Write ``rows`` (dicts with ``SUMMARY_COLUMNS``) as a CSV, atomically."""
    def write(tmp):
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=SUMMARY_COLUMNS, extrasaction="ignore")
            w.writeheader()
            for r in rows:
                w.writerow({k: ("" if r.get(k) is None else r.get(k, "")) for k in SUMMARY_COLUMNS})

    return io.atomic_write_via(path, write)


# --------------------------------------------------------------------------------------
# the batch
# --------------------------------------------------------------------------------------
def writable_folder(path, what: str) -> Path:
    """Create folder ``path`` if needed and check that it can be written; an OutputError naming it
    (and ``what`` it is for) otherwise."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{path}: {what} exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{path}: cannot create the {what} ({e.strerror})") from None
    if not os.access(path, os.W_OK):
        raise OutputError(f"{path}: {what} is not writable")
    return path


def _client(workers: int | None, scheduler: str | None, log):
    """A ``dask.distributed.Client`` and the local cluster it owns (None with ``scheduler``)."""
    import dask
    from dask.distributed import Client, LocalCluster

    if scheduler:
        try:
            return Client(scheduler, timeout="20s"), None
        except (OSError, TimeoutError, ValueError) as e:
            raise InputError(f"--scheduler {scheduler}: cannot reach a Dask scheduler ({_one_line(e)})") from None
    n = int(workers or 1)
    # one thread per worker process: a study is CPU-bound, and torch/OpenMP threads stay at 1
    # (the nanny sets OMP_NUM_THREADS=1); memory is not limited (a study's peak is in the README)
    # (the statistical profiler, which samples the task's stack every 10 ms, is off: nobody reads it here)
    # (the scheduler's HTTP server, /health and /metrics, listens on a free port of 127.0.0.1: with
    # dashboard_address=None it still takes 8787, and a second cluster on the host then warns and moves)
    with dask.config.set({"distributed.worker.profile.enabled": False}):
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address="127.0.0.1:0", memory_limit=0, silence_logs=50)
    if log is not None:
        log(f"local Dask cluster: {n} worker process{'es' if n > 1 else ''} at {cluster.scheduler_address}")
    return Client(cluster), cluster


def run_batch(studies, out_dir, *, workers: int | None = None, scheduler: str | None = None, retries: int = 2,
              images: bool = True, progress: bool = True, log=None) -> list[dict]:
    """Reconstruct every study on a Dask cluster; write ``out_dir/summary.csv``; return its rows.

    Parameters
    ----------
    studies : list of StudySpec
    out_dir : path
        ``out_dir/<study>/`` per study (as ``reconstruct`` writes it) and ``out_dir/summary.csv``.
    workers : int, optional
        Worker processes of the local cluster (default 1). Ignored with ``scheduler``.
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://host:8786``). Its workers must see the input
        files and ``out_dir`` at the same paths (a shared file system).
    retries : int
        Further attempts for a study whose task raised unexpectedly (a crash, a lost worker).

    Studies with an output folder holding ``report.json`` are skipped (``status`` ``skipped``), or
    ``failed`` when made otherwise than asked (:func:`finished_row`; ``images`` is asked too).
    ``summary.csv`` is rewritten (atomically) after each study, so an interrupted batch leaves a
    summary of what it finished.
    """
    if workers is not None and int(workers) < 1:
        raise InputError(f"--workers {workers}: expected at least 1")
    if retries < 0:
        raise InputError(f"--retries {retries}: expected at least 0")
    out_dir = Path(os.path.abspath(out_dir))
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"{out_dir}: output folder exists and is not a folder")
    summary_path = out_dir / SUMMARY_NAME
    previous = read_summary(summary_path)
    rows: dict[str, dict] = {}
    todo = []
    refused = 0  # finished, but made otherwise than asked
    for s in studies:
        done = finished_row(s, out_dir, previous.get(s.study), images=images)
        if done is not None:
            rows[s.study] = done
            refused += done["status"] == FAILED
        elif s.error:
            rows[s.study] = run_study(s, out_dir)
        else:
            todo.append(s)
    if log is not None and len(rows):
        log(f"{sum(r['status'] == SKIPPED for r in rows.values())} studies already done (skipped), "
            + (f"{refused} made otherwise than asked (failed: see the error column of {summary_path}), "
               if refused else "") + f"{len(todo)} to run")

    def ordered():
        return [rows[s.study] for s in studies if s.study in rows]

    # the cluster first: a scheduler that cannot be reached is refused before anything is written
    client, cluster = _client(workers, scheduler, log) if todo else (None, None)
    try:
        writable_folder(out_dir, "output folder")
        write_summary(summary_path, ordered())
        if todo:
            io.clean_stale_staging(out_dir / todo[0].study)  # staging folders of killed runs, before any task
            _run_on(client, todo, out_dir, rows, retries=retries, images=images, progress=progress,
                    on_row=lambda: write_summary(summary_path, ordered()))
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
    final = ordered()
    write_summary(summary_path, final)
    return final


def _run_on(client, todo, out_dir, rows, *, retries, images, progress, on_row) -> None:
    from dask.distributed import as_completed

    futures = {}
    for s in todo:
        f = client.submit(run_study, s, str(out_dir), images=images, retries=retries, pure=False,
                          key=f"study-{s.study}-{os.getpid()}-{time.time_ns()}")
        futures[f] = s
    it = as_completed(list(futures))
    if progress:
        from tqdm import tqdm

        it = tqdm(it, total=len(futures), desc="studies", unit="study", file=sys.stderr)
    for f in it:
        s = futures[f]
        try:
            row = f.result()
        except Exception as e:  # noqa: BLE001 - retries exhausted: recorded, the batch goes on
            row = {"study": s.study, "status": FAILED, "error": _one_line(f"{e.__class__.__name__}: {e}"),
                   **_asked_cells(s)}
        rows[s.study] = row
        f.release()
        on_row()


def _counts(rows) -> str:
    n = {st: sum(1 for r in rows if r.get("status") == st) for st in STATUSES}
    return ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in n.items() if v)


# --------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------
def add_cli_options(p) -> None:
    p.add_argument("manifest", metavar="MANIFEST",
                   help="a CSV with the columns study,cta,roadmap,frames (optional: series_uid, roadmap_frame, "
                        "method, segmenter, force, track_motion, access_lps as a quoted \"x,y,z\" or none), or a "
                        "DICOM folder tree (one study per StudyInstanceUID; see README, 'batch')")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output folder: DIR/<study>/ per study and DIR/summary.csv")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", type=int, default=None, metavar="N",
                   help="worker processes of a local Dask cluster on 127.0.0.1 (default 1)")
    g.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="an existing Dask scheduler (e.g. tcp://10.0.0.5:8786); its workers must see the inputs "
                        "and --out at the same paths")
    p.add_argument("--retries", type=int, default=2, metavar="K",
                   help="further attempts for a study whose task crashed or lost its worker (default 2)")
    p.add_argument("--no-images", action="store_true", help="skip screenshot/overlay/metrics PNGs")


def cli_batch(args) -> int:
    def say(msg):
        print(msg, file=sys.stderr)

    studies = load_studies(args.manifest, access_lps_mm=getattr(args, "access_lps", None))
    if Path(args.manifest).is_dir():
        say(f"{args.manifest}: {len(studies)} studies ({sum(s.error is None for s in studies)} with a CTA series "
            "and XA runs)")
    rows = run_batch(studies, args.out, workers=args.workers, scheduler=args.scheduler, retries=args.retries,
                     images=not args.no_images, progress=True, log=say)
    print(f"wrote {Path(args.out) / SUMMARY_NAME}: {len(rows)} studies ({_counts(rows)})")
    if any(r.get("status") in (FAILED, NOT_RECONSTRUCTED) for r in rows):
        say(f"guidewire3d: some studies were not reconstructed; see the error column of "
            f"{Path(args.out) / SUMMARY_NAME}")
        return 1
    return 0

