"""Writing results: VTP/STL models, report.json, registration files, overlay and metrics images.

Every file is written atomically (a temporary sibling, then a rename). Models are in LPS mm;
STL headers and VTP field data carry ``SPACE=LPS`` so that 3D Slicer places them correctly.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from guidewire3d.io import atomic_write_bytes, atomic_write_text, atomic_write_via
from guidewire3d.metrics import evaluate_against_truth

__all__ = [
    "polyline_polydata",
    "wire_polydata",
    "tube_polydata",
    "write_polydata",
    "read_polydata",
    "write_report",
    "write_registration",
    "write_outdir",
    "overlay_image",
    "report_dict",
]

REPORT_VERSION = 1


# --------------------------------------------------------------------------------------
# VTK models
# --------------------------------------------------------------------------------------
def _vtk_array(values, name):
    from vtk.util.numpy_support import numpy_to_vtk

    arr = numpy_to_vtk(np.ascontiguousarray(values, dtype=float), deep=True)
    arr.SetName(name)
    return arr


def polyline_polydata(points_lps_mm, arrays: dict | None = None):
    """One VTK polyline through ``(N, 3)`` points with optional per-point arrays."""
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk

    pts = np.ascontiguousarray(np.asarray(points_lps_mm, dtype=float).reshape(-1, 3))
    vp = vtk.vtkPoints()
    vp.SetData(numpy_to_vtk(pts, deep=True))
    lines = vtk.vtkCellArray()
    if len(pts) >= 2:
        lines.InsertNextCell(len(pts))
        for i in range(len(pts)):
            lines.InsertCellPoint(i)
    poly = vtk.vtkPolyData()
    poly.SetPoints(vp)
    poly.SetLines(lines)
    for name, values in (arrays or {}).items():
        poly.GetPointData().AddArray(_vtk_array(values, name))
    return poly


def wire_polydata(wire):
    """The 3D wire as a polyline with ``uncertainty_mm`` and ``arclength_mm`` point arrays."""
    pts = np.asarray(wire.points_lps_mm, dtype=float)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))] if len(pts) else np.zeros(0)
    poly = polyline_polydata(pts, {"uncertainty_mm": np.asarray(wire.uncertainty_mm, float), "arclength_mm": arc})
    poly.GetPointData().SetActiveScalars("uncertainty_mm")
    return poly


#: Radius (mm) of the guidewire tube everywhere it is drawn or exported (the STL, the viewer, the
#: Slicer module): a 0.035 inch wire is 0.89 mm across, and 0.5 mm keeps a 0.014 inch one visible.
WIRE_TUBE_RADIUS_MM = 0.5


def tube_polydata(line_poly, radius_mm: float, *, sides: int = 12):
    """A closed tube surface (triangles) around a polyline."""
    import vtk

    tube = vtk.vtkTubeFilter()
    tube.SetInputData(line_poly)
    tube.SetRadius(float(radius_mm))
    tube.SetNumberOfSides(sides)
    tube.CappingOn()
    tri = vtk.vtkTriangleFilter()
    tri.SetInputConnection(tube.GetOutputPort())
    tri.Update()
    out = vtk.vtkPolyData()
    out.DeepCopy(tri.GetOutput())
    return out


def _tag_lps(poly):
    import vtk

    s = vtk.vtkStringArray()
    s.SetName("SPACE")
    s.InsertNextValue("LPS")
    poly.GetFieldData().AddArray(s)
    return poly


def write_polydata(poly, path) -> Path:
    """Write ``.vtp``, ``.vtk`` or ``.stl`` (binary, ``SPACE=LPS`` header) atomically."""
    import vtk

    path = Path(path)
    ext = path.suffix.lower()
    if ext == ".vtp":
        w = vtk.vtkXMLPolyDataWriter()
        w.SetDataModeToBinary()
        data = vtk.vtkPolyData()
        data.DeepCopy(poly)
        w.SetInputData(_tag_lps(data))
    elif ext == ".stl":
        w = vtk.vtkSTLWriter()
        w.SetFileTypeToBinary()
        w.SetHeader("SPACE=LPS")
        tri = vtk.vtkTriangleFilter()
        tri.SetInputData(poly)
        tri.Update()
        w.SetInputData(tri.GetOutput())
    elif ext == ".vtk":
        w = vtk.vtkPolyDataWriter()
        w.SetHeader("SPACE=LPS")
        w.SetInputData(poly)
    else:
        raise ValueError(f"{path}: unsupported model format {ext}")

    def _write(tmp):
        w.SetFileName(str(tmp))
        if w.Write() != 1:
            raise OSError(f"{path}: VTK writer failed")

    return atomic_write_via(path, _write)


def read_polydata(path):
    import vtk

    path = Path(path)
    r = {".vtp": vtk.vtkXMLPolyDataReader, ".stl": vtk.vtkSTLReader, ".vtk": vtk.vtkPolyDataReader}[path.suffix.lower()]()
    r.SetFileName(str(path))
    r.Update()
    return r.GetOutput()


# --------------------------------------------------------------------------------------
# JSON records
# --------------------------------------------------------------------------------------
def _f(x, nd=4):
    return None if x is None or not np.isfinite(x) else round(float(x), nd)


def registration_record(reg, *, source: str = "automatic") -> dict:
    return {
        "success": bool(reg.success),
        "verdict": reg.verdict.value,
        "message": str(reg.message),
        "mean_residual_px": _f(reg.mean_residual_px),
        "inlier_fraction": _f(reg.inlier_fraction),
        "pose_std_mm": _f(reg.pose_std_mm),
        "jackknife_std_mm": _f(getattr(reg, "jackknife_std_mm", float("nan"))),
        "depth_scan_rise": _f(getattr(reg, "depth_scan_rise", float("nan"))),
        "single_path": bool(reg.single_path),
        "covariance_6x6": (np.asarray(reg.covariance_6x6, float).tolist()
                           if reg.covariance_6x6 is not None and np.all(np.isfinite(reg.covariance_6x6)) else None),
        "iterations": int(reg.iterations),
        "seconds": _f(reg.seconds),
        "source": source,
    }


def frame_record(index: int, wire2d, wire3d, seconds: float, frame_result=None) -> dict:
    """A frame's entry of ``report.json`` (``frame_result``: its ``live.FrameResult``, for the verdict)."""
    pts = np.asarray(wire3d.points_lps_mm, float).reshape(-1, 3) if wire3d.success else np.zeros((0, 3))
    unc = np.asarray(wire3d.uncertainty_mm, float) if wire3d.success else np.zeros(0)
    uv = np.asarray(getattr(wire2d, "points_uv_px", np.zeros((0, 2))), float).reshape(-1, 2) if wire2d else np.zeros((0, 2))
    rec = {
        "index": int(index),
        "success": bool(wire3d.success),
        "message": str(wire3d.message),
        "points_lps_mm": np.round(pts, 4).tolist(),
        "uncertainty_mm": np.round(unc, 4).tolist(),
        "length_mm": _f(wire3d.length_mm) if wire3d.success else None,
        "projection_error_px": _f(wire3d.projection_error_px) if wire3d.success else None,
        "seconds": _f(seconds, 6),
        "wire_uv_px": uv.tolist(),  # full precision: the viewer and the plugin reconstruct from it again
        "verdict": frame_result.verdict.value if frame_result is not None else ("ok" if wire3d.success else "failed"),
        "verdict_message": frame_result.message if frame_result is not None else str(wire3d.message),
        "orientation": (frame_result.orientation.to_dict()
                        if frame_result is not None and frame_result.orientation is not None else None),
    }
    if frame_result is not None and frame_result.motion is not None:
        # --track-motion: the frame's own pose (the wire was reconstructed in it)
        rec["motion"] = frame_result.to_dict()["motion"]
    return rec


