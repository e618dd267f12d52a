"""The Slicer module's "Extract vessels" (planning: the CTA alone), run for real under slicer-core (no Qt).

The volume is a phantom with a known answer: straight parallel tubes (400 HU, radius 2 mm) along S in 40 HU
tissue with noise, 0.5 mm voxels (as ``tests/test_vessels3d_seeds_apart.py``), placed off the origin so that an
LPS/RAS mix-up moves every point by tens of mm. The module's nodes are RAS; the checks convert them back to LPS
and compare with the tubes' axes.
"""
from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import vtk  # noqa: E402
from vtk.util.numpy_support import vtk_to_numpy  # noqa: E402

from guidewire3d import io  # noqa: E402
from guidewire3d.errors import InputError, SegmentationError  # noqa: E402

PLUGIN_DIR = Path(__file__).resolve().parents[1] / "plugin" / "GuidewireReconstruction"
sys.path.insert(0, str(PLUGIN_DIR))

from GuidewireReconstructionLib import logic as L  # noqa: E402
from test_plugin import reload_node  # noqa: E402

SPACING_MM = 0.5
RADIUS_MM = 2.0
SHAPE_ZYX = (60, 80, 80)
ORIGIN_LPS_MM = np.array([-35.0, 60.0, -120.0])  # off the origin: a missed L/P flip is 70-120 mm off
AXIS_Y_MM = 20.0  # the tubes' axes, from the volume's origin
TUBE_X_MM = (10.0, 30.0)  # 20 mm apart
AXES_LPS_MM = [ORIGIN_LPS_MM[:2] + np.array([x, AXIS_Y_MM]) for x in TUBE_X_MM]  # (L, P) of each axis
MID_S_MM = ORIGIN_LPS_MM[2] + 15.0  # half-way along the tubes
AXIS_TOL_MM = 1.0  # centerline to the tube's axis (the brief's tolerance; the stage does ~0.1 mm here)
RADIUS_TOL_MM = 0.5  # surface to the tube's wall, radius per branch in the table
MIN_LENGTH_MM = 20.0  # the tubes span 30 mm; the centerline stops short of the volume's ends
FLOAT32_MM = 1e-4


def _tubes(xs_mm=TUBE_X_MM) -> io.Volume:
    """Straight parallel tubes along S at ``x = xs_mm`` (from the origin), 400 HU in 40 HU tissue, with noise."""
    z, y, x = np.meshgrid(*[SPACING_MM * np.arange(k) for k in SHAPE_ZYX], indexing="ij", sparse=True)
    v = np.full(SHAPE_ZYX, 40.0, np.float32)
    for xc in xs_mm:
        r = np.sqrt((x - xc) ** 2 + (y - AXIS_Y_MM) ** 2)
        v += (360.0 * np.clip(RADIUS_MM + 0.5 * SPACING_MM - r, 0, SPACING_MM) / SPACING_MM).astype(np.float32)
    v += np.random.default_rng(0).normal(0, 10, SHAPE_ZYX).astype(np.float32)
    return io.Volume(v, (SPACING_MM,) * 3, tuple(ORIGIN_LPS_MM), np.eye(3), source="tubes")


@pytest.fixture()
def hs(tmp_path):
    """A fresh headless scene per test (it becomes slicer.mrmlScene)."""
    h = L.create_headless_scene(home_directory=tmp_path / "home")
    yield h
    h.scene.Clear(1)


def _points_node(scene, points_lps_mm, name="Seeds"):
    node = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", name)
    for p in L.lps_to_ras(np.asarray(points_lps_mm, float).reshape(-1, 3)):
        node.AddControlPointWorld(vtk.vtkVector3d(*p))
    return node


def _seed(k: int) -> list:
    """A seed on tube ``k``'s axis, half-way along it (LPS mm)."""
    return [*AXES_LPS_MM[k], MID_S_MM]


def _points_lps(model) -> np.ndarray:
    return L.ras_to_lps(vtk_to_numpy(model.GetPolyData().GetPoints().GetData()).astype(float))


def _array(model, name) -> np.ndarray:
    arr = model.GetPolyData().GetPointData().GetArray(name)
    assert arr is not None, f"{model.GetName()} has no point array {name}"
    return vtk_to_numpy(arr)


