"""Scene building for the viewer: functions that add actors to a plotter and return handles.

Nothing here shows a window or registers a callback. The real-time path (``update_wire``,
``update_carm``, ``update_overlay``, ``set_frame_image``) changes the points and scalars of the
existing VTK objects in place; no actor is added or removed after ``build_scene``.

Coordinates: the 3D viewport is in LPS mm. The 2D viewport draws the image plane with pixel
``(u, v)`` at world ``(u, -v, 0)`` so that row 0 (``v = 0``) is at the top, as on the C-arm monitor.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from guidewire3d.app.export import WIRE_TUBE_RADIUS_MM
from guidewire3d.errors import InputError
from guidewire3d.io import atomic_write_bytes
from guidewire3d.geometry import CArm, Pose

__all__ = [
    "WireHandles",
    "CArmHandles",
    "Overlay2DHandles",
    "SceneHandles",
    "new_plotter",
    "renderer_at",
    "add_vessels",
    "add_centerline",
    "add_wire",
    "update_wire",
    "add_carm",
    "update_carm",
    "make_image_texture",
    "set_texture_image",
    "add_overlay_2d",
    "update_overlay",
    "build_scene",
    "set_frame_image",
    "set_text",
    "add_text",
    "beams_eye_camera",
    "overview_camera",
    "fit_2d_camera",
    "world_to_display_px",
    "volume_image_data",
    "add_cta_slices",
    "WIRE_RADIUS_MM",
    "UNCERTAINTY_CLIM_MM",
]

WIRE_RADIUS_MM = WIRE_TUBE_RADIUS_MM  # one value for every front end (export.WIRE_TUBE_RADIUS_MM)
UNCERTAINTY_CLIM_MM = (0.0, 2.0)
UNCERTAINTY_CMAP = "plasma"
RADIUS_CMAP = "viridis"
VESSEL_COLOR = (0.95, 0.6, 0.55)
CENTERLINE_2D_COLOR = (1.0, 0.85, 0.1)
WIRE_2D_COLOR = (1.0, 0.2, 0.8)
WIRE_PROJ_COLOR = (0.2, 1.0, 0.4)
ROADMAP_CENTERLINE_COLOR = (0.1, 0.85, 1.0)
FRUSTUM_COLOR = (0.55, 0.75, 1.0)
BACKGROUND_3D = (0.08, 0.09, 0.12)
BACKGROUND_2D = (0.0, 0.0, 0.0)
Z_IMAGE_2D = 0.0
Z_OVERLAY_2D = (0.5, 1.0, 1.5)  # centerline, detected wire, projected 3D wire


# --------------------------------------------------------------------------------------
# small VTK helpers
# --------------------------------------------------------------------------------------
def _vtk_points(points) -> "object":
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk

    vp = vtk.vtkPoints()
    vp.SetData(numpy_to_vtk(np.ascontiguousarray(np.asarray(points, dtype=float).reshape(-1, 3)), deep=True))
    return vp


def _cells(offsets, connectivity):
    import vtk
    from vtk.util.numpy_support import numpy_to_vtkIdTypeArray

    ca = vtk.vtkCellArray()
    ca.SetData(
        numpy_to_vtkIdTypeArray(np.ascontiguousarray(offsets, dtype=np.int64), deep=True),
        numpy_to_vtkIdTypeArray(np.ascontiguousarray(connectivity, dtype=np.int64), deep=True),
    )
    return ca


def _named_array(values, name: str):
    from vtk.util.numpy_support import numpy_to_vtk

    arr = numpy_to_vtk(np.ascontiguousarray(np.asarray(values, dtype=float).reshape(-1)), deep=True)
    arr.SetName(name)
    return arr


def _dedupe_polyline(points, values=None, *, min_step_mm: float = 1e-6):
    """Drop consecutive duplicate points (the tube filter cannot orient a zero-length segment)."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(p) < 2:
        return p, (None if values is None else np.asarray(values, float).reshape(-1))
    keep = np.r_[True, np.linalg.norm(np.diff(p, axis=0), axis=1) > min_step_mm]
    v = None if values is None else np.asarray(values, float).reshape(-1)[keep]
    return p[keep], v


