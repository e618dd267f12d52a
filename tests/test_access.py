"""The access point (``--access-lps``): the vessel tree rooted where the wire enters.

The pure function on a synthetic tree whose nearest point is known; the commands on the small
simulated case (its ground truth: the wire enters at the tree's root and advances to a leaf); the
default (no access point) unchanged; bad values refused with one line and nothing written.
"""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from guidewire3d import io
from guidewire3d.app import export
from guidewire3d.app.cli import main
from guidewire3d.errors import InputError
from guidewire3d.phantom import load_truth
from guidewire3d.vesseltree import (
    MAX_ACCESS_DISTANCE_MM,
    VesselTree,
    access_record,
    check_access,
    rooted_at_access,
)

EXACT = 1e-9  # mm: points that are copied, not computed
JSON_MM = 1e-3  # mm: points rounded to 3 decimals in report.json / vessels.json
VTP_MM = 1e-4  # mm: points that went through a float32 VTK file


# ------------------------------------------------------------------------------------------
# the pure function, on a synthetic tree
# ------------------------------------------------------------------------------------------
def _tree() -> VesselTree:
    """A trunk along +z (10 mm steps, radius 5 -> 3 mm) with a side branch along +x from its third point
    and a second one along -y from its fourth: the root (point 0) is the trunk's widest end."""
    z = np.arange(6) * 10.0
    trunk = np.c_[np.zeros(6), np.zeros(6), z]
    side = np.c_[np.arange(5) * 10.0, np.zeros(5), np.full(5, 20.0)]
    back = np.c_[np.zeros(4), -np.arange(4) * 8.0, np.full(4, 30.0)]
    return VesselTree.from_polylines([trunk, side, back], [np.linspace(5, 3, 6), np.full(5, 1.5), np.full(4, 1.0)],
                                     [None, (0, 2), (0, 3)])


def _undirected_edges(tree: VesselTree) -> set:
    return {tuple(sorted(map(int, e))) for e in tree.edges}


def test_access_roots_the_tree_at_its_nearest_point_and_keeps_its_geometry():
    tree = _tree()
    rng = np.random.default_rng(0)
    for target in (9, 5, 12, 0):  # the side branch's end, the trunk's far end, the back branch's end, the root
        access = tree.points_lps_mm[target] + rng.normal(0.0, 1.0, 3)  # within a mm or two of the point
        want = int(np.argmin(np.linalg.norm(tree.points_lps_mm - access, axis=1)))
        assert want == target
        rooted = rooted_at_access(tree, access)
        assert rooted.root == target
        np.testing.assert_array_equal(rooted.points_lps_mm, tree.points_lps_mm)
        np.testing.assert_array_equal(rooted.radius_mm, tree.radius_mm)
        assert _undirected_edges(rooted) == _undirected_edges(tree)
        assert rooted.total_length_mm == pytest.approx(tree.total_length_mm, abs=EXACT)
        # every point's path now starts at the access point's nearest point
        assert all(rooted.path_to_root(i)[0] == target for i in range(tree.n_points))
        rec = access_record(rooted, access)
        assert rec["root_index"] == target
        np.testing.assert_allclose(rec["root_lps_mm"], tree.points_lps_mm[target], atol=JSON_MM)
        assert rec["distance_mm"] == pytest.approx(np.linalg.norm(tree.points_lps_mm[target] - access), abs=0.01)
    assert rooted_at_access(tree, tree.points_lps_mm[0]) is tree  # already rooted there
    assert tree.root == 0  # the input is not modified


def test_an_access_outside_the_field_of_view_uses_the_nearest_point():
    """A puncture below the CTA's field of view (beyond the trunk's far end, along it): the trunk's end."""
    tree = _tree()
    below = tree.points_lps_mm[5] + [0.0, 0.0, 120.0]
    assert rooted_at_access(tree, below).root == 5