def _off_axis_mm(points_lps_mm, k: int) -> np.ndarray:
    return np.linalg.norm(points_lps_mm[:, :2] - AXES_LPS_MM[k], axis=1)


def _column(table_node, name) -> list:
    t = table_node.GetTable()
    return [t.GetValueByName(i, name).ToDouble() for i in range(t.GetNumberOfRows())]


def _parameters(**kw):
    """What the module's parameter node holds for "Extract vessels", as a plain object."""
    p = dict(ctaVolume=None, seeds=None, access=None, planVesselModel=None, planCenterlineModel=None,
             branchesTable=None, planSegmentation=None)
    p.update(kw)
    return SimpleNamespace(**p)


# ------------------------------------------------------------------------------------------
# One seed, one tree
# ------------------------------------------------------------------------------------------
def test_one_seed_gives_its_tubes_tree_on_the_axis(hs):
    cta = L.volume_to_node(_tubes(), scene=hs.scene)
    core = L.GuidewireReconstructionCoreLogic(hs.scene)
    out = core.plan_vessels(cta_volume_node=cta, seeds_node=_points_node(hs.scene, [_seed(0)]))

    cl = _points_lps(out.plan_centerline_model)
    assert len(cl) >= 2
    assert _off_axis_mm(cl, 0).max() < AXIS_TOL_MM  # the seeded tube's axis, not the other tube's
    assert np.ptp(cl[:, 2]) > MIN_LENGTH_MM
    assert set(_array(out.plan_centerline_model, "tree")) == {0}
    radius = _array(out.plan_centerline_model, "radius_mm")
    assert abs(float(np.median(radius)) - RADIUS_MM) < RADIUS_TOL_MM

    surf = _points_lps(out.plan_vessel_model)
    assert len(surf) > 100
    wall = _off_axis_mm(surf, 0)
    assert abs(float(np.median(wall)) - RADIUS_MM) < RADIUS_TOL_MM  # the wall of tube 0
    assert wall.max() < RADIUS_MM + 2 * SPACING_MM

    t = out.plan_table
    assert t.GetNumberOfRows() == len(core.plan.trees[0].vessels.tree.branches) >= 1
    assert set(_column(t, "tree")) == {0}
    # the branches add up to the centerline's length (the same record as `guidewire3d vessels`' vessels.json)
    assert sum(_column(t, "length_mm")) == pytest.approx(core.plan.trees[0].vessels.tree.total_length_mm, abs=0.1)
    assert all(abs(r - RADIUS_MM) < RADIUS_TOL_MM for r in _column(t, "radius_median_mm"))
    assert [n.GetAttribute(L.ROLE_ATTRIBUTE) for n in (out.plan_vessel_model, out.plan_centerline_model, t)] == \
        list(L.VESSEL_PLAN_ROLES)
    assert core.plan_summary.startswith("1 vessel tree: ")
    assert "Tree 1 (seeds 1)" in core.plan_summary and "(HU, seeds)" in core.plan_summary
    assert core.result is None and out.vessel_model is None  # the reconstruction's nodes are untouched


def test_automatic_tree_of_a_single_tube(hs):
    cta = L.volume_to_node(_tubes(TUBE_X_MM[:1]), scene=hs.scene)
    empty = hs.scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "no seeds")  # empty: automatic
    core = L.GuidewireReconstructionCoreLogic(hs.scene)
    out = core.plan_vessels(cta_volume_node=cta, seeds_node=empty)
    cl = _points_lps(out.plan_centerline_model)
    assert _off_axis_mm(cl, 0).max() < AXIS_TOL_MM
    assert np.ptp(cl[:, 2]) > MIN_LENGTH_MM
    assert "Tree 1 (automatic)" in core.plan_summary


