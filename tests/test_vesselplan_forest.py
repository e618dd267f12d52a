"""Seeds in separate vessel structures: ``guidewire3d vessels`` writes one tree per structure (a forest).

Until stop 44 a seed in a structure apart from the first seed's was refused (exit 2): a head whose left and right
carotid systems are apart at the lumen threshold (a circle of Willis broken there) could be planned one side at a time
only. ``reconstruct`` and ``live`` still refuse it (a wire is reconstructed in one connected tree); the planning command
now runs each structure alone and writes every tree, each point carrying its tree's index.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from vtk.util.numpy_support import vtk_to_numpy

from guidewire3d import io
from guidewire3d.app import cli, export, vesselplan
from guidewire3d.errors import SegmentationError

from test_vessels3d_seeds_apart import APART_MM, _two_tubes

AXIS_Y_MM = 20.0
LEFT_X_MM, RIGHT_X_MM = 10.0, 10.0 + APART_MM


def _seed_arg(p) -> str:
    return "--seed-lps=" + ",".join(f"{v:g}" for v in p)


@pytest.fixture(scope="module")
def tubes_file(tmp_path_factory):
    return io.write_volume(_two_tubes(), tmp_path_factory.mktemp("forest") / "tubes.nii.gz")


def test_seeds_in_two_structures_give_two_trees_each_on_its_own_axis(tubes_file, tmp_path, capsys):
    out = tmp_path / "plan"
    rc = cli.main(["vessels", "--cta", str(tubes_file), "--out", str(out),
                   _seed_arg((RIGHT_X_MM, AXIS_Y_MM, 15.0)), _seed_arg((LEFT_X_MM, AXIS_Y_MM, 12.0))])
    std = capsys.readouterr()
    assert rc == 0, std.err
    assert "2 separate vessel trees" in std.out and "each seed is tried alone" in std.err
    cl = export.read_polydata(out / "centerline.vtp")
    pts = vtk_to_numpy(cl.GetPoints().GetData())
    tree = vtk_to_numpy(cl.GetPointData().GetArray("tree"))
    assert sorted(set(tree.tolist())) == [0, 1]
    # tree 0 is the first seed's structure (the right tube); each tree lies on its own tube's axis, end to end
    for k, x in ((0, RIGHT_X_MM), (1, LEFT_X_MM)):
        p = pts[tree == k]
        assert np.all(np.abs(p[:, 0] - x) < 1.0) and np.all(np.abs(p[:, 1] - AXIS_Y_MM) < 1.0)
        assert np.ptp(p[:, 2]) > 20.0
    rec = json.loads((out / "vessels.json").read_text())
    assert rec["forest"]["n_trees"] == 2 and "apart from the first seed's" in rec["forest"]["reason"]
    assert [t["seeds"] for t in rec["trees"]] == [[0], [1]]
    assert rec["tree"] == rec["trees"][0]["tree"]  # the top level is the first tree's record, as with one tree
    assert rec["forest"]["total_length_mm"] == pytest.approx(sum(t["tree"]["total_length_mm"] for t in rec["trees"]),
                                                             abs=0.2)
    surf = export.read_polydata(out / "vessels.vtp")
    assert sorted(set(vtk_to_numpy(surf.GetPointData().GetArray("tree")).tolist())) == [0, 1]


def test_seeds_in_one_structure_give_one_tree_as_before(tubes_file, tmp_path):
    out = tmp_path / "plan"
    assert cli.main(["vessels", "--cta", str(tubes_file), "--out", str(out),
                     _seed_arg((LEFT_X_MM, AXIS_Y_MM, 5.0)), _seed_arg((LEFT_X_MM, AXIS_Y_MM, 25.0))]) == 0
    rec = json.loads((out / "vessels.json").read_text())
    assert "trees" not in rec and "forest" not in rec
    cl = export.read_polydata(out / "centerline.vtp")
    assert cl.GetPointData().GetArray("tree") is None
    assert np.all(np.abs(vtk_to_numpy(cl.GetPoints().GetData())[:, 0] - LEFT_X_MM) < 1.0)


def test_a_seed_in_no_vessel_is_still_refused_and_nothing_is_written(tubes_file, tmp_path, capsys):
    out = tmp_path / "plan"
    rc = cli.main(["vessels", "--cta", str(tubes_file), "--out", str(out),
                   _seed_arg((LEFT_X_MM, AXIS_Y_MM, 15.0)), _seed_arg((20.0, 35.0, 15.0))])  # tissue, 15 mm from both
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert rc == 2 and err.startswith("guidewire3d: error: ") and "--seed-lps=20,35,15" in err
    assert not out.exists() and not list(tmp_path.glob(".plan*"))


def test_the_access_point_picks_which_tree_comes_first():
    vol = _two_tubes()
    access = np.array([LEFT_X_MM, AXIS_Y_MM, 0.5])  # the left tube's lower end
    plan = vesselplan.plan_vessels(vol, seeds_lps_mm=[[RIGHT_X_MM, AXIS_Y_MM, 15.0], [LEFT_X_MM, AXIS_Y_MM, 15.0]],
                                   access_lps_mm=access)
    assert len(plan.trees) == 2 and plan.seed_groups == ((1,), (0,))
    first = plan.trees[0].vessels.tree
    assert np.linalg.norm(first.points_lps_mm[first.root] - access) < 2.0
    assert np.all(np.abs(first.points_lps_mm[:, 0] - LEFT_X_MM) < 1.0)


def test_one_connected_tree_is_still_required_where_a_wire_is_reconstructed():
    from guidewire3d.cta import vessels3d
    with pytest.raises(SegmentationError, match="writes one tree per structure"):
        vessels3d.extract_vessels(_two_tubes(), seeds_lps_mm=[[LEFT_X_MM, AXIS_Y_MM, 15.0],
                                                              [RIGHT_X_MM, AXIS_Y_MM, 15.0]])