def report_dict(result, *, inputs: dict, truth_metrics: dict | None = None, source: str = "automatic") -> dict:
    reg = result.registration
    rep = {
        "version": REPORT_VERSION,
        "inputs": inputs,
        "carm": result.carm.to_dict(),
        "frames_carm": result.frames_carm.to_dict(),
        "pose": reg.pose.matrix.tolist(),
        "projection_matrix": np.asarray(reg.projection_matrix).tolist(),
        "registration": registration_record(reg, source=source),
        "frames": [
            frame_record(idx, w2, w3, s, fr)
            for idx, w2, w3, s, fr in zip(result.frame_indices, result.wires2d, result.wires3d, result.frame_seconds,
                                          result.frame_results or [None] * len(result.wires3d))
        ],
        "timing": {k: _f(v, 4) for k, v in result.timing.items()},
        "vessels": {
            "n_centerline_points": int(result.tree.n_points),
            "n_branches": len(result.tree.branches),
            "total_length_mm": _f(result.tree.total_length_mm, 2),
        },
    }
    if truth_metrics is not None:
        rep["truth"] = truth_metrics
    return rep


def write_report(result, out_dir, *, inputs: dict, truth=None) -> Path:
    tm = evaluate_against_truth(result, truth) if truth is not None else None
    return atomic_write_text(Path(out_dir) / "report.json", json.dumps(report_dict(result, inputs=inputs, truth_metrics=tm), indent=1))