# ------------------------------------------------------------------------------------------
# Seeds in separate structures: a forest
# ------------------------------------------------------------------------------------------
def test_a_seed_in_each_tube_gives_two_trees_each_on_its_axis(hs):
    cta = L.volume_to_node(_tubes(), scene=hs.scene)
    core = L.GuidewireReconstructionCoreLogic(hs.scene)
    out = core.plan_vessels(cta_volume_node=cta, seeds_node=_points_node(hs.scene, [_seed(0), _seed(1)]))

    cl, tree = _points_lps(out.plan_centerline_model), _array(out.plan_centerline_model, "tree")
    assert sorted(set(tree)) == [0, 1]
    for k in (0, 1):  # tree k is seed k's tube (no access point: the first seed's tree first)
        assert _off_axis_mm(cl[tree == k], k).max() < AXIS_TOL_MM
        assert np.ptp(cl[tree == k][:, 2]) > MIN_LENGTH_MM
    surf, surf_tree = _points_lps(out.plan_vessel_model), _array(out.plan_vessel_model, "tree")
    for k in (0, 1):
        assert abs(float(np.median(_off_axis_mm(surf[surf_tree == k], k))) - RADIUS_MM) < RADIUS_TOL_MM

    assert sorted(set(_column(out.plan_table, "tree"))) == [0, 1]
    assert out.plan_table.GetNumberOfRows() == sum(len(a.vessels.tree.branches) for a in core.plan.trees)
    assert core.plan_summary.startswith("2 separate vessel trees")
    assert "Tree 1 (seeds 1)" in core.plan_summary and "Tree 2 (seeds 2)" in core.plan_summary


def test_the_access_points_tree_comes_first_and_is_rooted_at_it(hs):
    cta = L.volume_to_node(_tubes(), scene=hs.scene)
    access_lps = np.array([*AXES_LPS_MM[1], ORIGIN_LPS_MM[2] + 2.0])  # near the inferior end of tube 1
    core = L.GuidewireReconstructionCoreLogic(hs.scene)
    out = core.plan_vessels(cta_volume_node=cta, seeds_node=_points_node(hs.scene, [_seed(0), _seed(1)]),
                            access_node=_points_node(hs.scene, [access_lps], name="Access"))
    cl, tree = _points_lps(out.plan_centerline_model), _array(out.plan_centerline_model, "tree")
    assert _off_axis_mm(cl[tree == 0], 1).max() < AXIS_TOL_MM  # the second seed's tube, listed first
    assert _off_axis_mm(cl[tree == 1], 0).max() < AXIS_TOL_MM
    first = core.plan.trees[0].vessels.tree
    root = first.points_lps_mm[first.root]
    assert np.linalg.norm(root - access_lps) == pytest.approx(np.min(np.linalg.norm(cl[tree == 0] - access_lps, axis=1)),
                                                              abs=FLOAT32_MM)
    assert "Tree 1 (seeds 2)" in core.plan_summary and "nearest the access point" in core.plan_summary


# ------------------------------------------------------------------------------------------
# Re-running, the parameter node, saving
# ------------------------------------------------------------------------------------------
def test_parameters_are_read_written_back_and_a_rerun_updates_the_same_nodes(hs):
    cta = L.volume_to_node(_tubes(), scene=hs.scene)
    seeds = _points_node(hs.scene, [_seed(0)])
    mine = hs.scene.AddNewNodeByClass("vtkMRMLTableNode", "my branches")
    p = _parameters(ctaVolume=cta, seeds=seeds, branchesTable=mine)
    core = L.GuidewireReconstructionCoreLogic(hs.scene)
    summary = core.plan_vessels_parameters(p)
    assert summary == core.plan_summary and summary.startswith("1 vessel tree")
    out = core.outputs
    assert p.branchesTable is mine and out.plan_table is mine and mine.GetNumberOfRows() >= 1  # the user's node, filled
    assert p.planVesselModel is out.plan_vessel_model and p.planCenterlineModel is out.plan_centerline_model
    ids = [n.GetID() for n in out.all_nodes()]
    n_nodes = hs.scene.GetNumberOfNodes()

    # a second seed, in the other tube: the same three nodes now show two trees
    seeds.AddControlPointWorld(vtk.vtkVector3d(*L.lps_to_ras(_seed(1))))
    core.plan_vessels_parameters(p)
    assert [n.GetID() for n in core.outputs.all_nodes()] == ids
    assert hs.scene.GetNumberOfNodes() == n_nodes
    assert sorted(set(_array(p.planCenterlineModel, "tree"))) == [0, 1]
    assert sorted(set(_column(mine, "tree"))) == [0, 1]

    # a fresh logic (the module reloaded) finds the nodes through the parameter node
    again = L.GuidewireReconstructionCoreLogic(hs.scene)
    again.plan_vessels_parameters(p)
    assert [n.GetID() for n in again.outputs.all_nodes()] == ids
    assert hs.scene.GetNumberOfNodes() == n_nodes


