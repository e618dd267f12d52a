"""Plane B of a biplane output folder in the viewer's 3D scene (issue 23).

``reconstruct`` with two ``--roadmap`` writes plane A's output folder plus ``report.json``
``biplane`` (each plane's C-arm) and ``overlay_b_NNNN.png`` (plane B's 2D overlays). The viewer's
scene is plane A's; :func:`add_plane_b` adds plane B's source, frustum and detector (textured with
plane B's live frame) beside it, under names of their own so that plane A's actors stay.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from guidewire3d import io
from guidewire3d.app.outdir import display_images_uint8
from guidewire3d.geometry import CArm, Pose
from guidewire3d.viewer import scene as sc

__all__ = ["PlaneB", "plane_b_of_outdir", "add_plane_b"]

PLANE_B_COLOR = (0.55, 0.85, 1.0)


@dataclass(frozen=True, eq=False)
class PlaneB:
    carm: CArm
    images: np.ndarray | None  # (T, rows, cols) plane B's live frames, None if the file is gone
    frame_of: dict  # plane A frame index -> plane B frame index


def plane_b_of_outdir(out_dir) -> PlaneB | None:
    """Plane B of a biplane output folder (None for a single-view one)."""
    rep = json.loads((Path(out_dir) / "report.json").read_text())
    bp = rep.get("biplane")
    if not bp or len(bp.get("planes", [])) != 2:
        return None
    pb = bp["planes"][1]
    carm = CArm.from_dict(pb.get("frames_carm") or pb["carm"])
    images = None
    path = (rep.get("inputs") or {}).get("frames_b")
    if path and Path(path).is_file():
        run = io.read_xa(path)
        if tuple(run.frames.shape[1:]) == carm.shape:
            images = run.frames
    frame_of = {int(f["index"]): int((f.get("biplane") or {}).get("index_b", f["index"])) for f in rep.get("frames", [])}
    return PlaneB(carm, images, frame_of)


def add_plane_b(plotter, plane_b: PlaneB, pose: Pose, *, frame: int = 0, source_radius_mm: float = 8.0):
    """Add plane B's source, frustum and detector (its live frame ``frame_of[frame]``) to the 3D view
    (subplot (0, 0)); returns the detector actor."""
    import pyvista as pv
    import vtk

    plotter.subplot(0, 0)
    src, corners = sc._carm_geometry(plane_b.carm, pose)
    sphere = vtk.vtkSphereSource()
    sphere.SetCenter(*src)
    sphere.SetRadius(source_radius_mm)
    plotter.add_mesh(sphere, color=PLANE_B_COLOR, name="xray_source_b", reset_camera=False)
    fr = pv.PolyData(sc._frustum_points(src, corners), lines=np.column_stack([np.full(8, 2), sc._FRUSTUM_LINES]).ravel())
    plotter.add_mesh(fr, color=PLANE_B_COLOR, line_width=1.5, name="frustum_b", reset_camera=False, lighting=False,
                     opacity=0.8)
    img = np.full(plane_b.carm.shape, 96, np.uint8)
    if plane_b.images is not None and len(plane_b.images):
        k = min(plane_b.frame_of.get(int(frame), int(frame)), len(plane_b.images) - 1)
        img = display_images_uint8(plane_b.images[k:k + 1])[0]
    _, tex = sc.make_image_texture(img)
    det = plotter.add_mesh(sc._quad(corners), texture=tex, name="detector_b", reset_camera=False, lighting=False,
                           show_scalar_bar=False)
    det.GetProperty().BackfaceCullingOff()
    return det