def _set_polyline(poly, points, arrays: dict | None = None) -> None:
    """Replace, in place, the points / single polyline cell / point arrays of ``poly``."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    n = len(pts)
    poly.SetPoints(_vtk_points(pts))
    if n >= 2:
        poly.SetLines(_cells([0, n], np.arange(n)))
    else:
        poly.SetLines(_cells([0], []))
    for name, values in (arrays or {}).items():
        pd = poly.GetPointData()
        pd.RemoveArray(name)
        pd.AddArray(_named_array(values, name))
        pd.SetActiveScalars(name)
    poly.Modified()


def _uv_to_plane(uv_px, z: float) -> np.ndarray:
    uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
    return np.column_stack([uv[:, 0], -uv[:, 1], np.full(len(uv), float(z))])


# --------------------------------------------------------------------------------------
# handles
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class WireHandles:
    """The guidewire tube: ``polyline`` (input, points replaced in place) -> ``tube`` -> ``actor``."""

    polyline: object  # pyvista.PolyData
    tube: object  # vtkTubeFilter
    actor: object


@dataclass(frozen=True, eq=False)
class CArmHandles:
    """The C-arm drawn in its pose: source sphere, frustum/outline lines, textured detector quad."""

    source: object  # vtkSphereSource
    source_actor: object
    frustum: object  # pyvista.PolyData (lines)
    frustum_actor: object
    detector: object  # pyvista.PolyData (one quad with texture coordinates)
    detector_actor: object
    texture_image: object  # vtkImageData shared with the 2D view


@dataclass(frozen=True, eq=False)
class Overlay2DHandles:
    """The 2D view: the frame image and the overlays in pixel coordinates."""

    image: object  # pyvista.PolyData quad
    image_actor: object
    centerline: object  # pyvista.PolyData, tree edges
    centerline_actor: object
    wire2d: object
    wire2d_actor: object
    wire_proj: object
    wire_proj_actor: object
    shape: tuple[int, int]
    roadmap_centerline: object = None  # pyvista.PolyData points: the 2D roadmap centerline (registration target)
    roadmap_centerline_actor: object = None


@dataclass(frozen=True, eq=False)
class SceneHandles:
    """Everything ``build_scene`` made; the controller updates these in place."""

    plotter: object
    renderer_3d: object
    renderer_2d: object | None
    vessels_actor: object | None
    centerline_actor: object | None
    wire: WireHandles
    carm: CArmHandles
    overlay: Overlay2DHandles | None
    info_text: object | None  # vtkTextActor, top of the 2D view
    status_text: object | None  # vtkTextActor, bottom of the 2D view
    help_text: object | None


def write_png(path, image_rgb) -> Path:
    """A rendered image (``(H, W, 3|4)`` uint8 RGB[A], as ``Plotter.screenshot`` returns it) written to the PNG
    ``path`` atomically (nothing half-written); returns the path."""
    import cv2

    path = Path(path)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(np.asarray(image_rgb)[..., :3][..., ::-1]))
    if not ok:
        raise InputError(f"{path}: PNG encoding failed")
    atomic_write_bytes(path, buf.tobytes())
    return path


# --------------------------------------------------------------------------------------
# plotter
# --------------------------------------------------------------------------------------
def new_plotter(*, size_px=(1200, 800), off_screen: bool = False, two_views: bool = True, biplane: bool = False,
                title: str = "guidewire3d"):
    """A pyvista Plotter with one (3D) or two (3D | 2D) viewports. ``multi_samples=0`` (fast).

    ``biplane=True``: three viewports, the 3D view on the left half (subplot ``(0, 0)``), plane A's
    2D view top right (``(0, 1)``) and plane B's bottom right (``(1, 1)``).
    """
    import pyvista as pv

    theme = pv.themes.DarkTheme()
    theme.multi_samples = 0
    theme.allow_empty_mesh = True
    theme.font.color = "white"
    layout = dict(shape=(2, 2), groups=[(np.s_[:], 0)]) if biplane else dict(shape=(1, 2) if two_views else (1, 1))
    pl = pv.Plotter(
        **layout,
        window_size=tuple(int(s) for s in size_px),
        off_screen=off_screen,
        border=False,
        title=title,
        theme=theme,
    )
    return pl


def renderer_at(plotter, row: int, col: int):
    """The renderer of subplot ``(row, col)`` (also inside a group spanning several cells)."""
    return plotter.renderers[plotter.renderers.loc_to_index((row, col))]


# --------------------------------------------------------------------------------------
# 3D content
# --------------------------------------------------------------------------------------
def add_vessels(plotter, surface, *, opacity: float = 0.3, color=VESSEL_COLOR, max_triangles: int = 60000):
    """The vessel surface (LPS mm), semi-transparent (decimated above ``max_triangles``). Returns the actor."""
    import pyvista as pv

    mesh = pv.wrap(surface).copy(deep=False)
    mesh.clear_data()
    mesh = mesh.triangulate()
    if mesh.n_cells > max_triangles:  # display only: software rendering is fill/vertex bound
        mesh = mesh.decimate_pro(1.0 - max_triangles / mesh.n_cells, preserve_topology=True)
    actor = plotter.add_mesh(mesh, color=color, opacity=opacity, smooth_shading=True, specular=0.2,
                             ambient=0.6, diffuse=0.7, name="vessels", reset_camera=False)
    # one translucent layer (front faces) reads better and halves the blending work
    actor.GetProperty().BackfaceCullingOn()
    return actor


def add_centerline(plotter, tree, *, line_width: float = 2.0, show_scalar_bar: bool = True):
    """The vessel centerline as lines coloured by ``radius_mm``, with a scalar bar. Returns the actor."""
    import pyvista as pv

    poly = pv.wrap(tree.to_polydata())
    sb = dict(title="vessel radius (mm)", vertical=False, position_x=0.60, position_y=0.90, width=0.36, height=0.06,
              n_labels=3, fmt="%.1f", label_font_size=12, title_font_size=12)
    return plotter.add_mesh(poly, scalars="radius_mm", cmap=RADIUS_CMAP, line_width=line_width,
                            render_lines_as_tubes=False, show_scalar_bar=show_scalar_bar, scalar_bar_args=sb,
                            name="centerline", reset_camera=False, lighting=False)


def add_wire(plotter, points_lps_mm, uncertainty_mm, *, radius_mm: float = WIRE_RADIUS_MM,
             clim_mm=UNCERTAINTY_CLIM_MM, show_scalar_bar: bool = True, sides: int = 12) -> WireHandles:
    """The guidewire as a tube coloured by per-point ``uncertainty_mm``, with a scalar bar in mm.

    Parameters
    ----------
    points_lps_mm : (N, 3) array_like of float
    uncertainty_mm : (N,) array_like of float
    radius_mm, clim_mm, show_scalar_bar, sides : keyword-only
        Tube radius, colour range (mm), scalar bar and tube resolution.
    """
    import pyvista as pv
    import vtk

    line = pv.PolyData()
    pts, unc = _dedupe_polyline(points_lps_mm, uncertainty_mm)
    _set_polyline(line, pts, {"uncertainty_mm": unc})
    tube = vtk.vtkTubeFilter()
    tube.SetInputData(line)
    tube.SetRadius(float(radius_mm))
    tube.SetNumberOfSides(int(sides))
    tube.CappingOn()
    tube.SetVaryRadiusToVaryRadiusOff()
    sb = dict(title="wire uncertainty (mm)", vertical=False, position_x=0.60, position_y=0.78, width=0.36,
              height=0.06, n_labels=5, fmt="%.1f", label_font_size=12, title_font_size=12)
    # our own mapper on the tube's output port, so a changed polyline re-runs the tube at render time
    from pyvista.plotting.mapper import DataSetMapper

    mapper = DataSetMapper()
    mapper.SetInputConnection(tube.GetOutputPort())
    mapper.SetScalarModeToUsePointFieldData()
    mapper.SelectColorArray("uncertainty_mm")
    mapper.ScalarVisibilityOn()
    lut = pv.LookupTable(cmap=UNCERTAINTY_CMAP)
    lut.scalar_range = tuple(float(c) for c in clim_mm)
    mapper.lookup_table = lut
    mapper.SetScalarRange(*lut.scalar_range)
    mapper.SetUseLookupTableScalarRange(True)
    actor = pv.Actor(mapper=mapper)
    prop = actor.GetProperty()
    prop.SetAmbient(0.35)
    prop.SetDiffuse(0.75)
    prop.SetSpecular(0.1)
    prop.SetInterpolationToPhong()
    plotter.add_actor(actor, name="wire", reset_camera=False)
    if show_scalar_bar:
        plotter.add_scalar_bar(mapper=mapper, **sb)
    actor.SetVisibility(len(pts) >= 2)
    return WireHandles(polyline=line, tube=tube, actor=actor)


def update_wire(handles: WireHandles, points_lps_mm, uncertainty_mm) -> None:
    """Replace the wire's points and uncertainty in place (same actor, same tube filter)."""
    pts, unc = _dedupe_polyline(points_lps_mm, uncertainty_mm)
    if unc is None or len(unc) != len(pts):
        unc = np.zeros(len(pts))
    _set_polyline(handles.polyline, pts, {"uncertainty_mm": unc})
    handles.actor.SetVisibility(len(pts) >= 2)