def test_a_deleted_output_node_is_made_again(hs):
    cta = L.volume_to_node(_tubes(TUBE_X_MM[:1]), scene=hs.scene)
    core = L.GuidewireReconstructionCoreLogic(hs.scene)
    out = core.plan_vessels(cta_volume_node=cta, seeds_node=_points_node(hs.scene, [_seed(0)]))
    hs.scene.RemoveNode(out.plan_table)
    out = core.plan_vessels(cta_volume_node=cta, seeds_node=_points_node(hs.scene, [_seed(0)]))
    assert hs.scene.GetNodeByID(out.plan_table.GetID()) is out.plan_table and out.plan_table.GetNumberOfRows() >= 1


def test_planned_nodes_save_and_reload(hs, tmp_path):
    cta = L.volume_to_node(_tubes(), scene=hs.scene)
    core = L.GuidewireReconstructionCoreLogic(hs.scene)
    out = core.plan_vessels(cta_volume_node=cta, seeds_node=_points_node(hs.scene, [_seed(0), _seed(1)]))
    paths = {q.name: q for q in core.save_outputs(tmp_path / "out")}
    assert sorted(paths) == ["GW_planned_centerline.vtk", "GW_planned_vessels.stl", "GW_vessel_branches.tsv",
                             "GW_vessel_segmentation.seg.nrrd"]

    def reload(cls, path):
        return reload_node(hs.scene, cls, path)

    back = reload("vtkMRMLModelNode", paths["GW_planned_centerline.vtk"])
    np.testing.assert_allclose(_points_lps(back), _points_lps(out.plan_centerline_model), atol=FLOAT32_MM)
    np.testing.assert_array_equal(_array(back, "tree"), _array(out.plan_centerline_model, "tree"))
    table = reload("vtkMRMLTableNode", paths["GW_vessel_branches.tsv"])
    assert _column(table, "length_mm") == pytest.approx(_column(out.plan_table, "length_mm"))
    seg = reload("vtkMRMLSegmentationNode", paths["GW_vessel_segmentation.seg.nrrd"])
    assert seg.GetSegmentation().GetNumberOfSegments() == 2
    for k in (0, 1):
        np.testing.assert_array_equal(_segment_mask(hs.scene, seg, k, cta), _segment_mask(hs.scene, out.plan_segmentation,
                                                                                         k, cta))


def _segment_mask(scene, seg, k: int, cta) -> np.ndarray:
    """Segment ``k`` of ``seg`` on the CTA's grid, (k, j, i) as the CTA's array (the module logic's export, as
    slicer.util would do it with the application's modules)."""
    import slicer

    logic = slicer.vtkSlicerSegmentationsModuleLogic()
    logic.SetMRMLScene(scene)
    lab = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", "segment export")
    ids = vtk.vtkStringArray()
    ids.InsertNextValue(seg.GetSegmentation().GetNthSegmentID(k))
    assert logic.ExportSegmentsToLabelmapNode(seg, ids, lab, cta)
    out = np.array(slicer.util.arrayFromVolume(lab)) > 0
    scene.RemoveNode(lab)
    return out


def test_the_segmentation_holds_each_trees_mask_on_the_ctas_grid(hs):
    """One segment per tree, on the seeded tube's voxels and not the other's; the CTA's array order and placement
    (the tubes lie off the origin: an IJK/RAS slip would move them out of the volume)."""
    cta = L.volume_to_node(_tubes(), scene=hs.scene)
    core = L.GuidewireReconstructionCoreLogic(hs.scene)
    out = core.plan_vessels(cta_volume_node=cta, seeds_node=_points_node(hs.scene, [_seed(0), _seed(1)]))
    seg = out.plan_segmentation
    assert seg.IsA("vtkMRMLSegmentationNode") and seg.GetAttribute(L.ROLE_ATTRIBUTE) == "plan_segmentation"
    names = [seg.GetSegmentation().GetNthSegment(k).GetName() for k in range(seg.GetSegmentation().GetNumberOfSegments())]
    assert names == ["vessel tree 1", "vessel tree 2"]
    vol = L.volume_from_node(cta)
    zyx = np.argwhere(np.ones(vol.shape_zyx, bool)).astype(float)
    lps = vol.index_zyx_to_lps(zyx).reshape(*vol.shape_zyx, 3)
    for k in (0, 1):
        m = _segment_mask(hs.scene, seg, k, cta)
        np.testing.assert_array_equal(m, core.plan.trees[k].vessels.mask_zyx)
        off = np.linalg.norm(lps[m][:, :2] - AXES_LPS_MM[k], axis=1)
        assert m.sum() > 500 and off.max() < RADIUS_MM + 2 * SPACING_MM  # tube k's voxels only

    # a rerun with one seed: the same node, one segment
    core.plan_vessels(cta_volume_node=cta, seeds_node=_points_node(hs.scene, [_seed(1)]))
    assert core.outputs.plan_segmentation is seg and seg.GetSegmentation().GetNumberOfSegments() == 1
    assert seg.GetSegmentation().GetNthSegment(0).GetName() == "vessels"


