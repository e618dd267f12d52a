"""MRML-only logic of the GuidewireReconstruction module (no Qt: runs under ``pip install slicer-core``).

It adapts MRML nodes to the numpy inputs of ``guidewire3d``, runs the pipeline, and turns the
results back into MRML nodes. It makes no GUI calls.

Coordinate frames
-----------------
``guidewire3d`` works in DICOM patient LPS (mm); Slicer's world frame is RAS (mm). The two differ by
``F = diag(-1, -1, 1)`` (a 180 degree rotation about the S axis). The conversion happens in this
module only, through the pair :func:`lps_to_ras` / :func:`ras_to_lps`:

* points and vectors ``(..., 3)``: ``x_ras = F x_lps``;
* rigid/affine 4x4 transforms between two LPS-like frames: ``T_ras = F4 T_lps F4`` with
  ``F4 = diag(-1, -1, 1, 1)``.

The registration transform node
-------------------------------
The registration estimates ``Pose`` ``T_iso_from_lps``: CTA LPS points -> C-arm room frame (axes
parallel to LPS, origin at the isocentre). The linear transform node stores it expressed in RAS::

    node.GetMatrixTransformFromParent() == lps_to_ras(pose.matrix) == F4 @ pose.matrix @ F4

i.e. "from parent" maps world (CTA) RAS to room RAS. Nodes drawn in room coordinates (the C-arm
source and detector, the roadmap centerline on the detector) are children of the transform, so
Slicer shows them where the registration puts the C-arm relative to the CTA. Moving the transform
with Slicer's interaction handles moves the C-arm; :meth:`GuidewireReconstructionCoreLogic.refine`
reads the matrix back (``pose = Pose.from_matrix(ras_to_lps(from_parent))``) and refines it.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import slicer
import vtk
from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy

from guidewire3d import io
from guidewire3d.app import export
from guidewire3d.app import igtl
from guidewire3d.app import vesselplan
from guidewire3d.cta import vesselmodel
from guidewire3d.errors import InputError, ReconstructionError, RegistrationError
from guidewire3d.geometry import CArm, Pose
from guidewire3d.methods import ReconMethod
from guidewire3d.reconstruction import Wire3D
from guidewire3d.vesseltree import access_record, check_access
from guidewire3d.xray.segmentation import SegMethod

__all__ = [
    "WireMethod",
    "Segmenter",
    "HeadlessScene",
    "lps_to_ras",
    "ras_to_lps",
    "create_headless_scene",
    "volume_from_node",
    "volume_to_node",
    "seeds_from_node",
    "access_from_node",
    "check_seeds_inside",
    "plan_summary",
    "xa_to_sequence_node",
    "xa_from_sequence_node",
    "polydata_lps_to_ras",
    "wire_tube_polydata",
    "pose_to_transform_node",
    "pose_from_transform_node",
    "detector_points_room_lps_mm",
    "OutputNodes",
    "VESSEL_PLAN_ROLES",
    "GuidewireReconstructionCoreLogic",
    "WIRE_RADIUS_MM",
    "CARM_ATTRIBUTE",
    "ROLE_ATTRIBUTE",
]

log = logging.getLogger(__name__)

#: Radius (mm) of the displayed guidewire tube: the package's one value.
WIRE_RADIUS_MM = export.WIRE_TUBE_RADIUS_MM
#: Node attribute holding the C-arm geometry (JSON of ``CArm.to_dict``) of an XA sequence node.
CARM_ATTRIBUTE = "GuidewireReconstruction.CArm"
#: Node attribute naming the role of each output node (``vessels``, ``wire``, ...).
ROLE_ATTRIBUTE = "GuidewireReconstruction.Role"
#: Roles of the nodes written by "Extract vessels" (:meth:`GuidewireReconstructionCoreLogic.plan_vessels`).
VESSEL_PLAN_ROLES = ("plan_vessels", "plan_centerline", "plan_branches")

_F = np.diag([-1.0, -1.0, 1.0])  # LPS <-> RAS; the only place this matrix is written
_F4 = np.eye(4)
_F4[:3, :3] = _F


# The choices are the library's own enums (the parameter node stores them by value).
WireMethod = ReconMethod  #: 3D reconstruction method, ``pipeline.run(method=...)``
Segmenter = SegMethod  #: 2D guidewire segmentation, ``pipeline.run(segmenter=...)``


# --------------------------------------------------------------------------------------
# LPS <-> RAS: the one pair of conversion helpers
# --------------------------------------------------------------------------------------
def _convert(a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.shape == (4, 4):
        return _F4 @ a @ _F4
    if a.ndim >= 1 and a.shape[-1] == 3:
        return a @ _F.T
    raise InputError(f"LPS/RAS conversion needs points (..., 3) or a 4x4 transform, got shape {a.shape}")


def lps_to_ras(a) -> np.ndarray:
    """LPS -> RAS for points/vectors ``(..., 3)`` (``F x``) or a 4x4 transform (``F4 T F4``).

    Returns a new array; the input is not modified.
    """
    return _convert(a)


def ras_to_lps(a) -> np.ndarray:
    """RAS -> LPS, the inverse of :func:`lps_to_ras` (the same matrix: ``F`` is its own inverse)."""
    return _convert(a)


# --------------------------------------------------------------------------------------
# Scene set-up without the Slicer application
# --------------------------------------------------------------------------------------
@dataclass
class HeadlessScene:
    """A ``vtkMRMLScene`` with the application logic and the module logics the module uses."""

    scene: object
    app_logic: object
    logics: dict


def create_headless_scene(*, home_directory=None) -> HeadlessScene:
    """Create a scene usable without Slicer's Qt application and make it ``slicer.mrmlScene``.

    Used by the tests and by scripts run with ``pip install slicer-core``; inside Slicer the
    application already provides ``slicer.mrmlScene`` with these logics. ``home_directory``
    (optional) receives an empty ``ColorFiles`` folder, which silences the color logic's search.

    The application logic and the Colors, Volumes, Models, Markups and Sequences module logics are
    set on it, so that ``AddDefaultStorageNode`` and archetype volume loading work.
    """
    import tempfile

    scene = slicer.vtkMRMLScene()
    app = slicer.vtkSlicerApplicationLogic()
    home = Path(home_directory or tempfile.gettempdir())
    if home_directory is not None:
        (home / "ColorFiles").mkdir(parents=True, exist_ok=True)  # the color logic scans it (empty is fine)
    app.SetHomeDirectory(str(home))
    app.SetShareDirectory(".")
    app.SetMRMLScene(scene)
    logics = {}
    for name, cls in (
        ("Colors", slicer.vtkSlicerColorLogic),
        ("Volumes", slicer.vtkSlicerVolumesLogic),
        ("Models", slicer.vtkSlicerModelsLogic),
        ("Markups", slicer.vtkSlicerMarkupsLogic),
        ("Sequences", slicer.vtkSlicerSequencesLogic),
        ("Transforms", slicer.vtkSlicerTransformLogic),
        ("Tables", slicer.vtkSlicerTablesLogic),
    ):
        logic = cls()
        logic.SetMRMLApplicationLogic(app)
        logic.SetMRMLScene(scene)
        app.SetModuleLogic(name, logic)
        logics[name] = logic
    slicer.mrmlScene = scene
    return HeadlessScene(scene, app, logics)


# --------------------------------------------------------------------------------------
# Inputs: MRML -> numpy
# --------------------------------------------------------------------------------------
def _matrix(vtk_matrix) -> np.ndarray:
    return np.array([[vtk_matrix.GetElement(i, j) for j in range(4)] for i in range(4)])


def _vtk_matrix(a) -> vtk.vtkMatrix4x4:
    m = vtk.vtkMatrix4x4()
    for i in range(4):
        for j in range(4):
            m.SetElement(i, j, float(a[i, j]))
    return m


def _world_matrix(node) -> np.ndarray:
    """4x4 linear map from the node's local RAS to world RAS (identity when untransformed)."""
    parent = node.GetParentTransformNode()
    if parent is None:
        return np.eye(4)
    if not parent.IsTransformToWorldLinear():
        raise InputError(f"{node.GetName()}: is under a non-linear transform; harden or remove it first")
    m = vtk.vtkMatrix4x4()
    parent.GetMatrixTransformToWorld(m)
    return _matrix(m)


def volume_from_node(volume_node) -> io.Volume:
    """A ``guidewire3d.io.Volume`` (HU, LPS placement) from a scalar volume node (parent transform applied)."""
    if volume_node is None or not volume_node.IsA("vtkMRMLScalarVolumeNode"):
        raise InputError("CTA volume: select a scalar volume node")
    if volume_node.GetImageData() is None:
        raise InputError(f"{volume_node.GetName()}: volume node has no image data")
    if volume_node.GetImageData().GetNumberOfScalarComponents() != 1:
        raise InputError(f"{volume_node.GetName()}: expected a scalar volume (1 component)")
    arr = np.array(slicer.util.arrayFromVolume(volume_node), dtype=np.float32, copy=True)  # (k, j, i)
    m = vtk.vtkMatrix4x4()
    volume_node.GetIJKToRASMatrix(m)
    ijk_to_ras = _world_matrix(volume_node) @ _matrix(m)
    axes_lps = ras_to_lps(ijk_to_ras[:3, :3].T).T  # columns: i, j, k steps in LPS
    spacing = np.linalg.norm(axes_lps, axis=0)
    if np.any(spacing <= 0):
        raise InputError(f"{volume_node.GetName()}: degenerate IJK to RAS matrix")
    direction = axes_lps / spacing
    origin = ras_to_lps(ijk_to_ras[:3, 3])
    return io.Volume(arr, tuple(spacing), tuple(origin), direction, source=volume_node.GetName())