def _carm_geometry(carm: CArm, pose: Pose):
    src = carm.source_lps_mm(pose)
    corners = carm.detector_corners_lps_mm(pose)
    return src, corners


def _frustum_points(src, corners) -> np.ndarray:
    return np.vstack([src[None, :], corners])


_FRUSTUM_LINES = np.array([[0, 1], [0, 2], [0, 3], [0, 4], [1, 2], [2, 3], [3, 4], [4, 1]])


def make_image_texture(image_u8):
    """A ``vtkImageData`` (dims ``cols x rows``) whose point ``(i, j)`` is pixel ``(u=i, v=j)``, and its texture.

    Texture coordinate ``(s, t) = ((u + 0.5) / cols, (v + 0.5) / rows)`` is the centre of pixel ``(u, v)``:
    ``t`` grows with the row index ``v`` (no vertical flip).
    """
    import vtk

    img = np.asarray(image_u8)
    rows, cols = img.shape
    data = vtk.vtkImageData()
    data.SetDimensions(cols, rows, 1)
    set_texture_image(data, img)
    tex = vtk.vtkTexture()
    tex.SetInputData(data)
    tex.InterpolateOn()
    tex.SetColorModeToDirectScalars()
    return data, tex


def set_texture_image(image_data, image_u8) -> None:
    """Replace the pixels of a texture's ``vtkImageData`` in place (``(rows, cols)`` uint8)."""
    from vtk.util.numpy_support import numpy_to_vtk

    img = np.asarray(image_u8, dtype=np.uint8)
    rgb = np.ascontiguousarray(np.repeat(img.reshape(-1, 1), 3, axis=1))
    arr = numpy_to_vtk(rgb, deep=True)
    arr.SetName("frame")
    image_data.GetPointData().SetScalars(arr)
    image_data.Modified()