# ------------------------------------------------------------------------------------------
# Bad inputs: one-line errors before the vessel stage, no node created
# ------------------------------------------------------------------------------------------
def test_bad_inputs_raise_before_the_work_and_create_no_nodes(hs, monkeypatch):
    cta = L.volume_to_node(_tubes(), scene=hs.scene)
    seeds = _points_node(hs.scene, [_seed(0)])
    core = L.GuidewireReconstructionCoreLogic(hs.scene)
    far = _points_node(hs.scene, [[*AXES_LPS_MM[0], MID_S_MM + 400.0]], name="far access")
    two = _points_node(hs.scene, [_seed(0), _seed(1)], name="two access points")
    outside = _points_node(hs.scene, [_seed(0), [*AXES_LPS_MM[0], MID_S_MM - 50.0]], name="seed outside")
    small = io.Volume(np.zeros((4, 4, 4), np.float32), (0.5,) * 3, (0.0, 0.0, 0.0), np.eye(3), source="tiny")
    tiny = L.volume_to_node(small, scene=hs.scene, name="tiny")
    n_nodes = hs.scene.GetNumberOfNodes()

    def no_work(*a, **k):
        raise AssertionError("the vessel stage ran")

    monkeypatch.setattr(L.vesselplan, "plan_vessels", no_work)
    with pytest.raises(InputError, match="CTA volume: select a scalar volume node"):
        core.plan_vessels(cta_volume_node=None, seeds_node=seeds)
    with pytest.raises(InputError, match=r"access point \(.* LPS mm\): 3\d\d mm outside the CTA's field of view"):
        core.plan_vessels(cta_volume_node=cta, seeds_node=seeds, access_node=far)
    with pytest.raises(InputError, match="access point: two access points holds 2 points"):
        core.plan_vessels(cta_volume_node=cta, access_node=two)
    with pytest.raises(InputError, match=r"seed points seed outside: point 2 \(RAS .* mm\) lies outside the volume CTA"):
        core.plan_vessels(cta_volume_node=cta, seeds_node=outside)
    with pytest.raises(InputError, match="CTA volume"):  # the parameter node's entry: no CTA selected
        core.plan_vessels_parameters(_parameters(seeds=seeds))
    with pytest.raises(InputError, match="tiny: field of view of 2.0 mm is too small"):
        core.plan_vessels(cta_volume_node=tiny)
    assert hs.scene.GetNumberOfNodes() == n_nodes
    assert core.plan is None and core.outputs.all_nodes() == []


def test_a_volume_without_a_plausible_tree_raises_and_creates_no_nodes(hs):
    cta = L.volume_to_node(_tubes(), scene=hs.scene)  # two tubes of the same size, no seed: ambiguous
    core = L.GuidewireReconstructionCoreLogic(hs.scene)
    n_nodes = hs.scene.GetNumberOfNodes()
    with pytest.raises(SegmentationError, match="ambiguous"):
        core.plan_vessels(cta_volume_node=cta)
    assert hs.scene.GetNumberOfNodes() == n_nodes
    assert core.plan is None and core.outputs.all_nodes() == []


# ------------------------------------------------------------------------------------------
# The summary: every note of the vessel stage
# ------------------------------------------------------------------------------------------
def _fake_tree(length_mm: float, radii_mm, n_branches: int):
    return SimpleNamespace(branches=[None] * n_branches, total_length_mm=length_mm,
                           radius_mm=np.asarray(radii_mm, float))