def test_a_far_access_is_refused_naming_the_option_and_the_distance():
    tree = _tree()
    far = tree.points_lps_mm[5] + [0.0, 0.0, MAX_ACCESS_DISTANCE_MM + 10.0]
    with pytest.raises(InputError, match=r"^--access-lps=0,0,210: 160 mm from the nearest point of the vessel tree "
                                         r"\(at most 150 mm"):
        rooted_at_access(tree, far)
    with pytest.raises(InputError, match=r"access point \(0,0,210 LPS mm\): 160 mm"):
        rooted_at_access(tree, far, option="access point")
    assert rooted_at_access(tree, far, max_distance_mm=200.0).root == 5


@pytest.mark.parametrize("bad, match", [
    ("abc", "expected a point x,y,z"),
    ([1.0, 2.0], "got 2 values"),
    ([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], "got 6 values"),
    ([np.nan, 0.0, 0.0], "not a finite point"),
    ([0.0, np.inf, 0.0], "not a finite point"),
])
def test_bad_access_points_are_refused(bad, match):
    with pytest.raises(InputError, match=match):
        rooted_at_access(_tree(), bad)


def test_check_access_refuses_a_point_far_outside_the_volume_before_any_work():
    bounds = np.array([[0.0, 0.0, 0.0], [100.0, 100.0, 100.0]])
    np.testing.assert_array_equal(check_access((10, 20, -140), bounds_lps_mm=bounds), [10.0, 20.0, -140.0])
    with pytest.raises(InputError, match=r"--access-lps=10,20,-160: 160 mm outside the CTA's field of view"):
        check_access((10, 20, -160), bounds_lps_mm=bounds)
    # 3D distance to the box, not per axis: 120 mm below and 120 mm beside it is 170 mm away
    with pytest.raises(InputError, match="170 mm outside"):
        check_access((-120, 50, -120), bounds_lps_mm=bounds)