def _quad(corners, *, tcoords=((0, 0), (1, 0), (1, 1), (0, 1))):
    import pyvista as pv

    q = pv.PolyData(np.asarray(corners, float), faces=np.array([4, 0, 1, 2, 3]))
    q.active_texture_coordinates = np.asarray(tcoords, dtype=float)
    return q


def add_carm(plotter, carm: CArm, pose: Pose, image_u8, *, texture=None, source_radius_mm: float = 8.0,
             name_suffix: str = "", source_color=(1.0, 0.9, 0.3), frustum_color=FRUSTUM_COLOR) -> CArmHandles:
    """Source point, frustum lines and the detector plane textured with ``image_u8`` in the C-arm pose.

    The detector quad's corners are ``carm.detector_corners_lps_mm(pose)`` (pixel edges
    ``(0,0), (W,0), (W,H), (0,H)``) with texture coordinates ``(0,0), (1,0), (1,1), (0,1)``, so the
    pixel ``(u, v)`` lands where the ray from the source to it meets the detector.
    ``name_suffix`` keeps a second C-arm's actors (plane B: ``"_b"``) apart from the first's.

    Parameters
    ----------
    image_u8 : (rows, cols) ndarray of uint8
        The frame shown on the detector; ignored when ``texture=(image_data, vtkTexture)`` is given.
    """
    import vtk

    src, corners = _carm_geometry(carm, pose)
    sphere = vtk.vtkSphereSource()
    sphere.SetCenter(*src)
    sphere.SetRadius(source_radius_mm)
    sphere.SetThetaResolution(16)
    sphere.SetPhiResolution(12)
    source_actor = plotter.add_mesh(sphere, color=source_color, name=f"xray_source{name_suffix}", reset_camera=False)

    import pyvista as pv

    fr = pv.PolyData(_frustum_points(src, corners), lines=np.column_stack([np.full(8, 2), _FRUSTUM_LINES]).ravel())
    frustum_actor = plotter.add_mesh(fr, color=frustum_color, line_width=1.5, name=f"frustum{name_suffix}", reset_camera=False,
                                     lighting=False, opacity=0.8)
    if texture is None:
        if image_u8 is None:
            image_u8 = np.full(carm.shape, 96, np.uint8)
        data, tex = make_image_texture(image_u8)
    else:
        data, tex = texture
    det = _quad(corners)
    det_actor = plotter.add_mesh(det, texture=tex, name=f"detector{name_suffix}", reset_camera=False, lighting=False,
                                 show_scalar_bar=False)
    det_actor.GetProperty().SetColor(1.0, 1.0, 1.0)
    det_actor.GetProperty().BackfaceCullingOff()
    return CArmHandles(sphere, source_actor, fr, frustum_actor, det, det_actor, data)