def test_summary_names_units_levels_and_every_note():
    mr = SimpleNamespace(
        vessels=SimpleNamespace(tree=_fake_tree(123.0, [1.0, 2.0, 3.0], 5), cut_through_lps_mm=((12.4, -30.0, 250.6),)),
        model=SimpleNamespace(hu=False, lumen=812.5, background=101.25, source="automatic"),
        plausibility=SimpleNamespace(vessel_cm3=4.44), first_pass_problems=("too long for its volume",),
        segmentation="strict+pruned", pruned="2 dim wide branches cut", bias_field="a bias field of 1.4x divided out",
        seeded="automatic tree", seconds={"total": 12.0}, fallback="")
    ct = SimpleNamespace(
        vessels=SimpleNamespace(tree=_fake_tree(40.0, [2.0, 2.0], 1), cut_through_lps_mm=()),
        model=SimpleNamespace(hu=True, lumen=400.0, background=40.0, source="seeds"),
        plausibility=SimpleNamespace(vessel_cm3=0.5), first_pass_problems=(), segmentation="standard", pruned="",
        bias_field="", seeded="seeds", seconds={"total": 3.0}, fallback="")
    text = L.plan_summary(SimpleNamespace(trees=(mr, ct), seed_groups=((0, 2), (1,))))
    assert text.splitlines() == [
        "2 separate vessel trees (one per structure the seeds lie in): 6 branches, 16.3 cm of centerline.",
        "Tree 1 (seeds 1, 3): 5 branches, 12.3 cm of centerline, radius 2.0 mm median / 3.0 mm max, 4.4 cm3; lumen "
        "812.5, background 101.2 (arbitrary units, automatic); 12.0 s. Note: the first vessel tree was implausible "
        "(too long for its volume); the strict pass's tree is kept, 2 dim wide branches cut (check it in the viewer); "
        "a bias field of 1.4x divided out; the tree is that of the corrected volume (the intensity levels are its); "
        "the automatic vessel tree holds every seed: it is kept, rooted at its end nearest the first seed along its "
        "widest lumens; a region deeper than the widest vessel expected (16 mm) at LPS 12, -30, 251 mm was cut as a "
        "heart chamber, though a vessel leaves it on opposite sides: it may be an aneurysm beside other vessels, and "
        "the tree may stop there or miss the vessel beyond it (check it in the viewer).",
        "Tree 2 (seeds 2): 1 branch, 4.0 cm of centerline, radius 2.0 mm median / 2.0 mm max, 0.5 cm3; lumen 400, "
        "background 40 (HU, seeds); 3.0 s. Note: the automatic vessel tree does not hold every seed: the tree is the "
        "seeds' own, from the lumen level read at them, rooted at its end nearest the first seed along its widest "
        "lumens.",
    ]
    auto = SimpleNamespace(**{**ct.__dict__, "seeded": ""})
    assert L.plan_summary(SimpleNamespace(trees=(auto,), seed_groups=((),))).splitlines() == [
        "1 vessel tree: 1 branch, 4.0 cm of centerline.",
        "Tree 1 (automatic): 1 branch, 4.0 cm of centerline, radius 2.0 mm median / 2.0 mm max, 0.5 cm3; lumen 400, "
        "background 40 (HU, seeds); 3.0 s.",
    ]


def test_summary_says_when_the_tree_is_the_hu_defaults():
    """A tree from the HU defaults after the intensity model refused the volume (``vesselmodel.hu_defaults_auto``):
    the note says why, first."""
    ct = SimpleNamespace(
        vessels=SimpleNamespace(tree=_fake_tree(40.0, [2.0, 2.0], 1), cut_through_lps_mm=()),
        model=SimpleNamespace(hu=True, lumen=410.0, background=45.0, source="HU defaults"),
        plausibility=SimpleNamespace(vessel_cm3=0.5), first_pass_problems=(), segmentation="HU defaults", pruned="",
        bias_field="", seeded="", seconds={"total": 3.0},
        fallback="its own intensity model refused it (ambiguous); its median and the fat or air below water read as a "
                 "CT's in HU (much bone or contrast, no air in view): its vessel tree from the HU defaults")
    text = L.plan_summary(SimpleNamespace(trees=(ct,), seed_groups=((),)))
    assert "(HU, HU defaults)" in text
    assert "Note: its own intensity model refused it (ambiguous);" in text and "(check it in the viewer)" in text