def test_nearest_point_returns_index_then_distance():
    tree = _tree()
    idx, dist = tree.nearest_point([[41.0, 0.0, 20.0], [0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(idx, [9, 0])
    np.testing.assert_allclose(dist, [1.0, 0.0], atol=EXACT)


# ------------------------------------------------------------------------------------------
# `guidewire3d vessels` on the small simulated case
# ------------------------------------------------------------------------------------------
def _polydata_points_and_edges(path):
    poly = export.read_polydata(path)
    pts = np.array([poly.GetPoint(i) for i in range(poly.GetNumberOfPoints())])
    edges = set()
    lines = poly.GetLines()
    lines.InitTraversal()
    import vtk

    ids = vtk.vtkIdList()
    while lines.GetNextCell(ids):
        run = [ids.GetId(k) for k in range(ids.GetNumberOfIds())]
        edges |= {tuple(sorted(e)) for e in zip(run[:-1], run[1:])}
    return pts, edges


@pytest.fixture(scope="module")
def planned(small_case_dir, tmp_path_factory):
    """`vessels` on the small case without an access point, then with one at the far end of a leaf branch."""
    root = tmp_path_factory.mktemp("access-vessels")
    plain = root / "plain"
    assert main(["vessels", "--cta", str(small_case_dir / "ct"), "--out", str(plain)]) == 0
    rec = json.loads((plain / "vessels.json").read_text())
    start = np.asarray(rec["tree"]["root_lps_mm"])
    leaves = [b for b in rec["branches"] if not b["children"]]
    leaf_end = np.asarray(max(leaves, key=lambda b: np.linalg.norm(np.asarray(b["end_lps_mm"]) - start))["end_lps_mm"])
    access = leaf_end + [0.04, -0.03, 0.02]  # nearer the leaf's end than its neighbours (about 0.5 mm apart)
    rooted = root / "rooted"
    assert main(["vessels", "--cta", str(small_case_dir / "ct"), "--out", str(rooted),
                 "--access-lps=" + ",".join(f"{v:.3f}" for v in access)]) == 0
    return plain, rooted, access, leaf_end


def test_vessels_writes_the_tree_rooted_at_the_access(planned):
    plain, rooted, access, leaf_end = planned
    a = json.loads((plain / "vessels.json").read_text())
    b = json.loads((rooted / "vessels.json").read_text())
    # the root is the leaf's end (vessels.json rounds to 0.01 mm), recorded with the access point
    np.testing.assert_allclose(b["tree"]["root_lps_mm"], leaf_end, atol=0.01)
    np.testing.assert_allclose(b["access"]["root_lps_mm"], leaf_end, atol=0.01)
    np.testing.assert_allclose(b["access"]["access_lps_mm"], access, atol=JSON_MM)
    np.testing.assert_allclose(b["inputs"]["access_lps_mm"], access, atol=JSON_MM)
    assert b["access"]["distance_mm"] == pytest.approx(np.linalg.norm(access - leaf_end), abs=0.02)
    # how each root was chosen: the simulator's coronary-sized tree has no aorta, so its own is its widest end
    assert (a["tree"]["root"], b["tree"]["root"]) == ("the widest end", "the access point (--access-lps)")
    assert len(b["branches"]) == len(a["branches"])  # rooted at a leaf's end: the same runs, reversed
    assert np.linalg.norm(np.subtract(b["tree"]["root_lps_mm"], a["tree"]["root_lps_mm"])) > 10.0
    # the same tree: points, radii, edges and length; only the branches' direction changed
    for key in ("n_points", "total_length_mm", "radius_mm"):
        assert b["tree"][key] == a["tree"][key]
    pa, ea = _polydata_points_and_edges(plain / "centerline.vtp")
    pb, eb = _polydata_points_and_edges(rooted / "centerline.vtp")
    np.testing.assert_allclose(pb, pa, atol=VTP_MM)
    assert eb == ea and len(ea) == a["tree"]["n_points"] - 1
    assert (rooted / "vessels.stl").read_bytes() == (plain / "vessels.stl").read_bytes()


def test_vessels_without_access_writes_the_automatic_tree_unchanged(planned, small_case_dir, tmp_path):
    """The default is the tree of the vessel stage as it was: byte for byte, no "access" record."""
    from guidewire3d.cta import vesselmodel

    plain = planned[0]
    rec = json.loads((plain / "vessels.json").read_text())
    assert "access" not in rec and "access_lps_mm" not in rec["inputs"]
    tree = vesselmodel.extract_vessels_auto(io.read_volume(small_case_dir / "ct")).vessels.tree
    export.write_polydata(tree.to_polydata(), tmp_path / "centerline.vtp")
    assert (plain / "centerline.vtp").read_bytes() == (tmp_path / "centerline.vtp").read_bytes()
    np.testing.assert_allclose(rec["tree"]["root_lps_mm"], tree.points_lps_mm[tree.root], atol=0.01)


def test_vessels_refuses_an_access_far_from_the_tree_and_writes_nothing(small_case_dir, tmp_path, capsys):
    """Within 150 mm of the CTA's field of view (not refused before the vessel stage) but further from every
    vessel: refused once the tree is known, and the output folder does not appear."""
    vol = io.read_volume(small_case_dir / "ct")
    lo, hi = vol.bounds_lps_mm
    access = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2] - 140.0])  # 140 mm below the volume
    out = tmp_path / "out"
    rc = main(["vessels", "--cta", str(small_case_dir / "ct"), "--out", str(out),
               "--access-lps=" + ",".join(f"{v:.2f}" for v in access)])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1
    assert err.startswith("guidewire3d: error: --access-lps=") and "mm from the nearest point of the vessel tree" in err
    d = float(err.split(": ")[3].split(" mm")[0])
    assert MAX_ACCESS_DISTANCE_MM < d < 200.0
    assert not out.exists() and list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------