def update_carm(handles: CArmHandles, carm: CArm, pose: Pose) -> None:
    """Move the drawn C-arm to ``pose`` in place."""
    src, corners = _carm_geometry(carm, pose)
    handles.source.SetCenter(*src)
    handles.source.Modified()
    handles.frustum.points = _frustum_points(src, corners)
    handles.frustum.Modified()
    handles.detector.points = np.asarray(corners, float)
    handles.detector.Modified()


def volume_image_data(volume):
    """A ``pyvista.ImageData`` of a ``guidewire3d.io.Volume`` in LPS mm (point data ``HU``)."""
    import pyvista as pv

    nz, ny, nx = volume.shape_zyx
    img = pv.ImageData(dimensions=(nx, ny, nz), spacing=volume.spacing_mm, origin=volume.origin_lps_mm)
    img.direction_matrix = np.asarray(volume.direction, float)
    img.point_data["HU"] = np.asarray(volume.array_zyx, dtype=np.float32).ravel(order="C")
    return img


def add_cta_slices(plotter, volume, centre_lps_mm, *, window_hu=(-150.0, 650.0), opacity: float = 1.0):
    """Three orthogonal CTA slices (LPS axes) through ``centre_lps_mm``, grey window ``window_hu``.

    Returns ``(slices, actor)``: the sliced ``pyvista.MultiBlock`` merged to one PolyData, and its actor.
    """
    img = volume_image_data(volume)
    c = np.asarray(centre_lps_mm, float)
    import pyvista as pv
    import vtk

    append = vtk.vtkAppendPolyData()
    for s in img.slice_orthogonal(x=float(c[0]), y=float(c[1]), z=float(c[2])):
        append.AddInputData(s)
    append.Update()
    slices = pv.wrap(append.GetOutput())
    actor = plotter.add_mesh(slices, scalars="HU", cmap="gray", clim=list(window_hu), opacity=opacity,
                             show_scalar_bar=False, lighting=False, name="cta_slices", reset_camera=False)
    return slices, actor