def write_registration(out_dir, *, pose, automatic_pose, carm, reg_record: dict, source: str = "automatic") -> Path:
    rec = {
        "pose": pose.matrix.tolist(),
        "automatic_pose": automatic_pose.matrix.tolist(),
        "projection_matrix": carm.projection_matrix(pose).tolist(),
        "carm": carm.to_dict(),
        "source": source,
        "registration": dict(reg_record, source=source),
    }
    return atomic_write_text(Path(out_dir) / "registration.json", json.dumps(rec, indent=1))


def write_registration_inputs(out_dir, tree, centerline2d, centerline2d_b=None) -> Path:
    """``registration_inputs.npz``: the 3D tree and the roadmap's 2D centerline the registration used
    (and, for a biplane run, plane B's roadmap centerline: ``centerline_b_uv_px``,
    ``centerline_b_radius_px``), so that the viewer and the plugin can score and refine the pose."""
    import io as _io

    arrays = dict(
        tree_points_lps_mm=tree.points_lps_mm,
        tree_radius_mm=tree.radius_mm,
        tree_parent=tree.parent,
        centerline_uv_px=np.asarray(centerline2d.points_uv_px, float),
        centerline_radius_px=np.asarray(centerline2d.radius_px, float),
    )
    if getattr(tree, "centerline_sigma_mm", None) is not None:
        arrays["tree_centerline_sigma_mm"] = np.float64(tree.centerline_sigma_mm)
    if getattr(tree, "lost_lumen_lps_mm", None) is not None:
        arrays["tree_lost_lumen_lps_mm"] = np.asarray(tree.lost_lumen_lps_mm, float)
        arrays["tree_lost_lumen_step_mm"] = np.float64(tree.lost_lumen_step_mm)
    if centerline2d_b is not None:
        arrays["centerline_b_uv_px"] = np.asarray(centerline2d_b.points_uv_px, float)
        arrays["centerline_b_radius_px"] = np.asarray(centerline2d_b.radius_px, float)
    buf = _io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return atomic_write_bytes(Path(out_dir) / "registration_inputs.npz", buf.getvalue())


# --------------------------------------------------------------------------------------
# images
# --------------------------------------------------------------------------------------
def _to_u8(img) -> np.ndarray:
    img = np.asarray(img, dtype=np.float32)
    lo, hi = np.percentile(img, [0.5, 99.5])
    return (np.clip((img - lo) / max(hi - lo, 1e-6), 0, 1) * 255).astype(np.uint8)