# `guidewire3d reconstruct`: bad values refused before any work, the truth's entry point
# ------------------------------------------------------------------------------------------
def _reconstruct(case_dir, out, *extra):
    return main(["reconstruct", "--cta", str(case_dir / "ct"), "--roadmap", str(case_dir / "roadmap.dcm"),
                 "--frames", str(case_dir / "frames.dcm"), "--out", str(out), "--segmenter", "ridge", "--no-images",
                 *extra])


@pytest.mark.parametrize("value, match", [
    ("--access-lps=abc", "argument --access-lps: expected x,y,z in mm, got 'abc'"),
    ("--access-lps=1,2", "argument --access-lps: expected x,y,z in mm, got '1,2'"),
    ("--access-lps=nan,0,0", "--access-lps=nan,0,0: not a finite point"),
    ("--access-lps=1000,0,0", "--access-lps=1000,0,0: [0-9]+ mm outside the CTA's field of view"),
])
def test_reconstruct_refuses_a_bad_access_with_one_line_and_writes_nothing(small_case_dir, tmp_path, capsys, value,
                                                                          match):
    out = tmp_path / "out"
    rc = _reconstruct(small_case_dir, out, value)
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert re.search("^guidewire3d: error: " + match, err), err
    assert list(tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def reconstructed(small_case_dir, tmp_path_factory):
    """`reconstruct` without an access point, and with one at the simulated wire's entry (the truth)."""
    truth = load_truth(small_case_dir)
    entry = truth.tree.points_lps_mm[truth.wire_path_point_ids[0]]
    root = tmp_path_factory.mktemp("access-reconstruct")
    assert _reconstruct(small_case_dir, root / "plain") == 0
    assert _reconstruct(small_case_dir, root / "entry", "--access-lps=" + ",".join(f"{v:.3f}" for v in entry)) == 0
    return root / "plain", root / "entry", entry, truth


def test_reconstruct_records_the_access_and_its_root(reconstructed):
    plain, at_entry, entry, _ = reconstructed
    rep = json.loads((at_entry / "report.json").read_text())
    np.testing.assert_allclose(rep["inputs"]["access_lps_mm"], entry, atol=JSON_MM)
    np.testing.assert_allclose(rep["access"]["access_lps_mm"], entry, atol=JSON_MM)
    reg = np.load(at_entry / "registration_inputs.npz")
    tree = VesselTree(reg["tree_points_lps_mm"], reg["tree_radius_mm"], reg["tree_parent"])
    assert rep["access"]["root_index"] == tree.root  # what the folder holds is the rooted tree
    np.testing.assert_allclose(rep["access"]["root_lps_mm"], tree.points_lps_mm[tree.root], atol=JSON_MM)
    nearest = np.min(np.linalg.norm(tree.points_lps_mm - entry, axis=1))
    assert rep["access"]["distance_mm"] == pytest.approx(nearest, abs=0.01)
    assert "access" not in json.loads((plain / "report.json").read_text())


def test_an_access_at_the_wires_true_entry_reproduces_the_default(reconstructed):
    """The simulated wire enters at the automatic tree's root (its widest end): rooting the tree at the
    entry changes nothing, and the 3D wires match the truth as without it."""
    from guidewire3d import metrics

    plain, at_entry, _, truth = reconstructed
    assert (at_entry / "centerline.vtp").read_bytes() == (plain / "centerline.vtp").read_bytes()
    a = json.loads((plain / "report.json").read_text())
    b = json.loads((at_entry / "report.json").read_text())
    assert b["pose"] == a["pose"]
    for fa, fb in zip(a["frames"], b["frames"], strict=True):
        assert (fb["success"], fb["verdict"], fb["points_lps_mm"]) == (fa["success"], fa["verdict"], fa["points_lps_mm"])
    errs = [metrics.wire_errors_mm(f["points_lps_mm"], truth.wire_lps_mm[f["index"]][truth.wire_visible[f["index"]]])
            ["mean_error_mm"] for f in b["frames"] if f["success"]]
    assert len(errs) == truth.n_frames and np.median(errs) < 1.0  # test_pipeline.py's MEAN_3D_ERROR_MM


# ------------------------------------------------------------------------------------------
# live setup and the Slicer module's logic
# ------------------------------------------------------------------------------------------
def test_live_from_an_output_folder_roots_its_tree(reconstructed):
    from guidewire3d.app import stream

    plain = reconstructed[0]
    base = stream.setup_from_outdir(plain)
    far_leaf = int(np.argmax(base.tree.arclength_from_root_mm))
    setup = stream.setup_from_outdir(plain, access_lps_mm=base.tree.points_lps_mm[far_leaf] + 0.05)
    assert setup.tree.root == far_leaf and base.tree.root != far_leaf
    assert _undirected_edges(setup.tree) == _undirected_edges(base.tree)
    assert setup.pose is base.pose or np.array_equal(setup.pose.matrix, base.pose.matrix)
    assert "rooted at" in setup.description and "rooted at" not in base.description


PLUGIN_DIR = Path(__file__).resolve().parents[1] / "plugin" / "GuidewireReconstruction"


@pytest.fixture()
def plugin_logic(tmp_path):
    pytest.importorskip("slicer")
    sys.path.insert(0, str(PLUGIN_DIR))
    try:
        from GuidewireReconstructionLib import logic as L
    finally:
        sys.path.remove(str(PLUGIN_DIR))
    hs = L.create_headless_scene(home_directory=tmp_path / "home")
    yield L, hs
    hs.scene.Clear(1)


def test_plugin_access_markup_is_one_point_in_lps(plugin_logic):
    import vtk

    L, hs = plugin_logic
    access_lps = np.array([-12.5, 30.0, -140.0])
    node = hs.scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "Access")
    assert L.access_from_node(node) is None and L.access_from_node(None) is None
    node.AddControlPointWorld(vtk.vtkVector3d(*L.lps_to_ras(access_lps)))
    np.testing.assert_allclose(L.access_from_node(node), access_lps, atol=EXACT)
    node.AddControlPointWorld(vtk.vtkVector3d(0.0, 0.0, 0.0))
    with pytest.raises(InputError, match="Access holds 2 points; place one"):
        L.access_from_node(node)