# --------------------------------------------------------------------------------------
# 2D content
# --------------------------------------------------------------------------------------
def add_overlay_2d(plotter, shape, *, texture, centerline_edges=None, roadmap_centerline_uv_px=None,
                   line_width: float = 2.0) -> Overlay2DHandles:
    """The 2D view in the current subplot: the frame (shared texture) and empty overlays.

    Parameters
    ----------
    shape : (rows, cols)
    texture : (vtkImageData, vtkTexture)
        From ``make_image_texture`` (shared with the detector plane so one update changes both).
    centerline_edges : (E, 2) int array, optional
        Point-index pairs of the projected centerline (the tree's edges).
    roadmap_centerline_uv_px : (M, 2) array, optional
        The 2D roadmap centerline (what the registration matched), drawn as points, hidden at first.
    """
    import pyvista as pv

    rows, cols = (int(s) for s in shape)
    corners_uv = np.array([[-0.5, -0.5], [cols - 0.5, -0.5], [cols - 0.5, rows - 0.5], [-0.5, rows - 0.5]])
    img = _quad(_uv_to_plane(corners_uv, Z_IMAGE_2D))
    img_actor = plotter.add_mesh(img, texture=texture[1], name="frame2d", lighting=False, reset_camera=False,
                                 show_scalar_bar=False)
    img_actor.GetProperty().SetColor(1.0, 1.0, 1.0)

    cl = pv.PolyData()
    edges = np.zeros((0, 2), np.int64) if centerline_edges is None else np.asarray(centerline_edges, np.int64)
    n_pts = int(edges.max()) + 1 if len(edges) else 0
    cl.SetPoints(_vtk_points(np.zeros((n_pts, 3))))
    cl.SetLines(_cells(np.arange(0, 2 * len(edges) + 1, 2), edges.ravel()))
    cl_actor = plotter.add_mesh(cl, color=CENTERLINE_2D_COLOR, line_width=line_width, name="centerline2d",
                                lighting=False, reset_camera=False, opacity=0.85)
    w2 = pv.PolyData()
    _set_polyline(w2, np.zeros((0, 3)))
    w2_actor = plotter.add_mesh(w2, color=WIRE_2D_COLOR, line_width=line_width, name="wire2d", lighting=False,
                                reset_camera=False)
    wp = pv.PolyData()
    _set_polyline(wp, np.zeros((0, 3)))
    wp_actor = plotter.add_mesh(wp, color=WIRE_PROJ_COLOR, line_width=line_width, name="wire_proj",
                                lighting=False, reset_camera=False)
    rc = pv.PolyData(_uv_to_plane(np.zeros((0, 2)) if roadmap_centerline_uv_px is None else roadmap_centerline_uv_px,
                                  Z_OVERLAY_2D[0] - 0.25))
    rc_actor = plotter.add_mesh(rc, color=ROADMAP_CENTERLINE_COLOR, point_size=2.0, style="points",
                                name="roadmap_centerline", lighting=False, reset_camera=False)
    rc_actor.SetVisibility(False)
    return Overlay2DHandles(img, img_actor, cl, cl_actor, w2, w2_actor, wp, wp_actor, (rows, cols), rc, rc_actor)


def update_overlay(handles: Overlay2DHandles, *, centerline_uv_px=None, wire_uv_px=None, wire_proj_uv_px=None) -> None:
    """Move the 2D overlays in place. Any argument left ``None`` is unchanged.

    ``centerline_uv_px`` must have one row per point of the centerline edges given at creation.
    Non-finite pixels (behind the source) are dropped from the wire polylines.
    """
    if centerline_uv_px is not None:
        uv = np.nan_to_num(np.asarray(centerline_uv_px, float).reshape(-1, 2), nan=-1e4)
        handles.centerline.SetPoints(_vtk_points(_uv_to_plane(uv, Z_OVERLAY_2D[0])))
        handles.centerline.Modified()
    for uv, poly, z in ((wire_uv_px, handles.wire2d, Z_OVERLAY_2D[1]), (wire_proj_uv_px, handles.wire_proj, Z_OVERLAY_2D[2])):
        if uv is None:
            continue
        uv = np.asarray(uv, float).reshape(-1, 2)
        uv = uv[np.isfinite(uv).all(axis=1)]
        _set_polyline(poly, _uv_to_plane(uv, z))


def set_frame_image(handles: SceneHandles, image_u8) -> None:
    """Show a new frame on the detector plane and in the 2D view (one shared texture, in place)."""
    set_texture_image(handles.carm.texture_image, image_u8)


def add_text(renderer, text: str, *, top: bool, font_size: int = 13, color=(1.0, 1.0, 1.0), x: float = 0.01):
    """A left-aligned ``vtkTextActor`` anchored at the top-left or bottom-left of ``renderer``'s viewport."""
    import vtk

    a = vtk.vtkTextActor()
    a.SetInput(str(text))
    tp = a.GetTextProperty()
    tp.SetFontSize(int(font_size))
    tp.SetColor(*color)
    tp.SetJustificationToLeft()
    tp.SetFontFamilyToCourier()
    tp.SetBackgroundColor(0.0, 0.0, 0.0)
    tp.SetBackgroundOpacity(0.45)
    if top:
        tp.SetVerticalJustificationToTop()
    else:
        tp.SetVerticalJustificationToBottom()
    c = a.GetPositionCoordinate()
    c.SetCoordinateSystemToNormalizedViewport()
    c.SetValue(x, 0.985 if top else 0.012)
    renderer.AddActor2D(a)
    return a


def set_text(actor, text: str) -> None:
    if actor is not None:
        actor.SetInput(str(text))