def volume_to_node(vol: io.Volume, *, name: str = "CTA", scene=None):
    """A new scalar volume node holding ``vol`` with the IJK -> RAS matrix of its LPS placement."""
    scene = scene or slicer.mrmlScene
    node = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", name)
    a = vol.affine_lps
    ijk_to_ras = np.eye(4)
    ijk_to_ras[:3, :3] = lps_to_ras(a[:3, :3].T).T
    ijk_to_ras[:3, 3] = lps_to_ras(a[:3, 3])
    node.SetIJKToRASMatrix(_vtk_matrix(ijk_to_ras))
    slicer.util.updateVolumeFromArray(node, np.ascontiguousarray(vol.array_zyx))
    node.CreateDefaultDisplayNodes()
    return node


def seeds_from_node(markups_node) -> np.ndarray | None:
    """``(N, 3)`` LPS seed points (world coordinates) of a markups node; ``None`` when empty/absent."""
    if markups_node is None:
        return None
    n = markups_node.GetNumberOfControlPoints()
    if n == 0:
        return None
    ras = np.array([markups_node.GetNthControlPointPositionWorld(i) for i in range(n)], dtype=float)
    return ras_to_lps(ras)


def access_from_node(markups_node) -> np.ndarray | None:
    """``(3,)`` LPS access point (world coordinates) of a markups node: where the wire enters the
    vessels (``guidewire3d.vesseltree.rooted_at_access``); ``None`` when empty/absent.

    Raises
    ------
    InputError
        The node holds more than one point (which one is the access would be a guess).
    """
    pts = seeds_from_node(markups_node)
    if pts is None:
        return None
    if len(pts) != 1:
        raise InputError(f"access point: {markups_node.GetName()} holds {len(pts)} points; place one, where the wire "
                         "enters the vessels (the sheath tip or the puncture)")
    return pts[0]


def check_seeds_inside(vol: io.Volume, seeds_lps_mm, *, what: str = "seed points") -> None:
    """InputError naming the first seed (1-based, in RAS as Slicer shows it) that lies outside ``vol``.

    A cheap check made before the vessel stage; whether a seed lies in a bright lumen is the vessel
    stage's own check (its intensity model, as for ``guidewire3d vessels``).

    Parameters
    ----------
    vol : io.Volume
        The CTA (its voxel grid in LPS).
    seeds_lps_mm : (K, 3) array_like of float or None
        The seed points (LPS mm); ``None``: nothing to check.
    """
    if seeds_lps_mm is None:
        return
    seeds = np.asarray(seeds_lps_mm, dtype=float).reshape(-1, 3)
    shape = np.array(vol.shape_zyx)
    for k, s in enumerate(seeds):
        ras = ", ".join(f"{v:.1f}" for v in lps_to_ras(s))
        if not np.all(np.isfinite(s)):
            raise InputError(f"{what}: point {k + 1} is not a finite point")
        idx = vol.lps_to_index_zyx(s[None])[0]
        if np.any(idx < -0.5) or np.any(idx > shape - 0.5):
            raise InputError(f"{what}: point {k + 1} (RAS {ras} mm) lies outside the volume {vol.source}; "
                             "place the seeds inside its vessels")


def plan_summary(plan, *, access_lps_mm=None) -> str:
    """What "Extract vessels" found, one line per tree: branches, centerline length, radii, vessel
    volume, the lumen and background levels and their units, and the notes of the vessel stage
    (strict pass, pruned branches, bias field, how the seeds made the tree).

    ``plan`` is a ``guidewire3d.app.vesselplan.VesselPlan``; ``access_lps_mm`` (LPS mm, optional) adds
    how far the first tree's root lies from the access point.
    """
    trees = plan.trees
    total_cm = sum(float(a.vessels.tree.total_length_mm) for a in trees) / 10.0
    n_br = sum(len(a.vessels.tree.branches) for a in trees)
    if len(trees) == 1:
        head = f"1 vessel tree: {_count(n_br, 'branch')}, {total_cm:.1f} cm of centerline."
    else:
        head = (f"{len(trees)} separate vessel trees (one per structure the seeds lie in): {_count(n_br, 'branch')}, "
                f"{total_cm:.1f} cm of centerline.")
    lines = [head]
    for k, (a, group) in enumerate(zip(trees, plan.seed_groups)):
        seeds = f"seeds {', '.join(str(i + 1) for i in group)}" if group else "automatic"
        line = f"Tree {k + 1} ({seeds}): {vesselplan.tree_summary(a)}."
        notes = vesselplan.tree_notes(a)
        if k == 0 and access_lps_mm is not None:
            rec = access_record(a.vessels.tree, access_lps_mm)
            notes.append(f"rooted at its point nearest the access point, {rec['distance_mm']:.1f} mm from it")
        if notes:
            line += " Note: " + "; ".join(notes) + "."
        lines.append(line)
    return "\n".join(lines)


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" if n == 1 else f"{n} {noun}es" if noun.endswith("ch") else f"{n} {noun}s"


# --------------------------------------------------------------------------------------
# XA runs <-> sequence nodes
# --------------------------------------------------------------------------------------
def xa_to_sequence_node(run: io.XARun, *, name: str = "XA", scene=None):
    """A sequence node with one 2D scalar volume per frame and the C-arm geometry as an attribute.

    Each frame is shown as a 2D image (column ``u`` -> screen right, row ``v`` -> screen down in
    the axial view) with the detector pixel spacing. A sequence browser is added so the frames can
    be played in Slicer.
    """
    scene = scene or slicer.mrmlScene
    seq = scene.AddNewNodeByClass("vtkMRMLSequenceNode", name)
    seq.SetIndexName("frame")
    seq.SetIndexUnit("")
    seq.SetIndexType(seq.NumericIndex)
    ps = run.carm.pixel_mm
    ijk_to_ras = np.eye(4)
    ijk_to_ras[:3, :3] = lps_to_ras(np.diag([ps, ps, 1.0]))  # index axes along L, P: upright image
    for t, frame in enumerate(run.frames):
        img = slicer.vtkMRMLScalarVolumeNode()
        img.SetName(f"{name} frame {t}")
        img.SetIJKToRASMatrix(_vtk_matrix(ijk_to_ras))
        image = vtk.vtkImageData()
        image.SetDimensions(run.carm.cols, run.carm.rows, 1)
        image.GetPointData().SetScalars(numpy_to_vtk(np.ascontiguousarray(frame, dtype=np.float32).ravel(), deep=True))
        img.SetAndObserveImageData(image)
        seq.SetDataNodeAtValue(img, str(t))
    seq.SetAttribute(CARM_ATTRIBUTE, json.dumps(run.carm.to_dict()))
    if run.frame_time_ms is not None:
        seq.SetAttribute("GuidewireReconstruction.FrameTimeMs", repr(float(run.frame_time_ms)))
    seq.SetAttribute("GuidewireReconstruction.Source", str(run.source))
    browser = scene.AddNewNodeByClass("vtkMRMLSequenceBrowserNode", f"{name} browser")
    browser.SetAndObserveMasterSequenceNodeID(seq.GetID())
    return seq


def xa_from_sequence_node(seq_node) -> io.XARun:
    """The ``io.XARun`` stored by :func:`xa_to_sequence_node` (frames and C-arm geometry)."""
    if seq_node is None or not seq_node.IsA("vtkMRMLSequenceNode"):
        raise InputError("XA input: select a sequence node created from an XA file")
    name = seq_node.GetName()
    text = seq_node.GetAttribute(CARM_ATTRIBUTE)
    if not text:
        raise InputError(f"{name}: sequence node has no C-arm geometry (attribute {CARM_ATTRIBUTE})")
    carm = CArm.from_dict(json.loads(text))
    n = seq_node.GetNumberOfDataNodes()
    if n == 0:
        raise InputError(f"{name}: sequence node has no frames")
    frames = []
    for t in range(n):
        node = seq_node.GetNthDataNode(t)
        image = node.GetImageData() if node is not None and node.IsA("vtkMRMLScalarVolumeNode") else None
        if image is None:
            raise InputError(f"{name}: frame {t} is not a scalar volume with image data")
        dims = image.GetDimensions()
        if (dims[1], dims[0]) != tuple(carm.shape) or dims[2] != 1:
            raise InputError(f"{name}: frame {t} is {dims[0]}x{dims[1]}x{dims[2]}, expected {carm.cols}x{carm.rows}x1")
        frames.append(vtk_to_numpy(image.GetPointData().GetScalars()).reshape(carm.rows, carm.cols))
    ft = seq_node.GetAttribute("GuidewireReconstruction.FrameTimeMs")
    return io.XARun(np.stack(frames).astype(np.float32), carm, source=seq_node.GetAttribute("GuidewireReconstruction.Source") or name,
                    frame_time_ms=float(ft) if ft else None)