def test_plugin_refuses_a_far_access_before_running(plugin_logic, small_case, small_case_dir):
    import vtk

    L, hs = plugin_logic
    cta = L.volume_to_node(small_case.volume, scene=hs.scene)
    node = hs.scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "Access")
    node.AddControlPointWorld(vtk.vtkVector3d(*L.lps_to_ras(np.array([1000.0, 0.0, 0.0]))))
    core = L.GuidewireReconstructionCoreLogic(hs.scene)
    with pytest.raises(InputError, match=r"^access point \(1000,0,0 LPS mm\): [0-9]+ mm outside the CTA"):
        core.process(cta_volume_node=cta, roadmap=small_case_dir / "roadmap.dcm", access_node=node)
    assert core.result is None


def test_plugin_parameter_node_has_the_access_markup():
    import ast
    import xml.etree.ElementTree as ET

    tree = ast.parse((PLUGIN_DIR / "GuidewireReconstruction.py").read_text())
    cls = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == "GuidewireReconstructionParameterNode")
    ann = {s.target.id: ast.unparse(s.annotation) for s in cls.body if isinstance(s, ast.AnnAssign)}
    assert ann["access"] == "vtkMRMLMarkupsFiducialNode"
    ui = ET.parse(PLUGIN_DIR / "Resources" / "UI" / "GuidewireReconstruction.ui")
    w = next(w for w in ui.iter("widget") if w.get("name") == "accessSelector")
    props = {p.get("name"): p for p in w.findall("property")}
    assert props["SlicerParameterName"].find("string").text == "access"
    assert props["noneEnabled"].find("bool").text == "true"  # optional