# --------------------------------------------------------------------------------------
# cameras
# --------------------------------------------------------------------------------------
def beams_eye_camera(renderer, carm: CArm, pose: Pose) -> None:
    """Put ``renderer``'s camera at the X-ray source looking down the beam, with the detector's view angle.

    The view up is ``-e_v`` so image row 0 is at the top. Seen from the source, the image
    columns run right to left (the display convention is a mirror of a camera; see DESIGN.md).
    """
    Rinv = pose.R.T
    e_u, e_v, d = carm.axes
    src = carm.source_lps_mm(pose)
    cam = renderer.GetActiveCamera()
    cam.SetParallelProjection(False)
    cam.SetPosition(*src)
    cam.SetFocalPoint(*(src + carm.sid_mm * (Rinv @ d)))
    cam.SetViewUp(*(-(Rinv @ e_v)))
    cam.SetViewAngle(float(np.degrees(2.0 * np.arctan(carm.rows * carm.pixel_mm / 2.0 / carm.sid_mm))))
    cam.SetClippingRange(0.5 * carm.sod_mm, 1.05 * carm.sid_mm)
    mark_camera_set(renderer)


def overview_camera(renderer, carm: CArm, pose: Pose, focus_bounds, *, margin: float = 1.4) -> None:
    """Look at the vessels over the X-ray source's shoulder, the textured detector behind them.

    The view direction is the beam turned about 35 degrees toward the image columns and a little
    downward, patient head up (``-e_v``). ``focus_bounds`` ``(xmin, xmax, ymin, ymax, zmin, zmax)``
    (the vessels) fill about ``1 / margin`` of the view.
    """
    Rinv = pose.R.T
    e_u, e_v, d = (Rinv @ a for a in carm.axes)
    b = np.asarray(focus_bounds, float).reshape(3, 2)
    box = np.array([[x, y, z] for x in b[0] for y in b[1] for z in b[2]])
    aim = b.mean(axis=1)
    look = d + 0.27 * e_u - 0.17 * e_v
    look /= np.linalg.norm(look)
    cam = renderer.GetActiveCamera()
    cam.SetParallelProjection(False)
    cam.SetViewAngle(30.0)
    cam.SetFocalPoint(*aim)
    up = -e_v - np.dot(-e_v, look) * look
    cam.SetViewUp(*(up / np.linalg.norm(up)))
    half = np.radians(cam.GetViewAngle() / 2.0)
    tan_h = np.tan(half) * min(1.0, _aspect(renderer))
    dist = 0.0
    for pts, m in ((box, margin),):
        rel = pts - aim
        along = rel @ (-look)
        lateral = np.linalg.norm(rel - np.outer(along, -look), axis=1)
        dist = max(dist, float(np.max(along + m * lateral / tan_h)))
    cam.SetPosition(*(aim - look * dist))
    renderer.ResetCameraClippingRange()
    mark_camera_set(renderer)


def _aspect(renderer) -> float:
    w, h = renderer.GetSize()
    return float(w) / float(h) if h > 0 and w > 0 else 1.0


def fit_2d_camera(renderer, shape) -> None:
    """Parallel camera that fits the whole ``(rows, cols)`` image in ``renderer``, row 0 at the top."""
    rows, cols = shape
    cam = renderer.GetActiveCamera()
    cam.SetParallelProjection(True)
    cx, cy = (cols - 1) / 2.0, -(rows - 1) / 2.0
    cam.SetFocalPoint(cx, cy, 0.0)
    cam.SetPosition(cx, cy, 1000.0)
    cam.SetViewUp(0.0, 1.0, 0.0)
    aspect = _aspect(renderer)
    cam.SetParallelScale(max(rows / 2.0, cols / 2.0 / aspect) * 1.04)
    renderer.ResetCameraClippingRange()
    cam.SetClippingRange(900.0, 1100.0)
    mark_camera_set(renderer)


def mark_camera_set(renderer) -> None:
    """Tell pyvista the camera was placed on purpose (otherwise it resets it at the first render)."""
    if hasattr(renderer, "camera_set"):
        renderer.camera_set = True


def world_to_display_px(renderer, points) -> np.ndarray:
    """``(N, 3)`` world points -> ``(N, 2)`` window pixel ``(x, row)`` with row 0 at the top of the window."""
    import vtk

    pts = np.asarray(points, float).reshape(-1, 3)
    coord = vtk.vtkCoordinate()
    coord.SetCoordinateSystemToWorld()
    _, h = renderer.GetRenderWindow().GetSize()
    out = np.empty((len(pts), 2))
    for i, p in enumerate(pts):
        coord.SetValue(*p)
        x, y = coord.GetComputedDoubleDisplayValue(renderer)
        out[i] = (x - 0.5, h - y - 0.5)
    return out


