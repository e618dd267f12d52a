"""Plane B of a biplane output folder in the viewer (issue 23).

``reconstruct`` with two ``--roadmap`` writes plane A's output folder plus ``report.json``
``biplane`` (each plane's C-arm, each pair's plane-B record). The biplane viewer
(``scene.new_plotter(biplane=True)``) has the 3D view on the left, plane A's 2D view top right and
plane B's bottom right. :func:`add_plane_b` adds plane B's source, frustum and detector to the 3D
view (under names of their own, ``*_b``, so plane A's stay) and plane B's 2D view: its live frame
(one texture shared with its detector), the projected centerline, its 2D wire and the projected 3D
wire. The controller moves them per frame and per pose with the ``scene`` update functions.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from guidewire3d.app.outdir import PlaneB, load_plane_b
from guidewire3d.geometry import Pose
from guidewire3d.viewer import scene as sc

__all__ = ["PlaneB", "PlaneBHandles", "plane_b_of_outdir", "add_plane_b", "PLANE_B_COLOR"]

PLANE_B_COLOR = (0.55, 0.85, 1.0)
PLANE_B_SOURCE_COLOR = (0.4, 0.8, 1.0)


def plane_b_of_outdir(out_dir) -> PlaneB | None:
    """Plane B of a biplane output folder (None for a single-view one): ``outdir.load_plane_b``."""
    return load_plane_b(out_dir)


@dataclass(frozen=True, eq=False)
class PlaneBHandles:
    """Plane B's actors: its C-arm in the 3D view and its 2D view (subplot ``(1, 1)``), if any."""

    carm: sc.CArmHandles
    overlay: sc.Overlay2DHandles | None
    renderer_2d: object | None
    info_text: object | None


def add_plane_b(plotter, plane_b: PlaneB, pose: Pose, *, tree=None, source_radius_mm: float = 8.0) -> PlaneBHandles:
    """Add plane B's C-arm (its live-frame view ``plane_b.frames_carm`` in ``pose``) to the 3D view and,
    on a biplane plotter (three viewports), plane B's 2D view with the projected ``tree`` centerline.

    The detector shows a grey image until the controller sets plane B's frame; the 2D wire overlays
    start empty.
    """
    carm = plane_b.frames_carm
    texture = sc.make_image_texture(np.full(carm.shape, 96, np.uint8))
    plotter.subplot(0, 0)
    carm_h = sc.add_carm(plotter, carm, pose, None, texture=texture, source_radius_mm=source_radius_mm,
                         name_suffix="_b", source_color=PLANE_B_SOURCE_COLOR, frustum_color=PLANE_B_COLOR)
    overlay = r2 = info = None
    if len(plotter.renderers) >= 3:
        plotter.subplot(1, 1)
        r2 = sc.renderer_at(plotter, 1, 1)
        r2.SetBackground(*sc.BACKGROUND_2D)
        r2.SetUseOIT(False)
        overlay = sc.add_overlay_2d(plotter, carm.shape, texture=texture,
                                    centerline_edges=tree.edges if tree is not None else None)
        if tree is not None:
            sc.update_overlay(overlay, centerline_uv_px=carm.project(tree.points_lps_mm, pose))
        info = sc.add_text(r2, "plane B", top=True, font_size=13, color=PLANE_B_COLOR)
        sc.fit_2d_camera(r2, carm.shape)
        plotter.subplot(0, 0)
    return PlaneBHandles(carm_h, overlay, r2, info)