# --------------------------------------------------------------------------------------
# Outputs: numpy -> MRML
# --------------------------------------------------------------------------------------
def _f_transform() -> vtk.vtkTransform:
    t = vtk.vtkTransform()
    t.SetMatrix(_vtk_matrix(_embed3(lps_to_ras(np.eye(3)))))  # rows of I moved as points: F itself
    return t


def _embed3(m3) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = m3
    return m


def polydata_lps_to_ras(poly_lps) -> vtk.vtkPolyData:
    """A new polydata with points (and normals) moved from LPS to RAS. The input is not modified."""
    f = vtk.vtkTransformPolyDataFilter()
    f.SetInputData(poly_lps)
    f.SetTransform(_f_transform())
    f.Update()
    out = vtk.vtkPolyData()
    out.DeepCopy(f.GetOutput())
    return out


def wire_tube_polydata(points_ras_mm, uncertainty_mm=None, *, radius_mm: float = WIRE_RADIUS_MM,
                       sides: int = 12) -> vtk.vtkPolyData:
    """A closed tube of ``radius_mm`` around the wire polyline ``(N, 3)`` (RAS mm).

    Point data ``uncertainty_mm`` (per wire point, interpolated along the tube) colours the tube.
    """
    p = np.asarray(points_ras_mm, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2:
        raise ReconstructionError(f"wire tube needs (N>=2, 3) points, got {p.shape}")
    keep = np.r_[True, np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-6]  # tube filter needs distinct points
    arrays = {}
    if uncertainty_mm is not None:
        arrays["uncertainty_mm"] = np.asarray(uncertainty_mm, dtype=float)[keep]
    out = export.tube_polydata(export.polyline_polydata(p[keep], arrays), radius_mm, sides=int(sides))
    if uncertainty_mm is not None:
        out.GetPointData().SetActiveScalars("uncertainty_mm")
    return out


def pose_to_transform_node(pose: Pose, node) -> None:
    """Store ``pose`` (``T_iso_from_lps``) in a linear transform node: from-parent = ``lps_to_ras(pose.matrix)``."""
    node.SetMatrixTransformFromParent(_vtk_matrix(lps_to_ras(pose.matrix)))


def pose_from_transform_node(node) -> Pose:
    """The ``Pose`` held by a registration transform node (inverse of :func:`pose_to_transform_node`).

    Only the node's own matrix is read; a parent transform above it is an error.
    """
    if node is None or not node.IsA("vtkMRMLLinearTransformNode"):
        raise RegistrationError("registration transform: select a linear transform node")
    if node.GetParentTransformNode() is not None:
        raise RegistrationError(f"{node.GetName()}: registration transform must not have a parent transform")
    m = vtk.vtkMatrix4x4()
    node.GetMatrixTransformFromParent(m)
    T = ras_to_lps(_matrix(m))
    # re-orthonormalise the rotation (interaction and float32 storage leave ~1e-7 drift)
    u, _, vt = np.linalg.svd(T[:3, :3])
    R = u @ vt
    if np.linalg.det(R) < 0:
        raise RegistrationError(f"{node.GetName()}: transform is a reflection, not a rigid registration")
    if np.abs(T[:3, :3] - R).max() > 1e-3:
        raise RegistrationError(f"{node.GetName()}: transform has scaling or shear; only rotation and translation are allowed")
    return Pose(R, T[:3, 3])


def detector_points_room_lps_mm(uv_px, carm: CArm) -> np.ndarray:
    """Pixels ``(N, 2)`` ``(u, v)`` -> their points on the detector, in the room frame (LPS axes, mm)."""
    uv = np.atleast_2d(np.asarray(uv_px, dtype=float))
    e_u, e_v, _ = carm.axes
    c = carm.principal_point_px
    return (carm.detector_centre_room_mm + (uv[:, :1] - c[0]) * carm.pixel_mm * e_u
            + (uv[:, 1:2] - c[1]) * carm.pixel_mm * e_v)


def _carm_polydata_room_ras(carm: CArm) -> vtk.vtkPolyData:
    """The C-arm in the room frame (RAS): the detector outline and the four rays from the source."""
    src = lps_to_ras(carm.source_room_mm)
    corners = lps_to_ras(carm.detector_corners_lps_mm(Pose.identity()))  # identity pose: room frame
    pts = np.vstack([src[None], corners])
    points = vtk.vtkPoints()
    points.SetData(numpy_to_vtk(np.ascontiguousarray(pts), deep=True))
    lines = vtk.vtkCellArray()
    for a, b in ((1, 2), (2, 3), (3, 4), (4, 1), (0, 1), (0, 2), (0, 3), (0, 4)):
        lines.InsertNextCell(2)
        lines.InsertCellPoint(a)
        lines.InsertCellPoint(b)
    poly = vtk.vtkPolyData()
    poly.SetPoints(points)
    poly.SetLines(lines)
    return poly


def _points_polydata(points_ras_mm) -> vtk.vtkPolyData:
    p = np.ascontiguousarray(points_ras_mm, dtype=float).reshape(-1, 3)
    pts = vtk.vtkPoints()
    pts.SetData(numpy_to_vtk(p, deep=True))
    verts = vtk.vtkCellArray()
    for i in range(len(p)):
        verts.InsertNextCell(1)
        verts.InsertCellPoint(i)
    poly = vtk.vtkPolyData()
    poly.SetPoints(pts)
    poly.SetVerts(verts)
    return poly


def _set_curve_points(curve, points_ras_mm) -> None:
    p = np.asarray(points_ras_mm, dtype=float).reshape(-1, 3)
    pts = vtk.vtkPoints()
    pts.SetData(numpy_to_vtk(np.ascontiguousarray(p), deep=True))
    curve.SetControlPointPositionsWorld(pts)


def _with_tree_array(poly) -> vtk.vtkPolyData:
    """``poly`` with the point array ``tree`` (all 0) added when it has none (a plan of one tree); in place."""
    if poly.GetPointData().GetArray("tree") is None:
        arr = numpy_to_vtk(np.zeros(poly.GetNumberOfPoints(), dtype=np.int32), deep=True)
        arr.SetName("tree")
        poly.GetPointData().AddArray(arr)
    return poly


def _fill_table(table_node, columns: list[tuple[str, str, list]]) -> None:
    table = vtk.vtkTable()
    for name, kind, values in columns:
        arr = {"int": vtk.vtkIntArray, "float": vtk.vtkDoubleArray, "str": vtk.vtkStringArray}[kind]()
        arr.SetName(name)
        for v in values:
            arr.InsertNextValue(v)
        table.AddColumn(arr)
    table_node.SetAndObserveTable(table)


# --------------------------------------------------------------------------------------
# The logic
# --------------------------------------------------------------------------------------
@dataclass
class OutputNodes:
    """The MRML nodes written by :class:`GuidewireReconstructionCoreLogic` (all coordinates RAS)."""

    transform: object = None  # vtkMRMLLinearTransformNode: registration (see module docstring)
    table: object = None  # vtkMRMLTableNode: per-frame metrics
    vessel_model: object = None  # vtkMRMLModelNode: CTA vessel surface
    centerline_curves: list = field(default_factory=list)  # vtkMRMLMarkupsCurveNode per tree branch
    carm_model: object = None  # vtkMRMLModelNode: source + detector, child of ``transform``
    roadmap_points_model: object = None  # vtkMRMLModelNode: 2D roadmap centerline on the detector, child of ``transform``
    wire_models: list = field(default_factory=list)  # vtkMRMLModelNode (tube) per live frame
    wire_curves: list = field(default_factory=list)  # vtkMRMLMarkupsCurveNode per live frame
    wire_sequence: object = None  # vtkMRMLSequenceNode: the tube per frame, synchronised with the frames' browser
    live_wire_model: object = None  # vtkMRMLModelNode: the newest wire of a connected live server (connect_live)
    motion_sequence: object = None  # vtkMRMLSequenceNode: each frame's tracked pose (track_motion), synchronised
    frame_indices: list = field(default_factory=list)  # index in the frames run of each wire node
    carm_b_model: object = None  # vtkMRMLModelNode: plane B's source + detector (biplane), child of ``transform``
    roadmap_b_points_model: object = None  # vtkMRMLModelNode: plane B's 2D roadmap centerline on its detector
    # "Extract vessels" (plan_vessels: the CTA alone, no X-ray)
    plan_vessel_model: object = None  # vtkMRMLModelNode: every tree's vessel surface (point array ``tree``)
    plan_centerline_model: object = None  # vtkMRMLModelNode: every tree's centerline (``tree``, ``branch``, ``radius_mm``)
    plan_table: object = None  # vtkMRMLTableNode: one row per branch of every tree
    plan_segmentation: object = None  # vtkMRMLSegmentationNode: every tree's vessel mask, a segment each

    def all_nodes(self) -> list:
        singles = [self.transform, self.table, self.vessel_model, self.carm_model, self.roadmap_points_model,
                   self.wire_sequence, self.live_wire_model, self.motion_sequence, self.carm_b_model,
                   self.roadmap_b_points_model, self.plan_vessel_model, self.plan_centerline_model, self.plan_table,
                   self.plan_segmentation]
        return [n for n in singles + self.centerline_curves + self.wire_models + self.wire_curves if n is not None]


class GuidewireReconstructionCoreLogic:
    """Runs ``guidewire3d`` on MRML inputs and writes MRML outputs (no Qt, no GUI calls).

    Parameters
    ----------
    scene : vtkMRMLScene, optional
        Defaults to ``slicer.mrmlScene``.
    app_logic : vtkSlicerApplicationLogic, optional
        Its Sequences module logic updates the wire sequence's proxy node when the frames are
        browsed (inside Slicer: ``slicer.app.applicationLogic()``).
    centerline_step_mm : float
        Control-point spacing of the centerline curves (the tree is resampled for display).
    """

    def __init__(self, scene=None, *, app_logic=None, centerline_step_mm: float = 2.0):
        self.scene = scene or slicer.mrmlScene
        self.app_logic = app_logic  # vtkSlicerApplicationLogic: gives the Sequences logic (proxy updates)
        self.frames_sequence = None  # the frames' sequence node of the last process(), if any
        if self.scene is None:
            raise InputError("no MRML scene: set slicer.mrmlScene or pass scene=")
        self.centerline_step_mm = float(centerline_step_mm)
        self.result = None  # pipeline.PipelineResult of the last process()
        self.method = WireMethod.VESSEL
        self.segmenter = Segmenter.UNET
        self.wires2d: list = []  # ordered 2D wire per live frame (orderedwire.OrderedWire)
        self.registration = None  # the registration currently shown (after refine: the refined one)
        self.wires3d: list = []
        self.frame_results: list = []  # live.FrameResult per live frame (verdict: ok / uncertain / failed)
        self.track_motion = False  # the frames' poses follow breathing (process(track_motion=True))
        self.biplane = None  # biplane.BiplaneResult of the last process() with plane B, else None
        self.pairs: list = []  # biplane.BiplaneFrame per pair (plane B's 2D wire, views, both projection errors)
        self.outputs = OutputNodes()
        self.live = None  # igtl.WireFollower of a connected `guidewire3d live` server (connect_live)
        self.live_status = ""
        self.plan = None  # vesselplan.VesselPlan of the last plan_vessels() ("Extract vessels")
        self.plan_summary = ""

    # --- live ---------------------------------------------------------------------------
    def connect_live(self, address: str = f"127.0.0.1:{igtl.DEFAULT_PORT}", *, wait_s: float = 10.0):
        """Follow a ``guidewire3d live`` server (``HOST:PORT``): :meth:`poll_live` then shows its newest
        wire as the model node ``GW live guidewire`` (RAS, uncertainty as point scalars). The widget
        polls on a timer; without one, call :meth:`poll_live` yourself.

        This reads the server through the package's own client (no OpenIGTLinkIF needed); with
        OpenIGTLinkIF installed, a connector node shows the same ``Guidewire`` POLYDATA directly.
        """
        self.disconnect_live()
        host, port = igtl.parse_host_port(address, option="live server")
        try:
            client = igtl.IGTLClient(host, port, keep=64, connect_timeout_s=wait_s)
        except ConnectionError as e:
            raise InputError(f"live server {address}: {e}") from None
        self.live = igtl.WireFollower(client)
        self.live_status = f"connected to {host}:{port}, waiting for a wire"
        return self.live

    def poll_live(self) -> bool:
        """Show what the live server sent since the last call; True when the wire changed."""
        if self.live is None:
            return False
        got = self.live.poll()
        s = self.live.status
        if s:
            self.live_status = (f"live frame {s.get('frame')}: {s.get('verdict')} {s.get('message', '')[:80]}"
                                f" ({s.get('dropped', 0)} dropped)")
        if got is None:
            return False
        o = self.outputs
        poly = (wire_tube_polydata(lps_to_ras(got.points_lps_mm), got.uncertainty_mm)
                if len(got.points_lps_mm) >= 2 else vtk.vtkPolyData())
        o.live_wire_model = self._model(o.live_wire_model, "GW live guidewire", "live_wire", poly, color=(1.0, 0.6, 0.1))
        dn = o.live_wire_model.GetDisplayNode()
        dn.SetActiveScalarName("uncertainty_mm")
        dn.SetScalarVisibility(True)
        o.live_wire_model.SetAttribute("GuidewireReconstruction.Frame", str(got.status.get("frame", "")))
        o.live_wire_model.SetAttribute("GuidewireReconstruction.Verdict", str(got.status.get("verdict", "")))
        return True

    def disconnect_live(self) -> None:
        if self.live is not None:
            self.live.client.close()
            self.live = None
            self.live_status = "disconnected"

    # --- inputs -------------------------------------------------------------------------
    def load_xa(self, path, *, name: str | None = None):
        """Read an XA DICOM file into a new sequence node (frames + C-arm geometry attribute)."""
        run = io.read_xa(path)
        return xa_to_sequence_node(run, name=name or Path(path).stem, scene=self.scene)

    @staticmethod
    def _xa(value, what: str) -> io.XARun:
        if value is None or (isinstance(value, (str, Path)) and not str(value)):
            raise InputError(f"{what}: give an XA DICOM file path or a sequence node")
        if isinstance(value, io.XARun):
            return value
        if isinstance(value, (str, Path)):
            return io.read_xa(value)
        return xa_from_sequence_node(value)

    # --- the whole chain -------------------------------------------------------------------
    def process(self, *, cta_volume_node, roadmap, frames=None, seeds_node=None, roadmap_frame: int | None = None,
                method: WireMethod | str = WireMethod.VESSEL, segmenter: Segmenter | str = Segmenter.UNET,
                force: bool = False, outputs: OutputNodes | None = None, pose: Pose | None = None,
                track_motion: bool = False, roadmap_b=None, frames_b=None, access_node=None) -> OutputNodes:
        """Run the pipeline and write (or update) the output nodes.

        With ``roadmap_b`` (plane B of a biplane C-arm) the biplane chain runs instead
        (``guidewire3d.app.biplane.run``: one pose from both roadmaps, each pair's wire from both
        planes) and plane B's C-arm and roadmap centerline get nodes of their own.

        Parameters
        ----------
        cta_volume_node : vtkMRMLScalarVolumeNode
            The CTA (HU). Its IJK -> RAS matrix (and a linear parent transform) place it.
        roadmap, frames : str | Path | vtkMRMLSequenceNode | io.XARun
            The contrast roadmap run and the live frames (``frames=None``: the roadmap run).
        seeds_node : vtkMRMLMarkupsFiducialNode, optional
            Seed points inside the vessels of interest.
        access_node : vtkMRMLMarkupsFiducialNode, optional
            One point where the wire enters the vessels (the sheath tip or the puncture): the vessel
            tree is rooted at its point nearest to it (``access_lps_mm`` of the pipeline), for
            transradial wires and any entry other than the groin. Empty or absent: the tree's own root (the
            lower end of its aorta, where a transfemoral wire enters; without an aorta, its widest end).
        roadmap_frame : int, optional
            Frame of the roadmap run to use (``None`` or negative: the most contrast-filled).
        outputs : OutputNodes, optional
            Existing output nodes to update; missing ones are created.
        pose : Pose, optional
            Start from this pose (refined only) instead of registering from the nominal one.
        track_motion : bool
            Follow breathing: each frame's pose is updated from its wire (``reconstruct
            --track-motion``); with a frames sequence the C-arm then follows the frame browser.
            With two planes each pair's pose is updated from both planes' wires
            (``motion.BiplaneMotionTracker``); both C-arms follow the frame browser.
        roadmap_b, frames_b : str | Path | vtkMRMLSequenceNode | io.XARun, optional
            Plane B's roadmap and live frames (``frames_b=None``: plane B's roadmap run). Each plane's
            geometry comes from its own positioner tags.
        """
        from guidewire3d.app import biplane, pipeline

        method = WireMethod(method)
        segmenter = Segmenter(segmenter)
        if roadmap_b is None and frames_b is not None:
            raise InputError("plane B: give its roadmap as well as its live frames")
        vol = volume_from_node(cta_volume_node)
        road = self._xa(roadmap, "roadmap")
        live = road if frames is None else self._xa(frames, "frames")
        live_node = roadmap if frames is None else frames
        seeds = seeds_from_node(seeds_node)
        access = access_from_node(access_node)
        if access is not None:  # before the heavy work
            access = check_access(access, bounds_lps_mm=vol.bounds_lps_mm, option="access point")
        if roadmap_frame is not None and roadmap_frame < 0:
            roadmap_frame = None
        is_seq = hasattr(live_node, "IsA") and live_node.IsA("vtkMRMLSequenceNode")
        if roadmap_b is not None:
            road_b = self._xa(roadmap_b, "plane B roadmap")
            live_b = road_b if frames_b is None else self._xa(frames_b, "plane B frames")
            biplane.check_inputs([road, road_b], [live, live_b], roadmap_frame=roadmap_frame)  # before the heavy work
            t0 = time.perf_counter()
            bres = biplane.run(vol, [road, road_b], [live, live_b], roadmap_frame=roadmap_frame, seeds_lps_mm=seeds,
                               method=method.value, segmenter=segmenter.value, force=force, progress=False,
                               access_lps_mm=access, track_motion=bool(track_motion), log=log.info)
            log.info("guidewire3d biplane: %.1f s", time.perf_counter() - t0)
            return self.show_result(bres.plane_a, method=method, segmenter=segmenter, outputs=outputs,
                                    frames_sequence=live_node if is_seq else None, track_motion=track_motion,
                                    biplane_result=bres)
        t0 = time.perf_counter()
        result = pipeline.run(vol, road, live, roadmap_frame=roadmap_frame, seeds_lps_mm=seeds, method=method.value,
                              segmenter=segmenter.value, force=force, progress=False, pose=pose, log=log.info,
                              track_motion=bool(track_motion), access_lps_mm=access)
        log.info("guidewire3d pipeline: %.1f s", time.perf_counter() - t0)
        return self.show_result(result, method=method, segmenter=segmenter, outputs=outputs,
                                frames_sequence=live_node if is_seq else None, track_motion=track_motion)

    def show_result(self, result, *, method: WireMethod | str = WireMethod.VESSEL,
                    segmenter: Segmenter | str = Segmenter.UNET, outputs: OutputNodes | None = None,
                    frames_sequence=None, track_motion: bool = False, biplane_result=None) -> OutputNodes:
        """Write (or update) the output nodes from a ``pipeline.PipelineResult`` and keep it for :meth:`refine`.

        ``frames_sequence`` (the live frames' sequence node) gets a synchronised wire sequence, and,
        when the frames were tracked (``track_motion``), a synchronised sequence of each frame's pose
        that the C-arm and the roadmap centerline follow. ``biplane_result`` (a
        ``biplane.BiplaneResult`` whose ``plane_a`` is ``result``) adds plane B's nodes and the
        per-plane columns of the metrics table.
        """
        self.biplane = biplane_result
        self.pairs = list(biplane_result.pairs) if biplane_result is not None else []
        self.result = result
        self.track_motion = bool(track_motion)
        self.method = WireMethod(method)
        self.segmenter = Segmenter(segmenter)
        self.frames_sequence = frames_sequence
        self.registration = result.registration
        self.wires2d = list(result.wires2d)
        self.wires3d = list(result.wires3d)
        self.frame_results = list(getattr(result, "frame_results", []) or [])
        if len(self.wires3d) != len(result.frames):  # the pipeline stopped before the frames
            self.wires3d = [Wire3D.failed("not reconstructed: the registration failed (adjust the transform, then "
                                          "Refine)")] * len(result.frames)
        if outputs is not None:
            self.outputs = outputs
        self._write_static_outputs()
        self._write_plane_b_outputs()
        self._write_registration_outputs()
        self._write_wire_outputs()
        return self.outputs

    def refine(self, *, transform_node=None, force: bool = False):
        """Refine the registration from the pose in the transform node, then update it and the wires.

        Reads the (possibly user-edited) transform node, converts it back to ``T_iso_from_lps``,
        runs ``registration.refine`` and, unless it failed (or with ``force``), stores the refined pose
        in the node and reconstructs every frame's wire again; a pose the overlay fits but the roadmap
        leaves uncertain (``Verdict.UNCERTAIN``) is adopted. Returns the ``RegistrationResult``.
        """
        from guidewire3d import registration

        if self.result is None:
            raise RegistrationError("refine: run Apply (process) first")
        node = transform_node or self.outputs.transform
        start = pose_from_transform_node(node)
        res = self.result
        cl = res.centerline2d
        kwargs = {}
        if getattr(cl, "radius_px", None) is not None:
            kwargs["centerline_radius_px"] = cl.radius_px
        if self.biplane is not None:  # one pose for both roadmaps: the joint problem, from this start
            from guidewire3d.app import biplane

            b = self.biplane
            reg = biplane.register_biplane(res.tree, [cl.points_uv_px, b.centerline2d_b.points_uv_px], [res.carm, b.carm_b],
                                           centerline_radius_px=(getattr(cl, "radius_px", None),
                                                                 getattr(b.centerline2d_b, "radius_px", None)),
                                           init_pose=start, global_search=False).result
        else:
            reg = registration.refine(res.tree, cl.points_uv_px, res.carm, start, **kwargs)
        log.info("refine: %s (%s), residual %.2f px", reg.verdict.value, reg.message, reg.mean_residual_px)
        if reg.verdict is registration.Verdict.FAILED and not force:
            return reg
        self.outputs.transform = node
        self.registration = reg
        self._write_registration_outputs(source="refined")
        self.update_wires()
        return reg

    def update_wires(self, *, method: WireMethod | str | None = None) -> list:
        """Reconstruct every live frame's wire again with the current registration and write the wire nodes.

        ``method`` (default: the one of the last :meth:`process`) selects the 3D reconstruction.
        The 2D wires of the last run are reused; when the run stopped before the frames (failed
        registration, no ``force``), they are extracted now, as the pipeline does. Returns the new
        ``Wire3D`` list.
        """
        from guidewire3d.live import session as live

        if self.result is None:
            raise ReconstructionError("update_wires: run Apply (process) first")
        if method is not None:
            self.method = WireMethod(method)
        res, reg = self.result, self.registration
        if self.biplane is not None:
            return self._update_biplane_wires()
        session = live.Session(res.tree, res.frames_carm, reg.pose, registration_covariance=reg.covariance_6x6,
                               method=self.method.value, segmenter=self.segmenter.value,
                               track_motion=self.track_motion)
        if len(self.wires2d) != len(res.frames):
            # the run stopped before the frames: segment and order them now, as the pipeline does
            self.frame_results = list(session.run(res.frames))
            self.wires2d = [fr.wire2d for fr in self.frame_results]
        else:
            self.frame_results = [session.process_wire(w2, image=frame, index=k)
                                  for k, (frame, w2) in enumerate(zip(res.frames, self.wires2d))]
        wires = [fr.wire3d for fr in self.frame_results]
        self.wires3d = wires
        self._write_wire_outputs()
        return wires

    def _update_biplane_wires(self) -> list:
        """Every pair again through ``biplane.BiplaneSession`` at the current registration (both planes'
        2D wires of the last run reused; segmented now when the run stopped before the frames)."""
        from guidewire3d.app import biplane

        res, reg, b = self.result, self.registration, self.biplane
        session = biplane.BiplaneSession(res.tree, (res.frames_carm, b.frames_carm_b), reg.pose,
                                         registration_covariance=reg.covariance_6x6, segmenter=self.segmenter.value,
                                         method=self.method.value, threads=1, track_motion=self.track_motion)
        ids = list(getattr(res, "frame_indices", None) or range(len(res.frames)))
        try:
            if len(self.pairs) == len(res.frames):
                pairs = [session.process_wires(w2, p.wire2d_b, images=(fa, fb), index=i, index_b=p.index_b)
                         for i, w2, p, fa, fb in zip(ids, self.wires2d, self.pairs, res.frames, b.frames_b)]
            else:  # the run stopped before the frames: pairs in order
                pairs = [session.process(fa, fb, index=i, index_b=k)
                         for k, (i, fa, fb) in enumerate(zip(ids, res.frames, b.frames_b))]
        finally:
            session.close()
        self.pairs = pairs
        self.frame_results = [p.result for p in pairs]
        self.wires2d = [fr.wire2d for fr in self.frame_results]
        self.wires3d = [fr.wire3d for fr in self.frame_results]
        self._write_wire_outputs()
        return self.wires3d

    # --- planning: the vessels of the CTA alone ------------------------------------------------
    def plan_vessels(self, *, cta_volume_node, seeds_node=None, access_node=None,
                     outputs: OutputNodes | None = None) -> OutputNodes:
        """"Extract vessels": the vessel trees of the CTA alone, for planning (``guidewire3d vessels``).

        Runs ``guidewire3d.app.vesselplan.plan_vessels`` and writes (or updates in place) four nodes:
        the vessel surface of every tree (``plan_vessel_model``), every tree's centerline
        (``plan_centerline_model``: polylines per branch with point arrays ``tree``, ``branch`` and
        ``radius_mm``), a table with one row per branch (``plan_table``) and the vessel mask as a
        segmentation on the CTA's grid, one segment per tree (``plan_segmentation``: to check or edit in the
        Segment Editor). :attr:`plan_summary` then holds the summary (:func:`plan_summary`). The
        reconstruction's nodes are left as they are.

        Parameters
        ----------
        cta_volume_node : vtkMRMLScalarVolumeNode
            The CTA (HU), an MRA or a 3DRA. Its IJK -> RAS matrix (and a linear parent transform) place it.
        seeds_node : vtkMRMLMarkupsFiducialNode, optional
            Points inside the vessels of interest. Empty or absent: the automatic tree. Seeds in
            separate vessel structures give one tree per structure.
        access_node : vtkMRMLMarkupsFiducialNode, optional
            One point where the wire will enter the vessels: the tree nearest to it is rooted at its
            point nearest to it and listed first.
        outputs : OutputNodes, optional
            Existing output nodes to update; missing ones are created.

        Raises
        ------
        InputError
            No CTA, implausible voxel spacing or field of view, a seed outside the CTA, an access
            point holding several points or too far from the CTA: before the vessel stage, and
            without creating any node.
        SegmentationError
            No plausible vessel tree (no node is created or changed).
        """
        vol = volume_from_node(cta_volume_node)
        vesselmodel.check_geometry(vol)
        seeds = seeds_from_node(seeds_node)
        if seeds is not None:
            check_seeds_inside(vol, seeds, what=f"seed points {seeds_node.GetName()}")
        access = access_from_node(access_node)
        if access is not None:  # before the heavy work
            access = check_access(access, bounds_lps_mm=vol.bounds_lps_mm, option="access point")
        t0 = time.perf_counter()
        plan = vesselplan.plan_vessels(vol, seeds_lps_mm=seeds, access_lps_mm=access, progress=False, log=log.info)
        log.info("guidewire3d vessels: %d tree(s), %.1f s", len(plan.trees), time.perf_counter() - t0)
        if outputs is not None:
            self.outputs = outputs
        self.plan = plan
        self.plan_summary = plan_summary(plan, access_lps_mm=access)
        self._write_plan_outputs(plan, spacing_mm=vol.spacing_mm)
        self._write_plan_segmentation(plan, cta_volume_node)
        return self.outputs

    def _write_plan_segmentation(self, plan, cta_volume_node) -> None:
        """``plan_segmentation``: each tree's mask (on the CTA's IJK grid, the array :func:`volume_from_node` read) as
        a binary-labelmap segment placed by the CTA's IJK -> RAS matrix, under the CTA's parent transform; an
        existing node's segments are replaced."""
        o = self.outputs
        node = self._alive(o.plan_segmentation)
        if node is None:
            node = self._new("vtkMRMLSegmentationNode", "GW vessel segmentation", "plan_segmentation")
            node.CreateDefaultDisplayNodes()
        node.SetReferenceImageGeometryParameterFromVolumeNode(cta_volume_node)
        node.SetAndObserveTransformNodeID(cta_volume_node.GetTransformNodeID())
        segmentation = node.GetSegmentation()
        segmentation.RemoveAllSegments()
        ijk_to_ras = vtk.vtkMatrix4x4()
        cta_volume_node.GetIJKToRASMatrix(ijk_to_ras)
        colors = ((0.85, 0.3, 0.3), (0.3, 0.55, 0.9), (0.35, 0.75, 0.35), (0.9, 0.7, 0.2))
        for k, auto in enumerate(plan.trees):
            mask = np.asarray(auto.vessels.mask_zyx, dtype=np.uint8)
            img = slicer.vtkOrientedImageData()
            img.SetDimensions(mask.shape[2], mask.shape[1], mask.shape[0])
            img.AllocateScalars(vtk.VTK_UNSIGNED_CHAR, 1)
            vtk_to_numpy(img.GetPointData().GetScalars())[:] = mask.ravel()
            img.SetImageToWorldMatrix(ijk_to_ras)
            segment = slicer.vtkSegment()
            segment.SetName("vessels" if len(plan.trees) == 1 else f"vessel tree {k + 1}")
            segment.SetColor(*colors[k % len(colors)])
            segment.AddRepresentation(slicer.vtkSegmentationConverter.GetBinaryLabelmapRepresentationName(), img)
            segmentation.AddSegment(segment)
        o.plan_segmentation = node

    def _alive(self, node):
        """``node`` if it is still in the scene (the user may have deleted it), else None."""
        return node if node is not None and self.scene.GetNodeByID(node.GetID()) is node else None

    def _write_plan_outputs(self, plan, *, spacing_mm) -> None:
        o = self.outputs
        surface = _with_tree_array(polydata_lps_to_ras(vesselplan.forest_polydata(plan, "surface")))
        o.plan_vessel_model = self._model(self._alive(o.plan_vessel_model), "GW planned vessels", "plan_vessels",
                                          surface, color=(0.85, 0.3, 0.3), opacity=0.35)
        centerline = _with_tree_array(polydata_lps_to_ras(vesselplan.forest_polydata(plan, "centerline")))
        centerline.GetPointData().SetActiveScalars("radius_mm")
        fresh = self._alive(o.plan_centerline_model) is None
        o.plan_centerline_model = self._model(self._alive(o.plan_centerline_model), "GW planned centerline",
                                              "plan_centerline", centerline, color=(0.2, 0.6, 1.0))
        if fresh:
            d = o.plan_centerline_model.GetDisplayNode()
            d.SetLineWidth(3.0)
            d.SetActiveScalarName("radius_mm")
            d.SetScalarVisibility(True)
        o.plan_table = self._alive(o.plan_table) or self._new("vtkMRMLTableNode", "GW vessel branches", "plan_branches")
        rows = []
        for k, a in enumerate(plan.trees):
            rec = vesselplan.vessels_record(a, inputs={"spacing_mm": list(spacing_mm)})
            rows += [(k, b) for b in rec["branches"]]
        _fill_table(o.plan_table, [
            ("tree", "int", [k for k, _ in rows]),
            ("branch", "int", [b["index"] for _, b in rows]),
            ("parent", "int", [b["parent"] for _, b in rows]),
            ("points", "int", [b["n_points"] for _, b in rows]),
            ("length_mm", "float", [b["length_mm"] for _, b in rows]),
            ("radius_min_mm", "float", [b["radius_mm"]["min"] for _, b in rows]),
            ("radius_median_mm", "float", [b["radius_mm"]["median"] for _, b in rows]),
            ("radius_max_mm", "float", [b["radius_mm"]["max"] for _, b in rows]),
        ])
        o.plan_table.SetAttribute("GuidewireReconstruction.Summary", self.plan_summary)
        o.plan_table.SetAttribute("GuidewireReconstruction.SeedGroups",
                                  json.dumps([[int(i) + 1 for i in g] for g in plan.seed_groups]))

    def plan_vessels_parameters(self, p) -> str:
        """Run :meth:`plan_vessels` ("Extract vessels") with the module's parameter node ``p``; returns the summary.

        Reads ``ctaVolume``, ``seeds`` and ``access`` (optional), and the output nodes
        ``planVesselModel``, ``planCenterlineModel``, ``branchesTable`` and ``planSegmentation`` (created when empty, then
        written back to ``p``). No X-ray input is needed.
        """
        o = self.outputs
        outputs = OutputNodes(**{**o.__dict__,
                                 "plan_vessel_model": getattr(p, "planVesselModel", None) or o.plan_vessel_model,
                                 "plan_centerline_model": (getattr(p, "planCenterlineModel", None)
                                                           or o.plan_centerline_model),
                                 "plan_table": getattr(p, "branchesTable", None) or o.plan_table,
                                 "plan_segmentation": (getattr(p, "planSegmentation", None)
                                                       or o.plan_segmentation)})
        out = self.plan_vessels(cta_volume_node=p.ctaVolume, seeds_node=getattr(p, "seeds", None),
                                access_node=getattr(p, "access", None), outputs=outputs)
        p.planVesselModel = out.plan_vessel_model
        p.planCenterlineModel = out.plan_centerline_model
        p.branchesTable = out.plan_table
        p.planSegmentation = out.plan_segmentation
        return self.plan_summary

    # --- the module's parameter node ---------------------------------------------------------
    def process_parameters(self, p) -> str:
        """Run :meth:`process` with the module's parameter node ``p``; returns a one-line summary.

        ``p`` is the module's ``@parameterNodeWrapper`` (or any object with the same attributes):
        ``ctaVolume``, ``roadmapPath``/``roadmapSequence``, ``framesPath``/``framesSequence``, plane B's
        ``roadmapBPath``/``roadmapBSequence`` and ``framesBPath``/``framesBSequence`` (optional), ``seeds``,
        ``access`` (optional), ``roadmapFrame``, ``method``, ``segmenter``, ``force``, ``registrationTransform``,
        ``metricsTable``, ``vesselModel``. An XA file is loaded into a new sequence node, which is
        written back to ``p``; so are the output nodes created by the run.
        """
        roadmap = self._xa_parameter(p.roadmapSequence, p.roadmapPath, "Roadmap")
        if roadmap is None:
            raise InputError("roadmap: give an XA DICOM file path or a sequence node")
        p.roadmapSequence = roadmap
        frames = self._xa_parameter(p.framesSequence, p.framesPath, "Frames")
        if frames is not None:
            p.framesSequence = frames
        # plane B (optional): a biplane run when its roadmap is given
        roadmap_b = self._xa_parameter(getattr(p, "roadmapBSequence", None), getattr(p, "roadmapBPath", None),
                                       "Roadmap B")
        frames_b = self._xa_parameter(getattr(p, "framesBSequence", None), getattr(p, "framesBPath", None), "Frames B")
        if roadmap_b is not None:
            p.roadmapBSequence = roadmap_b
        if frames_b is not None:
            p.framesBSequence = frames_b
        o = self.outputs
        outputs = OutputNodes(**{**o.__dict__, "transform": p.registrationTransform or o.transform,
                                 "table": p.metricsTable or o.table, "vessel_model": p.vesselModel or o.vessel_model})
        out = self.process(cta_volume_node=p.ctaVolume, roadmap=roadmap, frames=frames, seeds_node=p.seeds,
                           roadmap_frame=int(p.roadmapFrame), method=p.method, segmenter=p.segmenter,
                           force=bool(p.force), outputs=outputs,
                           track_motion=bool(getattr(p, "trackMotion", False)), roadmap_b=roadmap_b, frames_b=frames_b,
                           access_node=getattr(p, "access", None))
        p.registrationTransform = out.transform
        p.metricsTable = out.table
        p.vesselModel = out.vessel_model
        return self.summary()

    def refine_parameters(self, p) -> str:
        """Run :meth:`refine` from ``p.registrationTransform``; returns a one-line summary."""
        from guidewire3d.registration import Verdict

        reg = self.refine(transform_node=p.registrationTransform, force=bool(p.force))
        if reg.verdict is Verdict.FAILED and not p.force:
            return f"Refine failed ({reg.message}); the transform and the wires were not changed."
        return self.summary()

    def _xa_parameter(self, sequence, path, what: str):
        if sequence is not None:
            return sequence
        text = "" if path is None else str(path).strip()
        if text in ("", "."):  # an empty pathlib.Path parameter reads back as "."
            return None
        return self.load_xa(text, name=f"{what} {Path(text).stem}")

    def summary(self) -> str:
        """One line: registration state and residual, frames reconstructed."""
        if self.registration is None:
            return "No result yet."
        reg = self.registration
        ok = sum(1 for w in self.wires3d if w.success)
        line = (f"Registration {reg.verdict.label} ({float(reg.mean_residual_px):.2f} px); "
                f"{ok}/{len(self.wires3d)} frames reconstructed")
        if self.biplane is not None:
            line += f" ({sum(1 for p in self.pairs if p.views == 'AB')} from both planes)"
        return line + "."

    def set_transform_interaction(self, visible: bool, *, transform_node=None) -> None:
        """Show or hide Slicer's interaction handles on the registration transform (moves the C-arm)."""
        node = transform_node or self.outputs.transform
        if node is None:
            raise RegistrationError("no registration transform yet: run Apply first")
        if node.GetDisplayNode() is None:
            node.CreateDefaultDisplayNodes()
        node.GetDisplayNode().SetEditorVisibility(bool(visible))

    # --- writing nodes -----------------------------------------------------------------------
    def _new(self, cls: str, name: str, role: str):
        node = self.scene.AddNewNodeByClass(cls, self.scene.GenerateUniqueName(name))
        node.SetAttribute(ROLE_ATTRIBUTE, role)
        return node

    def _model(self, node, name: str, role: str, poly, *, color=(1.0, 1.0, 1.0), opacity: float = 1.0):
        if node is None:
            node = self._new("vtkMRMLModelNode", name, role)
        node.SetAndObservePolyData(poly)
        if node.GetDisplayNode() is None:
            node.CreateDefaultDisplayNodes()
            d = node.GetDisplayNode()
            d.SetColor(*color)
            d.SetOpacity(opacity)
        return node

    def _curve(self, node, name: str, role: str, points_ras_mm, *, color=(1.0, 1.0, 0.0)):
        if node is None:
            node = self._new("vtkMRMLMarkupsCurveNode", name, role)
            node.SetCurveTypeToLinear()
            node.CreateDefaultDisplayNodes()
            d = node.GetDisplayNode()
            d.SetSelectedColor(*color)
            d.SetColor(*color)
            d.SetPointLabelsVisibility(False)
            d.SetPropertiesLabelVisibility(False)
            d.SetGlyphScale(1.0)
        _set_curve_points(node, points_ras_mm)
        node.SetLocked(True)
        return node

    def _write_static_outputs(self) -> None:
        """Vessel surface, centerline curves, C-arm model and the roadmap centerline on the detector."""
        res, o = self.result, self.outputs
        o.vessel_model = self._model(o.vessel_model, "GW vessel surface", "vessels",
                                     polydata_lps_to_ras(res.vessels.surface), color=(0.85, 0.3, 0.3), opacity=0.35)
        tree = res.tree
        from guidewire3d.metrics import resample_polyline

        branches = [resample_polyline(tree.points_lps_mm[b.point_ids], self.centerline_step_mm) for b in tree.branches]
        for k, pts in enumerate(branches):
            node = o.centerline_curves[k] if k < len(o.centerline_curves) else None
            node = self._curve(node, f"GW centerline {k}", "centerline", lps_to_ras(pts), color=(0.2, 0.6, 1.0))
            if k >= len(o.centerline_curves):
                o.centerline_curves.append(node)
        for extra in o.centerline_curves[len(branches):]:
            self.scene.RemoveNode(extra)
        del o.centerline_curves[len(branches):]

        if o.transform is None:
            o.transform = self._new("vtkMRMLLinearTransformNode", "GW registration (CTA to C-arm)", "registration")
        o.carm_model = self._model(o.carm_model, "GW C-arm", "carm", _carm_polydata_room_ras(res.carm), color=(0.9, 0.9, 0.2))
        o.carm_model.SetAndObserveTransformNodeID(o.transform.GetID())
        uv = np.asarray(res.centerline2d.points_uv_px, dtype=float)
        o.roadmap_points_model = self._model(o.roadmap_points_model, "GW roadmap centerline (detector)", "roadmap",
                                             _points_polydata(lps_to_ras(detector_points_room_lps_mm(uv, res.carm))),
                                             color=(0.2, 1.0, 0.4))
        o.roadmap_points_model.GetDisplayNode().SetPointSize(3.0)
        o.roadmap_points_model.SetAndObserveTransformNodeID(o.transform.GetID())

    def _write_plane_b_outputs(self) -> None:
        """Plane B's C-arm and its roadmap centerline on its detector (children of the registration
        transform, like plane A's); removed when the last run had one plane."""
        o, b = self.outputs, self.biplane
        if b is None:
            for name in ("carm_b_model", "roadmap_b_points_model"):
                node = getattr(o, name)
                if node is not None and self.scene.GetNodeByID(node.GetID()) is node:
                    self.scene.RemoveNode(node)
                setattr(o, name, None)
            return
        o.carm_b_model = self._model(o.carm_b_model, "GW C-arm plane B", "carm_b", _carm_polydata_room_ras(b.carm_b),
                                     color=(0.4, 0.8, 1.0))
        uv = np.asarray(b.centerline2d_b.points_uv_px, dtype=float)
        o.roadmap_b_points_model = self._model(o.roadmap_b_points_model, "GW roadmap centerline plane B (detector)",
                                               "roadmap_b",
                                               _points_polydata(lps_to_ras(detector_points_room_lps_mm(uv, b.carm_b))),
                                               color=(0.4, 0.8, 1.0))
        o.roadmap_b_points_model.GetDisplayNode().SetPointSize(3.0)
        for node in (o.carm_b_model, o.roadmap_b_points_model):
            node.SetAndObserveTransformNodeID(o.transform.GetID())

    def _write_registration_outputs(self, *, source: str = "automatic") -> None:
        """The pose into the transform node; quality figures and ``Source`` (automatic | refined) as attributes."""
        reg, node = self.registration, self.outputs.transform
        pose_to_transform_node(reg.pose, node)
        items = [("Success", str(bool(reg.success))), ("Verdict", reg.verdict.value), ("Message", str(reg.message)),
                 ("MeanResidualPx", f"{float(reg.mean_residual_px):.6g}"),
                 ("InlierFraction", f"{float(reg.inlier_fraction):.6g}"),
                 ("Iterations", str(int(reg.iterations))), ("Seconds", f"{float(reg.seconds):.6g}"), ("Source", source)]
        for key, value in items:
            node.SetAttribute(f"GuidewireReconstruction.Registration.{key}", value)

    def _write_wire_outputs(self) -> None:
        res, o = self.result, self.outputs
        frame_ids = list(getattr(res, "frame_indices", None) or range(len(self.wires3d)))[: len(self.wires3d)]
        if o.table is None:
            o.table = self._new("vtkMRMLTableNode", "GW frame metrics", "metrics")
        models, curves = [], []
        last_ok = max((i for i, w in enumerate(self.wires3d) if w.success), default=-1)
        for i, (fid, w) in enumerate(zip(frame_ids, self.wires3d)):
            model = o.wire_models[i] if i < len(o.wire_models) else None
            curve = o.wire_curves[i] if i < len(o.wire_curves) else None
            if w.success and len(w.points_lps_mm) >= 2:
                pts = lps_to_ras(w.points_lps_mm)
                model = self._model(model, f"GW guidewire frame {fid:04d}", "wire",
                                    wire_tube_polydata(pts, w.uncertainty_mm), color=(0.1, 1.0, 0.1))
                dn = model.GetDisplayNode()
                dn.SetActiveScalarName("uncertainty_mm")
                dn.SetScalarVisibility(True)
                curve = self._curve(curve, f"GW guidewire curve frame {fid:04d}", "wire_curve", pts, color=(0.1, 1.0, 0.1))
            else:  # keep the node (index stays aligned with the frames) but empty it
                model = self._model(model, f"GW guidewire frame {fid:04d}", "wire", vtk.vtkPolyData())
                curve = self._curve(curve, f"GW guidewire curve frame {fid:04d}", "wire_curve", np.zeros((0, 3)))
            model.SetAttribute("GuidewireReconstruction.Frame", str(fid))
            curve.SetAttribute("GuidewireReconstruction.Frame", str(fid))
            models.append(model)
            curves.append(curve)
        for extra in o.wire_models[len(models):] + o.wire_curves[len(curves):]:
            self.scene.RemoveNode(extra)
        o.wire_models, o.wire_curves, o.frame_indices = models, curves, frame_ids
        browsed = self._write_wire_sequence()
        self._write_motion_sequence()
        # with a browsable sequence its proxy shows the wire of the current frame; else show the last wire
        for i, (model, curve) in enumerate(zip(models, curves)):
            model.GetDisplayNode().SetVisibility(not browsed and i == last_ok)
            curve.GetDisplayNode().SetVisibility(i == last_ok)
        secs = list(getattr(res, "frame_seconds", []) or [])
        secs += [float("nan")] * (len(self.wires3d) - len(secs))
        ws = self.wires3d

        def _stat(w, fn):
            u = np.asarray(w.uncertainty_mm, dtype=float)
            return float(fn(u)) if w.success and u.size else float("nan")

        _fill_table(o.table, [
            ("frame", "int", [int(f) for f in frame_ids]),
            ("success", "int", [int(bool(w.success)) for w in ws]),
            ("points", "int", [int(len(w.points_lps_mm)) if w.success else 0 for w in ws]),
            ("length_mm", "float", [float(w.length_mm) if w.success else float("nan") for w in ws]),
            ("projection_error_px", "float", [float(w.projection_error_px) if w.success else float("nan") for w in ws]),
            ("mean_uncertainty_mm", "float", [_stat(w, np.mean) for w in ws]),
            ("max_uncertainty_mm", "float", [_stat(w, np.max) for w in ws]),
            ("frame_seconds", "float", [float(s) for s in secs[: len(ws)]]),  # pipeline: 2D + 3D per frame
            ("reconstruction_seconds", "float", [float(w.seconds) for w in ws]),  # 3D step of the shown wire
            ("verdict", "str", [_frame_verdict(self.frame_results, i, w) for i, w in enumerate(ws)]),
            ("message", "str", [_frame_message(self.frame_results, i, w) for i, w in enumerate(ws)]),
        ] + (self._biplane_columns(len(ws)) if self.biplane is not None else []))

    def _biplane_columns(self, n: int) -> list:
        """The metrics table's per-plane columns of a biplane run: plane B's frame, which planes made
        the wire, the 3D wire's projection error in each plane (NaN where not measured)."""
        pairs = self.pairs if len(self.pairs) == n else [None] * n
        return [
            ("frame_b", "int", [int(p.index_b) if p is not None else -1 for p in pairs]),
            ("views", "str", [p.views if p is not None else "" for p in pairs]),
            ("projection_error_px_a", "float", [float(p.projection_error_px[0]) if p is not None else float("nan")
                                                for p in pairs]),
            ("projection_error_px_b", "float", [float(p.projection_error_px[1]) if p is not None else float("nan")
                                                for p in pairs]),
        ]

    def _browser_for(self, sequence_node):
        for i in range(self.scene.GetNumberOfNodesByClass("vtkMRMLSequenceBrowserNode")):
            b = self.scene.GetNthNodeByClass(i, "vtkMRMLSequenceBrowserNode")
            master = b.GetMasterSequenceNode()
            if master is not None and master.GetID() == sequence_node.GetID():
                return b
        return None

    def update_proxies(self, browser) -> None:
        """Refresh the browser's proxy nodes (Slicer does it on its own when frames are browsed)."""
        logic = self.app_logic.GetModuleLogic("Sequences") if self.app_logic is not None else None
        if logic is not None:
            logic.UpdateProxyNodesFromSequences(browser)

    def _frames_browser(self):
        """The browser of the frames' sequence node, or None (frames not from a live sequence node)."""
        src = self.frames_sequence
        if src is None or self.scene.GetNodeByID(src.GetID()) is not src:
            return None
        return self._browser_for(src)

    def _synchronised_sequence(self, node, name: str, role: str, item_for_frame, browser):
        """(Re)fill the sequence ``node`` (created as ``name`` if missing) with one data node per frame
        of the frames' sequence, ``item_for_frame(t)``, synchronise it with ``browser`` and return
        ``(node, proxy)``."""
        src = self.frames_sequence
        if node is None or self.scene.GetNodeByID(node.GetID()) is None:
            node = self._new("vtkMRMLSequenceNode", name, role)
        node.RemoveAllDataNodes()
        node.SetIndexName(src.GetIndexName())
        node.SetIndexUnit(src.GetIndexUnit())
        node.SetIndexType(src.GetIndexType())
        for t in range(src.GetNumberOfDataNodes()):
            node.SetDataNodeAtValue(item_for_frame(t), src.GetNthIndexValue(t))
        if not browser.IsSynchronizedSequenceNodeID(node.GetID(), True):
            browser.AddSynchronizedSequenceNode(node)
            browser.SetSaveChanges(node, False)
        self.update_proxies(browser)
        return node, browser.GetProxyNode(node)

    def _write_wire_sequence(self) -> bool:
        """The wire tube of every frame of the frames' sequence, synchronised with its browser.

        Frames without a reconstructed wire get an empty model. Returns False (and writes nothing)
        when the frames did not come from a browsable sequence node.
        """
        o = self.outputs
        browser = self._frames_browser()
        if browser is None:
            return False
        by_frame = dict(zip(o.frame_indices, o.wire_models))

        def item(t):
            poly = vtk.vtkPolyData()
            model = by_frame.get(t)
            if model is not None and model.GetPolyData() is not None:
                poly.DeepCopy(model.GetPolyData())
            node = slicer.vtkMRMLModelNode()
            node.SetName(f"GW guidewire frame {t:04d}")
            node.SetAndObservePolyData(poly)
            return node

        o.wire_sequence, proxy = self._synchronised_sequence(o.wire_sequence, "GW guidewire (sequence)",
                                                             "wire_sequence", item, browser)
        if proxy is not None:
            proxy.SetAttribute(ROLE_ATTRIBUTE, "wire_proxy")
            if proxy.GetDisplayNode() is None:
                proxy.CreateDefaultDisplayNodes()
            d = proxy.GetDisplayNode()
            d.SetColor(0.1, 1.0, 0.1)
            d.SetActiveScalarName("uncertainty_mm")
            d.SetScalarVisibility(True)
            d.SetVisibility(True)
        return True

    def _write_motion_sequence(self) -> bool:
        """Each frame's tracked pose as a transform synchronised with the frames' browser; the C-arm
        and the roadmap centerline move under its proxy, so browsing the frames shows the tracked
        motion (as the viewer does). Without tracked frames (or a browsable sequence) they stay under
        the registration transform and no sequence is written."""
        o = self.outputs
        poses = {k: fr.pose for k, fr in zip(o.frame_indices, self.frame_results)
                 if getattr(fr, "motion", None) is not None and getattr(fr, "pose", None) is not None}
        browser = self._frames_browser()
        followers = (o.carm_model, o.roadmap_points_model, o.carm_b_model, o.roadmap_b_points_model)
        if not poses or browser is None:
            for node in followers:
                if node is not None and o.transform is not None:
                    node.SetAndObserveTransformNodeID(o.transform.GetID())
            return False

        def item(t):
            node = slicer.vtkMRMLLinearTransformNode()
            node.SetName(f"GW tracked pose frame {t:04d}")
            pose_to_transform_node(poses.get(t, self.registration.pose), node)  # untracked frames: the registration
            return node

        o.motion_sequence, proxy = self._synchronised_sequence(o.motion_sequence, "GW tracked pose (sequence)",
                                                               "motion_sequence", item, browser)
        if proxy is not None:
            proxy.SetAttribute(ROLE_ATTRIBUTE, "motion_proxy")
            for node in followers:  # both planes' C-arms and roadmap centerlines (a biplane run's too)
                if node is not None:
                    node.SetAndObserveTransformNodeID(proxy.GetID())
        return True

    # --- saving -------------------------------------------------------------------------
    def save_outputs(self, directory) -> list[Path]:
        """Write every output node through its storage node; returns the written files.

        Vessel surfaces ``.stl``, wire tubes, C-arm and planned centerline ``.vtk`` (keeps the
        uncertainty and radius scalars), curves ``.mrk.json``, metrics and branches ``.tsv``,
        registration ``.h5``. Model and markups files are
        written in LPS, as Slicer does by default; loading them back gives the same RAS nodes.
        """
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        written = []
        o = self.outputs
        plan = [(o.vessel_model, "stl"), (o.carm_model, "vtk"), (o.roadmap_points_model, "vtk"), (o.transform, "h5"),
                (o.table, "tsv"), (o.carm_b_model, "vtk"), (o.roadmap_b_points_model, "vtk"),
                (o.plan_vessel_model, "stl"), (o.plan_centerline_model, "vtk"), (o.plan_table, "tsv"),
                (o.plan_segmentation, "seg.nrrd")]
        plan += [(n, "mrk.json") for n in o.centerline_curves + o.wire_curves]
        plan += [(n, "vtk") for n in o.wire_models]
        for node, ext in plan:
            if node is None:
                continue
            if node.IsA("vtkMRMLModelNode") and (node.GetPolyData() is None or node.GetPolyData().GetNumberOfPoints() == 0):
                continue
            if node.IsA("vtkMRMLMarkupsNode") and node.GetNumberOfControlPoints() == 0:
                continue
            storage = node.GetStorageNode()
            if storage is None:
                node.AddDefaultStorageNode()
                storage = node.GetStorageNode()
            if storage is None:
                raise InputError(f"{node.GetName()}: no storage node (is the application logic set on the scene?)")
            path = directory / f"{_safe_name(node.GetName())}.{ext}"
            storage.SetFileName(str(path))
            if not storage.WriteData(node):
                raise InputError(f"{path}: writing {node.GetName()} failed")
            written.append(path)
        return written


def _frame_verdict(frame_results, i: int, wire3d) -> str:
    if i < len(frame_results):
        return frame_results[i].verdict.value
    return "ok" if wire3d.success else "failed"


def _frame_message(frame_results, i: int, wire3d) -> str:
    return str(frame_results[i].message) if i < len(frame_results) else str(wire3d.message)


def _safe_name(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name).strip("_") or "node"
