"""The vessel plan in the viewer: ``guidewire3d view DIR`` on a folder written by ``guidewire3d vessels``.

A planning folder has no C-arm and no wire: one 3D view of the vessel surface (translucent) and the centerline
coloured by radius, seen from the front (the patient's left on the screen's right, head up), with each tree's
numbers from ``vessels.json`` (branches, length, radii, the lumen and background levels and their units, the notes of
the vessel stage) and the keys. Seeds in separate structures give several trees (``vessels.json`` ``"trees"``): each
tree's surface gets its own colour and its caption line.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from guidewire3d.errors import InputError
from guidewire3d.viewer import scene as sc

__all__ = ["PlanView", "is_plan_folder", "load_plan", "plan_caption", "open_plan", "render_plan_screenshot",
           "run_plan_interactive", "PLAN_KEYS"]

PLAN_FILES = ("vessels.json", "centerline.vtp", "vessels.vtp")
#: surface colours of a forest's trees (the first tree in the viewer's vessel colour)
TREE_COLORS = (sc.VESSEL_COLOR, (0.55, 0.75, 1.0), (0.6, 0.95, 0.6), (1.0, 0.85, 0.45), (0.85, 0.6, 1.0))
PLAN_KEYS = (("c", "screenshot"), ("h", "screenshot x2"), ("r", "front view"), ("q", "quit"))


@dataclass(frozen=True, eq=False)
class PlanView:
    """What a planning folder holds: the surface and centerline (vtkPolyData, LPS mm) and ``vessels.json``."""

    folder: Path
    surface: object
    centerline: object
    record: dict


def is_plan_folder(folder) -> bool:
    """Whether ``folder`` was written by ``guidewire3d vessels`` (its files, and no ``report.json``)."""
    f = Path(folder)
    return all((f / n).is_file() for n in PLAN_FILES) and not (f / "report.json").is_file()


def load_plan(folder) -> PlanView:
    """Read a planning folder; InputError naming the file when one is missing or unreadable."""
    import pyvista as pv

    f = Path(folder)
    for n in PLAN_FILES:
        if not (f / n).is_file():
            raise InputError(f"{f}: no {n} (not a folder written by `guidewire3d vessels`)")
    try:
        record = json.loads((f / "vessels.json").read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"{f / 'vessels.json'}: not readable JSON ({e})") from None
    if not isinstance(record, dict) or "tree" not in record:
        raise InputError(f"{f / 'vessels.json'}: no 'tree' record (not written by `guidewire3d vessels`)")
    polys = []
    for n in ("vessels.vtp", "centerline.vtp"):
        try:
            polys.append(pv.read(str(f / n)))
        except Exception as e:  # VTK's readers raise many kinds; the file is named either way
            raise InputError(f"{f / n}: not a readable VTK PolyData file ({e})") from None
        if polys[-1].n_points == 0:
            raise InputError(f"{f / n}: empty (no points)")
    return PlanView(folder=f, surface=polys[0], centerline=polys[1], record=record)


def plan_caption(record: dict) -> str:
    """The caption: one line per tree (``vessels.json``'s ``"trees"``, else its top level) and its notes."""
    trees = record.get("trees") or [record]
    lines = [f"{len(trees)} separate vessel trees"] if len(trees) > 1 else []
    for k, t in enumerate(trees):
        tr, m = t.get("tree", {}), t.get("intensity_model", {})
        units = m.get("units") or ("HU" if m.get("hu") else "arbitrary units")
        seeds = t.get("seeds")
        head = "vessel tree" if len(trees) == 1 else \
            f"tree {k + 1}" + (f" (seeds {', '.join(str(i + 1) for i in seeds)})" if seeds else "")
        r = tr.get("radius_mm", {})
        nb = tr.get("n_branches", "?")
        lines.append(f"{head}: {nb} branch{'' if nb == 1 else 'es'}, {tr.get('total_length_mm', 0.0) / 10:.1f} cm, "
                     f"radius {r.get('median', float('nan')):.1f} / {r.get('max', float('nan')):.1f} mm, "
                     f"lumen {m.get('lumen', float('nan')):.4g} over {m.get('background', float('nan')):.4g} "
                     f"({units})")
        seg = t.get("segmentation", {})
        notes = [x for x in (seg.get("pruned"), seg.get("bias_field")) if x]
        if seg.get("first_pass_problems"):
            notes.insert(0, "first tree implausible: " + "; ".join(seg["first_pass_problems"]))
        for n in notes:
            lines.append("  note: " + (n if len(n) <= 110 else n[:107] + "..."))
    acc = record.get("access")
    if acc:
        lines.append(f"rooted at the access point ({acc.get('distance_mm', float('nan')):.1f} mm from it)")
    return "\n".join(lines)


def _front_camera(renderer, bounds) -> None:
    """From the front (anterior: -P), head up (+S): the patient's left on the screen's right."""
    b = np.asarray(bounds, dtype=float).reshape(3, 2)
    centre = b.mean(axis=1)
    extent = float(np.max(b[:, 1] - b[:, 0]))
    cam = renderer.GetActiveCamera()
    cam.SetFocalPoint(*centre)
    cam.SetPosition(*(centre - np.array([0.0, 3.0 * max(extent, 10.0), 0.0])))
    cam.SetViewUp(0.0, 0.0, 1.0)
    renderer.ResetCamera(*b.reshape(-1))
    renderer.ResetCameraClippingRange()
    sc.mark_camera_set(renderer)  # pyvista would put its own default view on the first render


def _tree_ids(poly) -> np.ndarray | None:
    arr = poly.point_data.get("tree") if hasattr(poly, "point_data") else None
    return None if arr is None else np.asarray(arr)


def open_plan(folder, *, size_px=(1200, 800), off_screen: bool = False):
    """A plotter showing the plan of ``folder``; returns ``(plotter, PlanView)``."""
    import pyvista as pv

    plan = load_plan(folder)
    if off_screen:
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    pl = sc.new_plotter(size_px=size_px, off_screen=off_screen, two_views=False,
                        title=f"guidewire3d plan: {Path(folder).name}")
    ids = _tree_ids(plan.surface)
    if ids is None or len(np.unique(ids)) < 2:
        sc.add_vessels(pl, plan.surface)
    else:
        for k in np.unique(ids):
            part = pv.wrap(plan.surface).extract_points(ids == k, adjacent_cells=False).extract_surface(algorithm="dataset_surface")
            actor = sc.add_vessels(pl, part, color=TREE_COLORS[int(k) % len(TREE_COLORS)])
            pl.remove_actor(actor)  # add_vessels names its actor "vessels": one per tree instead
            pl.add_actor(actor, name=f"vessels_{int(k)}", reset_camera=False)
    cl = pv.wrap(plan.centerline)
    sb = dict(title="vessel radius (mm)", vertical=False, position_x=0.62, position_y=0.06, width=0.34, height=0.06,
              n_labels=3, fmt="%.1f", label_font_size=12, title_font_size=12)
    pl.add_mesh(cl, scalars="radius_mm", cmap=sc.RADIUS_CMAP, line_width=2.0, show_scalar_bar=True,
                scalar_bar_args=sb, name="centerline", reset_camera=False, lighting=False)
    ren = pl.renderer
    sc.add_text(ren, plan_caption(plan.record), top=True, font_size=12)
    sc.add_text(ren, "  ".join(f"{k}: {d}" for k, d in PLAN_KEYS), top=False, font_size=11)
    _front_camera(ren, pv.wrap(plan.surface).bounds)
    return pl, plan


def render_plan_screenshot(folder, path, *, size=(1200, 800)) -> Path:
    """Render the plan of ``folder`` offscreen to the PNG ``path`` (written atomically); returns the path."""
    pl, _ = open_plan(folder, size_px=size, off_screen=True)
    try:
        pl.render()
        img = pl.screenshot(None, return_img=True)
    finally:
        pl.close()
    return sc.write_png(path, img)


def run_plan_interactive(folder, *, size_px=(1200, 800)) -> int:
    """The plan in a window; keys ``PLAN_KEYS`` (screenshots go into the folder). Returns 0."""
    import pyvista as pv

    pl, plan = open_plan(folder, size_px=size_px)
    shots = {"n": 0}

    def shot(scale: int) -> None:
        shots["n"] += 1
        path = plan.folder / f"plan_screenshot_{shots['n']:02d}.png"
        old = tuple(pl.window_size)
        pl.window_size = (scale * old[0], scale * old[1])
        pl.render()
        img = pl.screenshot(None, return_img=True)
        pl.window_size = old
        pl.render()
        print(f"screenshot written to {sc.write_png(path, img)}")

    def reset() -> None:
        _front_camera(pl.renderer, pv.wrap(plan.surface).bounds)
        pl.render()

    pl.add_key_event("c", lambda: shot(1))
    pl.add_key_event("h", lambda: shot(2))
    pl.add_key_event("r", reset)
    pl.show()
    return 0