def test_live_setup_from_inputs_roots_the_tree_it_registers(reconstructed, small_case_dir):
    """``live --cta --roadmap --access-lps``: the setup's tree is rooted at the access, its pose the one
    ``reconstruct`` registered (the same inputs; the access at the automatic root, the truth's entry)."""
    from guidewire3d.app import stream
    from guidewire3d.geometry import Pose

    _, at_entry, entry, _ = reconstructed
    setup = stream.setup_from_inputs(small_case_dir / "ct", small_case_dir / "roadmap.dcm", access_lps_mm=entry)
    rep = json.loads((at_entry / "report.json").read_text())
    assert setup.tree.root == rep["access"]["root_index"]
    assert setup.pose.allclose(Pose.from_matrix(np.asarray(rep["pose"])), atol_mm=1e-6)
    assert "rooted at" in setup.description


def test_live_refuses_a_far_access_with_one_line(reconstructed, capsys):
    plain = reconstructed[0]
    rc = main(["live", "--from", str(plain), "--access-lps=1000,0,0", "--max-frames", "1", "--port", "0"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert re.search(r"^guidewire3d: error: --access-lps=1000,0,0: [0-9]+ mm from the nearest point of the vessel tree",
                     err), err


# ------------------------------------------------------------------------------------------
# biplane `reconstruct`
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def biplane_case_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("access-biplane") / "case"
    assert main(["phantom", "--out", str(out), "--seed", "3", "--frames", "3", "--biplane"]) == 0
    return out


def _biplane_args(d, out, *extra):
    return ["reconstruct", "--cta", str(d / "ct"), "--roadmap", str(d / "roadmap.dcm"), "--roadmap",
            str(d / "roadmap_b.dcm"), "--frames", str(d / "frames.dcm"), "--frames", str(d / "frames_b.dcm"),
            "--out", str(out), "--segmenter", "ridge", "--no-images", *extra]


def test_biplane_reconstruct_records_the_access_and_matches_truth(biplane_case_dir, tmp_path):
    from guidewire3d import metrics

    truth = load_truth(biplane_case_dir)
    entry = truth.tree.points_lps_mm[truth.wire_path_point_ids[0]]
    out = tmp_path / "out"
    assert main(_biplane_args(biplane_case_dir, out, "--access-lps=" + ",".join(f"{v:.3f}" for v in entry))) == 0
    rep = json.loads((out / "report.json").read_text())
    np.testing.assert_allclose(rep["inputs"]["access_lps_mm"], entry, atol=JSON_MM)
    assert rep["inputs"]["biplane"] and rep["biplane"]["n_pairs"] == 3  # the biplane report kept
    reg = np.load(out / "registration_inputs.npz")
    tree = VesselTree(reg["tree_points_lps_mm"], reg["tree_radius_mm"], reg["tree_parent"])
    assert rep["access"]["root_index"] == tree.root
    assert rep["access"]["distance_mm"] == pytest.approx(np.min(np.linalg.norm(tree.points_lps_mm - entry, axis=1)),
                                                         abs=0.01)
    ok = [f for f in rep["frames"] if f["success"]]
    assert len(ok) == 3
    for f in ok:
        vis = np.asarray(truth.wire_visible[f["index"]], bool)
        assert metrics.wire_errors_mm(f["points_lps_mm"], np.asarray(truth.wire_lps_mm[f["index"]])[vis])[
            "mean_error_mm"] < 1.0  # test_biplane.py's tolerance


def test_biplane_reconstruct_refuses_a_far_access_and_writes_nothing(biplane_case_dir, tmp_path, capsys):
    rc = main(_biplane_args(biplane_case_dir, tmp_path / "out", "--access-lps=0,0,5000"))
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "--access-lps=0,0,5000: " in err and "mm outside the CTA" in err
    assert list(tmp_path.iterdir()) == []