# --------------------------------------------------------------------------------------
# the whole scene
# --------------------------------------------------------------------------------------
HELP = (
    "n/N frame +/-   space play   a roadmap\n"
    "g coarse/fine step\n"
    "j/l  i/k  d/D   move u / v / depth\n"
    "x/X y/Y z/Z     rotate about u / v / beam\n"
    "o refine  0 reset  Return apply\n"
    "c/h screenshot (x1/x2)  t/T wire(s)  V vessels\n"
    "7 beam's-eye  8 overview  9 CTA slices"
)


def build_scene(plotter, *, carm: CArm, pose: Pose, image_u8=None, vessels=None, tree=None,
                wire_points_lps_mm=None, wire_uncertainty_mm=None, roadmap_centerline_uv_px=None,
                show_help: bool = True) -> SceneHandles:
    """Add every actor of the viewer to ``plotter`` and return the handles.

    With a ``(1, 2)`` plotter (or a biplane one, ``new_plotter(biplane=True)``) the 3D view is
    subplot ``(0, 0)`` and the 2D view ``(0, 1)``; with a ``(1, 1)`` plotter only the 3D view is
    built (``overlay`` is None).

    Parameters
    ----------
    carm : CArm
        The live-frames view (detector drawn with it, 2D overlays projected with it).
    pose : Pose
        ``T_iso_from_lps``.
    image_u8 : (rows, cols) ndarray of uint8, optional
    vessels : pyvista-compatible surface, optional
    tree : VesselTree, optional
    wire_points_lps_mm, wire_uncertainty_mm : optional
        The first wire to show.
    """
    two = len(plotter.renderers) > 1
    for r in plotter.renderers:
        # plain alpha blending: order-independent transparency doubles the render time in software GL
        r.SetUseOIT(False)
    plotter.subplot(0, 0)
    r3 = renderer_at(plotter, 0, 0)
    r3.SetBackground(*BACKGROUND_3D)
    vessels_actor = add_vessels(plotter, vessels) if vessels is not None else None
    cl_actor = add_centerline(plotter, tree) if tree is not None else None
    wp = np.zeros((0, 3)) if wire_points_lps_mm is None else wire_points_lps_mm
    wu = np.zeros(len(np.asarray(wp).reshape(-1, 3))) if wire_uncertainty_mm is None else wire_uncertainty_mm
    wire = add_wire(plotter, wp, wu)
    if image_u8 is None:
        image_u8 = np.full(carm.shape, 96, np.uint8)
    texture = make_image_texture(image_u8)
    carm_h = add_carm(plotter, carm, pose, None, texture=texture)
    help_actor = None
    if show_help:
        help_actor = add_text(r3, HELP, top=True, font_size=11, color=(0.85, 0.85, 0.85))
    if vessels is not None:
        import pyvista as pv

        fb = pv.wrap(vessels).bounds
    elif tree is not None:
        lo, hi = tree.points_lps_mm.min(0), tree.points_lps_mm.max(0)
        fb = (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])
    else:
        c = pose.inverse().apply(np.zeros(3))  # the isocentre
        fb = (c[0] - 50, c[0] + 50, c[1] - 50, c[1] + 50, c[2] - 50, c[2] + 50)
    overview_camera(r3, carm, pose, fb)

    overlay = info = status = None
    r2 = None
    if two:
        plotter.subplot(0, 1)
        r2 = renderer_at(plotter, 0, 1)
        r2.SetBackground(*BACKGROUND_2D)
        edges = tree.edges if tree is not None else None
        overlay = add_overlay_2d(plotter, carm.shape, texture=texture, centerline_edges=edges,
                                 roadmap_centerline_uv_px=roadmap_centerline_uv_px)
        if tree is not None:
            update_overlay(overlay, centerline_uv_px=carm.project(tree.points_lps_mm, pose))
        info = add_text(r2, "", top=True, font_size=13)
        status = add_text(r2, "", top=False, font_size=11, color=(0.75, 0.9, 1.0))
        fit_2d_camera(r2, carm.shape)
        plotter.subplot(0, 0)
    return SceneHandles(plotter, r3, r2, vessels_actor, cl_actor, wire, carm_h, overlay, info, status, help_actor)
