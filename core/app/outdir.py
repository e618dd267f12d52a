"""Read a reconstruct OUT_DIR (see the OUT_DIR contract in the README) back into plain data: the
reader of what :mod:`guidewire3d.app.export` writes, used by the viewer, the Slicer module and
``guidewire3d live --from OUT``.

Nothing here draws or imports pyvista; ``load_outdir`` returns frozen dataclasses of numpy arrays.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from guidewire3d import io
from guidewire3d.errors import InputError
from guidewire3d.geometry import CArm, Pose
from guidewire3d.io import atomic_write_text
from guidewire3d.vesseltree import VesselTree

__all__ = [
    "WireFrame",
    "ViewerCase",
    "PlaneBFrame",
    "PlaneB",
    "load_outdir",
    "load_plane_b",
    "save_registration",
    "display_images_uint8",
    "load_cta",
]


def _ro(a, dtype=float, shape_tail=None, *, what: str) -> np.ndarray:
    arr = np.array(a, dtype=dtype, copy=True)
    if shape_tail is not None:
        if arr.size == 0:
            arr = arr.reshape((0,) + shape_tail)
        if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
            raise InputError(f"{what}: expected shape (N, {', '.join(map(str, shape_tail))}), got {arr.shape}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class WireFrame:
    """The reconstructed guidewire of one live frame (from ``report.json``'s ``frames``).

    Attributes
    ----------
    index : int
        Frame index in the live run.
    success : bool
        Whether reconstruction succeeded for the frame.
    message : str
    points_lps_mm : (N, 3) ndarray of float
        Wire points, proximal -> distal (tip last). May be empty when ``success`` is false.
    uncertainty_mm : (N,) ndarray of float
    wire_uv_px : (M, 2) ndarray of float
        The detected 2D wire in pixel ``(u, v)``.
    projection_error_px : float
    length_mm : float
    verdict : str
        ``ok``, ``uncertain`` (``message`` says what is not settled, e.g. which end is the tip) or
        ``failed``.
    pose : Pose or None
        The frame's own pose when the run tracked motion (``--track-motion``), else None.
    """

    index: int
    success: bool
    message: str
    points_lps_mm: np.ndarray
    uncertainty_mm: np.ndarray
    wire_uv_px: np.ndarray
    projection_error_px: float = float("nan")
    length_mm: float = float("nan")
    verdict: str = "ok"
    pose: Pose | None = None


@dataclass(frozen=True, eq=False)
class ViewerCase:
    """Everything the viewer shows, loaded from one OUT_DIR.

    Attributes
    ----------
    out_dir : Path
    carm : CArm
        The registered roadmap view (what ``centerline_uv_px`` was measured in).
    frames_carm : CArm
        The live-frames view (what ``images`` and ``wire_uv_px`` are in).
    pose : Pose
        Current ``T_iso_from_lps`` (``registration.json`` ``pose``; manual if corrected).
    automatic_pose : Pose
        The pose found by automatic registration.
    pose_source : str
        ``"automatic"`` or ``"manual"``.
    registration : dict
        The registration quality record.
    tree : VesselTree or None
        The registered 3D centerline graph (``registration_inputs.npz``), None if absent.
    centerline_uv_px : (M, 2) ndarray of float
        The 2D roadmap centerline the registration used (empty if absent).
    centerline_radius_px : (M,) ndarray of float or None
        The vessel radius at each of those points (None if the file does not hold it).
    wires : tuple of WireFrame
        One per live frame, in frame order.
    images : (T, rows, cols) ndarray of float32 or None
        The live frames (read from ``inputs.frames``), None if that file is unavailable.
    roadmap_image : (rows, cols) ndarray of float32 or None
        The contrast roadmap frame the registration used (``inputs.roadmap``, ``roadmap_frame``).
    vessels_path, centerline_path : Path or None
    messages : tuple of str
        Non-fatal problems found while loading (missing optional files).
    """

    out_dir: Path
    carm: CArm
    frames_carm: CArm
    pose: Pose
    automatic_pose: Pose
    pose_source: str
    registration: dict
    tree: VesselTree | None
    centerline_uv_px: np.ndarray
    wires: tuple[WireFrame, ...]
    images: np.ndarray | None
    vessels_path: Path | None
    centerline_path: Path | None
    inputs: dict
    messages: tuple[str, ...] = ()
    roadmap_image: np.ndarray | None = None
    centerline_radius_px: np.ndarray | None = None

    @property
    def frame_indices(self) -> tuple[int, ...]:
        """Live-frame indices the viewer steps through: the reconstructed ones, else every image."""
        if self.wires:
            return tuple(int(w.index) for w in self.wires)
        if self.images is not None:
            return tuple(range(len(self.images)))
        return ()

    @property
    def n_frames(self) -> int:
        return len(self.frame_indices)

    @property
    def centroid_lps_mm(self) -> np.ndarray:
        """Centroid of the registered vessel centerline (rotation centre for manual correction)."""
        if self.tree is not None:
            return self.tree.centroid_lps_mm
        pts = [w.points_lps_mm for w in self.wires if len(w.points_lps_mm)]
        if pts:
            return np.vstack(pts).mean(axis=0)
        return self.pose.inverse().apply(np.zeros(3))

    def with_pose(self, pose: Pose, *, source: str) -> "ViewerCase":
        return replace(self, pose=pose, pose_source=source)

    def with_wires(self, wires) -> "ViewerCase":
        return replace(self, wires=tuple(wires))


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: no such file (not a guidewire3d output folder?)") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not valid JSON ({e})") from None


def _pose_from(value, *, what: str) -> Pose:
    if isinstance(value, dict) and "matrix" in value:
        value = value["matrix"]
    try:
        return Pose.from_matrix(np.asarray(value, dtype=float))
    except (TypeError, ValueError):
        raise InputError(f"{what}: expected a 4x4 matrix") from None


def _wire_from(rec: dict, k: int, path: Path) -> WireFrame:
    what = f"{path}: frames[{k}]"
    try:
        pts = _ro(rec.get("points_lps_mm") or [], shape_tail=(3,), what=f"{what}.points_lps_mm")
        unc = _ro(rec.get("uncertainty_mm") or [], what=f"{what}.uncertainty_mm").reshape(-1)
        uv = _ro(rec.get("wire_uv_px") or [], shape_tail=(2,), what=f"{what}.wire_uv_px")
    except (TypeError, ValueError):
        raise InputError(f"{what}: points/uncertainty are not numeric arrays") from None
    if len(unc) != len(pts):
        if len(unc) == 0:
            unc = _ro(np.zeros(len(pts)), what=what)
        else:
            raise InputError(f"{what}: uncertainty_mm has {len(unc)} values for {len(pts)} points")
    success = bool(rec.get("success", len(pts) > 1))
    frame_pose = None
    motion = rec.get("motion")
    if isinstance(motion, dict) and motion.get("pose") is not None:
        frame_pose = _pose_from(motion["pose"], what=f"{what}.motion.pose")
    return WireFrame(
        index=int(rec.get("index", k)),
        success=success,
        message=str(rec.get("verdict_message") or rec.get("message", "")),
        verdict=str(rec.get("verdict") or ("ok" if success else "failed")),
        pose=frame_pose,
        points_lps_mm=pts,
        uncertainty_mm=unc,
        wire_uv_px=uv,
        projection_error_px=float(rec.get("projection_error_px", float("nan")) or float("nan")),
        length_mm=float(rec.get("length_mm", float("nan")) or float("nan")),
    )


def load_outdir(out_dir, *, load_images: bool = True) -> ViewerCase:
    """Read an OUT_DIR written by ``guidewire3d reconstruct`` / ``demo``.

    Parameters
    ----------
    out_dir : path-like
        The output folder (holds ``report.json``).
    load_images : bool, keyword-only
        Read the live frames from ``report.json`` ``inputs.frames`` (an XA DICOM file).

    Returns
    -------
    ViewerCase

    Raises
    ------
    InputError
        If the folder or ``report.json`` is missing or malformed.
    """
    out = Path(out_dir)
    if not out.is_dir():
        raise InputError(f"{out}: no such output folder")
    report_path = out / "report.json"
    report = _read_json(report_path)
    msgs: list[str] = []
    if "carm" not in report:
        raise InputError(f"{report_path}: missing field 'carm'")
    carm = CArm.from_dict(report["carm"])
    frames_carm = CArm.from_dict(report["frames_carm"]) if report.get("frames_carm") else carm

    reg_path = out / "registration.json"
    if reg_path.exists():
        reg = _read_json(reg_path)
        if "pose" not in reg:
            raise InputError(f"{reg_path}: missing field 'pose'")
        pose = _pose_from(reg["pose"], what=f"{reg_path}: pose")
        auto = _pose_from(reg.get("automatic_pose", reg["pose"]), what=f"{reg_path}: automatic_pose")
        source = str(reg.get("source", "automatic"))
        registration = dict(reg.get("registration") or report.get("registration") or {})
    else:
        if "pose" not in report:
            raise InputError(f"{report_path}: missing field 'pose' (and no registration.json)")
        pose = _pose_from(report["pose"], what=f"{report_path}: pose")
        auto, source = pose, "automatic"
        registration = dict(report.get("registration") or {})
        msgs.append("registration.json missing: using report.json pose")

    tree = None
    cl_uv = np.zeros((0, 2))
    cl_r = None
    npz_path = out / "registration_inputs.npz"
    if npz_path.exists():
        try:
            with np.load(npz_path, allow_pickle=False) as z:
                lost = "tree_lost_lumen_lps_mm" in z and "tree_lost_lumen_step_mm" in z
                tree = VesselTree(z["tree_points_lps_mm"], z["tree_radius_mm"], z["tree_parent"],
                                  float(z["tree_centerline_sigma_mm"]) if "tree_centerline_sigma_mm" in z else None,
                                  np.asarray(z["tree_lost_lumen_lps_mm"], float).reshape(-1, 3) if lost else None,
                                  float(z["tree_lost_lumen_step_mm"]) if lost else None)
                cl_uv = np.asarray(z["centerline_uv_px"], dtype=float).reshape(-1, 2)
                cl_r = _radius_of(z, "centerline_radius_px", len(cl_uv))
        except (KeyError, ValueError, OSError) as e:
            raise InputError(f"{npz_path}: unreadable registration inputs ({e})") from None
    else:
        msgs.append("registration_inputs.npz missing: no centerline overlay, score or refine")
    cl_uv.setflags(write=False)

    frames = report.get("frames") or []
    if not isinstance(frames, list):
        raise InputError(f"{report_path}: 'frames' must be a list")
    wires = tuple(_wire_from(rec, k, report_path) for k, rec in enumerate(frames))

    inputs = dict(report.get("inputs") or {})
    images = None
    fpath = inputs.get("frames")
    if load_images:
        if fpath and Path(fpath).is_file():
            run = io.read_xa(fpath)
            if tuple(run.frames.shape[1:]) != frames_carm.shape:
                raise InputError(f"{fpath}: frame size {run.frames.shape[1:]} differs from frames_carm {frames_carm.shape}")
            images = run.frames
        else:
            msgs.append(f"live frames not found ({fpath}): detector shown blank")
    roadmap_image = None
    if load_images:
        rpath = inputs.get("roadmap")
        k = int(inputs.get("roadmap_frame", 0) or 0)
        if rpath and fpath and Path(rpath).resolve() == Path(fpath).resolve() and images is not None:
            roadmap_image = images[min(k, len(images) - 1)]
        elif rpath and Path(rpath).is_file():
            road = io.read_xa(rpath)
            if tuple(road.frames.shape[1:]) == carm.shape:
                roadmap_image = road.frames[min(k, len(road.frames) - 1)]
            else:
                msgs.append(f"roadmap {rpath}: size {road.frames.shape[1:]} differs from carm {carm.shape}")
    if images is not None and wires and len(images) < max(w.index for w in wires) + 1:
        msgs.append(f"only {len(images)} live frames for frame indices up to {max(w.index for w in wires)}")

    vessels = out / "vessels.vtp"
    if not vessels.exists():
        vessels = out / "vessels.stl" if (out / "vessels.stl").exists() else None
    centerline = out / "centerline.vtp" if (out / "centerline.vtp").exists() else None
    return ViewerCase(
        out_dir=out,
        carm=carm,
        frames_carm=frames_carm,
        pose=pose,
        automatic_pose=auto,
        pose_source=source,
        registration=registration,
        tree=tree,
        centerline_uv_px=cl_uv,
        wires=wires,
        images=images,
        vessels_path=vessels,
        centerline_path=centerline,
        inputs=inputs,
        messages=tuple(msgs),
        roadmap_image=roadmap_image,
        centerline_radius_px=cl_r,
    )


def _radius_of(z, key: str, n: int) -> np.ndarray | None:
    """The per-point radius array ``key`` of an npz, None when absent or not one value per point."""
    if key not in z.files:
        return None
    r = np.asarray(z[key], dtype=float).ravel()
    if len(r) != n:
        return None
    r.setflags(write=False)
    return r


@dataclass(frozen=True, eq=False)
class PlaneBFrame:
    """Plane B's side of one reconstructed pair (``report.json`` ``frames[k].biplane``).

    Attributes
    ----------
    index_b : int
        The frame of plane B's live run paired with plane A's ``index``.
    views : str
        Which planes made the 3D wire: ``"AB"``, ``"A"``, ``"B"`` or ``""``.
    fallback : str
        Why one plane was left out ("" when none).
    wire_uv_px : (M, 2) ndarray of float
        Plane B's detected 2D wire (empty when it was not found).
    projection_error_px_a, projection_error_px_b : float
        The 3D wire's projection error in each plane (NaN when not measured).
    """

    index_b: int
    views: str
    fallback: str
    wire_uv_px: np.ndarray
    projection_error_px_a: float = float("nan")
    projection_error_px_b: float = float("nan")


@dataclass(frozen=True, eq=False)
class PlaneB:
    """Plane B of a biplane OUT_DIR (``report.json`` ``biplane``, ``inputs.frames_b``).

    Attributes
    ----------
    carm, frames_carm : CArm
        Plane B's roadmap and live-frame views (same pose as plane A: one patient pose).
    images : (T, rows, cols) ndarray of float32 or None
        Plane B's live frames, None if the file is unavailable.
    frames : dict of int -> PlaneBFrame
        Plane A frame index -> plane B's side of that pair.
    centerline_uv_px : (M, 2) ndarray of float
        Plane B's roadmap centerline (``registration_inputs.npz`` ``centerline_b_uv_px``; empty for
        an output folder written before it was kept): with plane A's, the joint refinement's input.
    centerline_radius_px : (M,) ndarray of float or None
        The vessel radius at each of those points.
    """

    carm: CArm
    frames_carm: CArm
    images: np.ndarray | None
    frames: dict
    centerline_uv_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    centerline_radius_px: np.ndarray | None = None

    def frame_for(self, index: int) -> PlaneBFrame | None:
        return self.frames.get(int(index))

    def image_index(self, index: int) -> int:
        """Plane B's live-frame index paired with plane A's frame ``index`` (``index`` itself if unrecorded)."""
        f = self.frames.get(int(index))
        return int(f.index_b) if f is not None else int(index)


def _nan(x) -> float:
    return float("nan") if x is None else float(x)


def load_plane_b(out_dir, *, load_images: bool = True) -> PlaneB | None:
    """Plane B of a biplane OUT_DIR, None for a single-view one.

    Raises
    ------
    InputError
        If ``report.json`` is missing or its ``biplane`` record is malformed.
    """
    path = Path(out_dir) / "report.json"
    rep = _read_json(path)
    bp = rep.get("biplane")
    if not bp or len(bp.get("planes", [])) != 2:
        return None
    pb = bp["planes"][1]
    try:
        carm = CArm.from_dict(pb["carm"])
        frames_carm = CArm.from_dict(pb.get("frames_carm") or pb["carm"])
    except (KeyError, TypeError) as e:
        raise InputError(f"{path}: biplane.planes[1] has no usable C-arm ({e})") from None
    frames = {}
    for k, fr in enumerate(rep.get("frames") or []):
        b = fr.get("biplane")
        if not isinstance(b, dict):
            continue
        uv = _ro(b.get("wire_uv_px_b") or [], shape_tail=(2,), what=f"{path}: frames[{k}].biplane.wire_uv_px_b")
        idx = int(fr.get("index", k))
        frames[idx] = PlaneBFrame(int(b.get("index_b", idx)), str(b.get("views", "")), str(b.get("fallback", "")), uv,
                                  _nan(b.get("projection_error_px_a")), _nan(b.get("projection_error_px_b")))
    images = None
    fpath = (rep.get("inputs") or {}).get("frames_b")
    if load_images and fpath and Path(fpath).is_file():
        run = io.read_xa(fpath)
        if tuple(run.frames.shape[1:]) != frames_carm.shape:
            raise InputError(f"{fpath}: frame size {run.frames.shape[1:]} differs from plane B's frames_carm "
                             f"{frames_carm.shape}")
        images = run.frames
    cl_uv, cl_r = np.zeros((0, 2)), None
    npz_path = Path(out_dir) / "registration_inputs.npz"
    if npz_path.exists():
        try:
            with np.load(npz_path, allow_pickle=False) as z:
                if "centerline_b_uv_px" in z.files:
                    cl_uv = np.asarray(z["centerline_b_uv_px"], dtype=float).reshape(-1, 2)
                    cl_r = _radius_of(z, "centerline_b_radius_px", len(cl_uv))
        except (ValueError, OSError) as e:
            raise InputError(f"{npz_path}: unreadable registration inputs ({e})") from None
    cl_uv.setflags(write=False)
    return PlaneB(carm, frames_carm, images, frames, cl_uv, cl_r)


def save_registration(out_dir, pose: Pose, *, source: str, carm: CArm, automatic_pose: Pose,
                      registration: dict | None = None) -> Path:
    """Rewrite ``registration.json``'s ``pose``, ``projection_matrix`` and ``source`` (atomically).

    ``automatic_pose`` is kept as is; other fields already in the file are preserved.

    Returns
    -------
    Path
        The written file.
    """
    if source not in ("automatic", "manual"):
        raise InputError(f"registration source must be 'automatic' or 'manual', got {source!r}")
    path = Path(out_dir) / "registration.json"
    rec = _read_json(path) if path.exists() else {}
    rec["pose"] = pose.matrix.tolist()
    rec.setdefault("automatic_pose", automatic_pose.matrix.tolist())
    rec["projection_matrix"] = carm.projection_matrix(pose).tolist()
    rec["carm"] = carm.to_dict()
    rec["source"] = source
    reg = dict(rec.get("registration") or registration or {})
    reg["source"] = source
    rec["registration"] = reg
    return atomic_write_text(path, json.dumps(rec, indent=1))


def display_images_uint8(images, *, low_pct: float = 0.5, high_pct: float = 99.5) -> np.ndarray:
    """Window a frame stack to uint8 with one percentile window for the whole run.

    Parameters
    ----------
    images : (T, rows, cols) array_like
    low_pct, high_pct : float, keyword-only
        Percentiles mapped to 0 and 255.

    Returns
    -------
    (T, rows, cols) ndarray of uint8
        A new array (the input is untouched).
    """
    a = np.asarray(images, dtype=np.float32)
    sample = a[:, ::4, ::4] if a.ndim == 3 else a[::4, ::4]
    lo, hi = np.percentile(sample, [low_pct, high_pct])
    if not np.isfinite(lo) or not np.isfinite(hi) or hi <= lo:
        lo, hi = float(np.nanmin(a)), float(np.nanmax(a)) + 1e-6
    return np.clip((a - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


def load_cta(case: ViewerCase):
    """Read the CTA the case was reconstructed from (``report.json`` ``inputs.cta``).

    Returns
    -------
    guidewire3d.io.Volume

    Raises
    ------
    InputError
        If the path is not recorded or does not exist any more.
    """
    path = case.inputs.get("cta")
    if not path:
        raise InputError(f"{case.out_dir / 'report.json'}: inputs.cta is not recorded")
    if not Path(path).exists():
        raise InputError(f"{path}: the CTA of this case is not there any more")
    return io.read_volume(path, series_uid=case.inputs.get("series_uid") or None)