def overlay_image(frame, *, centerline_uv_px=None, wire2d_uv_px=None, wire3d_uv_px=None, text: str = "") -> np.ndarray:
    """An RGB overlay: projected 3D centerline (green dots), detected 2D wire (yellow), projected 3D wire (red)."""
    import cv2

    g = _to_u8(frame)
    rgb = np.dstack([g, g, g])
    H, W = g.shape
    scale = 4  # sub-pixel drawing with cv2's shift

    def _poly(uv, color, thick):
        uv = np.asarray(uv, float).reshape(-1, 2)
        uv = uv[np.isfinite(uv).all(1)]
        if len(uv) >= 2:
            pts = np.rint(uv * (1 << scale)).astype(np.int32).reshape(-1, 1, 2)
            cv2.polylines(rgb, [pts], False, color, thick, cv2.LINE_AA, shift=scale)

    if centerline_uv_px is not None:
        uv = np.asarray(centerline_uv_px, float).reshape(-1, 2)
        uv = uv[np.isfinite(uv).all(1)]
        iu = np.rint(uv).astype(int)  # bounds on the rounded pixel: u in [W - 0.5, W) rounds to W
        iu = iu[(iu[:, 0] >= 0) & (iu[:, 0] < W) & (iu[:, 1] >= 0) & (iu[:, 1] < H)]
        rgb[iu[:, 1], iu[:, 0]] = (0, 200, 0)
    if wire2d_uv_px is not None:
        _poly(wire2d_uv_px, (255, 220, 0), 1)
    if wire3d_uv_px is not None:
        _poly(wire3d_uv_px, (255, 40, 40), 1)
    if text:
        cv2.putText(rgb, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return rgb


def write_png(path, rgb) -> Path:
    """Write an (H, W, 3) RGB or (H, W) grey uint8 image as PNG (atomically)."""
    import cv2

    a = np.asarray(rgb, np.uint8)
    ok, buf = cv2.imencode(".png", a if a.ndim == 2 else cv2.cvtColor(a, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    return atomic_write_bytes(path, buf.tobytes())


def frame_pose(frame_result, registration_pose):
    """The pose a live frame's wire was reconstructed in: its tracked pose (``--track-motion``), else the
    registration's."""
    if frame_result is not None and getattr(frame_result, "motion", None) is not None \
            and getattr(frame_result, "pose", None) is not None:
        return frame_result.pose
    return registration_pose


def overlay_uv(result, k: int, *, registered_tree_uv=None):
    """``(tree_uv_px, wire3d_uv_px or None)`` drawn on live frame ``k``'s overlay: the tree and the 3D wire projected in
    the pose the wire was reconstructed in (:func:`frame_pose`: a tracked frame's own, else the registration's).
    ``registered_tree_uv``: the tree projected in the registration's pose, when the caller has it (every frame not
    tracked shares it)."""
    reg_pose = result.registration.pose
    frs = getattr(result, "frame_results", None) or []
    pose = frame_pose(frs[k] if k < len(frs) else None, reg_pose)
    if pose is not reg_pose:
        tree_uv = result.frames_carm.project(result.tree.points_lps_mm, pose)
    elif registered_tree_uv is not None:
        tree_uv = registered_tree_uv
    else:
        tree_uv = result.carm.project(result.tree.points_lps_mm, reg_pose)
    w3 = result.wires3d[k]
    return tree_uv, (result.frames_carm.project(w3.points_lps_mm, pose) if w3.success else None)


def tracked_motion_mm(result) -> np.ndarray | None:
    """(T, 3) shift of the tree's centroid under each frame's tracked pose against the registration,
    in the C-arm's (u, v, depth) axes, mm; None when the run did not track motion."""
    frs = list(getattr(result, "frame_results", []) or [])
    if not frs or all(fr.motion is None for fr in frs):
        return None
    c = result.tree.points_lps_mm.mean(axis=0)
    base = result.registration.pose.apply(c[None])[0]
    axes = result.frames_carm.axes
    out = np.full((len(frs), 3), np.nan)
    for k, fr in enumerate(frs):
        if fr.pose is not None:
            out[k] = axes @ (fr.pose.apply(c[None])[0] - base)
    return out


def metrics_figure(result, path, *, plane_errors_px=None) -> Path:
    """Per-frame projection error, length and mean uncertainty (and the tracked motion, when the
    run tracked it), as a PNG.

    ``plane_errors_px`` : (T, 2) array_like of float, optional
        A biplane run's projection error of each frame's 3D wire in plane A and in plane B (NaN
        where not measured); the projection-error plot then shows one line per plane.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    idx = np.array(result.frame_indices)
    ok = np.array([w.success for w in result.wires3d], bool)
    perr = np.array([w.projection_error_px if w.success else np.nan for w in result.wires3d], float)
    length = np.array([w.length_mm if w.success else np.nan for w in result.wires3d], float)
    unc = np.array([float(np.mean(w.uncertainty_mm)) if w.success and len(w.uncertainty_mm) else np.nan for w in result.wires3d])
    motion = tracked_motion_mm(result)
    rows = 3 + (motion is not None)
    fig, axes = plt.subplots(rows, 1, figsize=(6, 2 * rows), sharex=True)
    planes = None if plane_errors_px is None else np.asarray(plane_errors_px, float).reshape(-1, 2)
    for ax, y, lab in zip(axes, (perr, length, unc), ("projection error (px)", "wire length (mm)", "mean uncertainty (mm)")):
        if y is perr and planes is not None:
            for j, name in enumerate("AB"):
                ax.plot(idx, planes[:, j], "o-", ms=3, label=f"plane {name}")
            ax.legend(fontsize=7, ncol=2)
        else:
            ax.plot(idx, y, "o-", ms=3)
        if (~ok).any():
            ax.plot(idx[~ok], np.zeros((~ok).sum()), "rx", label="not reconstructed")
        ax.set_ylabel(lab, fontsize=8)
        ax.grid(alpha=0.3)
    if motion is not None:  # --track-motion: how the tracked pose moved the tree's centroid
        ax = axes[3]
        for k, (lab, col) in enumerate((("image u", "C0"), ("image v", "C1"), ("depth", "C2"))):
            ax.plot(idx, motion[:, k], "o-", ms=2, color=col, label=lab)
        ax.set_ylabel("tracked motion (mm)", fontsize=8)
        ax.legend(fontsize=7, ncol=3)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("frame")
    fig.suptitle("guidewire3d per-frame metrics", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    atomic_write_via(path, lambda tmp: fig.savefig(tmp, dpi=100, format="png"))
    plt.close(fig)
    return path


# --------------------------------------------------------------------------------------
# the whole folder
# --------------------------------------------------------------------------------------
def write_outdir(result, out_dir, *, inputs: dict, images: bool = True, truth=None, screenshot=None,
                 plane_errors_px=None, centerline2d_b=None) -> Path:
    """Write every file of the output folder (see the README, "Output folder").

    ``plane_errors_px`` ((T, 2), a biplane run's per-plane projection errors): ``overlay_NNNN.png``
    states plane A's and ``metrics.png`` plots both planes'. ``centerline2d_b``: a biplane run's
    plane B roadmap centerline, kept in ``registration_inputs.npz`` beside plane A's.
    """
    out_dir = Path(out_dir)
    tree = result.tree
    write_polydata(tree.to_polydata(), out_dir / "centerline.vtp")
    write_polydata(result.vessels.surface, out_dir / "vessels.stl")
    write_polydata(result.vessels.surface, out_dir / "vessels.vtp")
    reg = result.registration
    write_registration(out_dir, pose=reg.pose, automatic_pose=reg.pose, carm=result.carm,
                       reg_record=registration_record(reg))
    write_registration_inputs(out_dir, tree, result.centerline2d, centerline2d_b)
    for idx, w3 in zip(result.frame_indices, result.wires3d):
        if not w3.success:
            continue
        line = wire_polydata(w3)
        write_polydata(line, out_dir / f"guidewire_{idx:04d}.vtp")
        write_polydata(tube_polydata(line, WIRE_TUBE_RADIUS_MM), out_dir / f"guidewire_{idx:04d}.stl")
    write_report(result, out_dir, inputs=inputs, truth=truth)
    if images:
        planes = None if plane_errors_px is None else np.asarray(plane_errors_px, float).reshape(-1, 2)
        cl_uv = result.carm.project(tree.points_lps_mm, reg.pose)
        for k, (idx, frame, w2, w3) in enumerate(zip(result.frame_indices, result.frames, result.wires2d,
                                                      result.wires3d)):
            cl_k, w3uv = overlay_uv(result, k, registered_tree_uv=cl_uv)
            perr = w3.projection_error_px if planes is None else planes[k, 0]
            txt = (f"frame {idx}: proj err {perr:.2f} px, length {w3.length_mm:.1f} mm"
                   if w3.success else f"frame {idx}: {w3.message}")
            rgb = overlay_image(frame, centerline_uv_px=cl_k, wire2d_uv_px=getattr(w2, "points_uv_px", None) if w2 else None,
                                wire3d_uv_px=w3uv, text=txt)
            write_png(out_dir / f"overlay_{idx:04d}.png", rgb)
        if result.wires3d:
            metrics_figure(result, out_dir / "metrics.png", plane_errors_px=plane_errors_px)
        if screenshot is not None:
            screenshot(out_dir, out_dir / "screenshot.png")
    return out_dir
