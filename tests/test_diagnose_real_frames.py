"""The measurements of scripts/diagnose_real_frames.py (issue 17) against hand-built ground truth: the per-point
error of a 3D wire and its part along the beam, and the tree re-rooted where the wire enters."""
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from guidewire3d.geometry import CArm, nominal_pose
from guidewire3d.vesseltree import VesselTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))


def _straight_tree():
    """A trunk along L from (0, 0, 0) to (100, 0, 0) mm (radius 8 -> 4 mm, rooted at its wide end x = 0) and a
    branch of radius 2 mm from (50, 0, 0) to (50, 0, 40) (along S)."""
    x = np.arange(0.0, 101.0, 1.0)
    trunk = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    z = np.arange(0.0, 41.0, 1.0)
    branch = np.column_stack([np.full_like(z, 50.0), np.zeros_like(z), z])
    return VesselTree.from_polylines([trunk, branch], [np.linspace(8.0, 4.0, len(x)), np.full(len(z), 2.0)],
                                     [None, (0, 50)])


def test_point_errors_split_the_error_along_the_beam():
    from diagnose_real_frames import point_errors

    tree = _straight_tree()
    carm = CArm(30.0, 10.0, 1100.0, 750.0, 0.3, (512, 512))
    pose = nominal_pose(tree.centroid_lps_mm)
    true = np.column_stack([np.arange(0.0, 101.0), np.zeros(101), np.zeros(101)])  # the trunk
    beam_lps = pose.R.T @ carm.beam_direction
    side = np.cross(beam_lps, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)                                    # across both the beam and the wire
    deep = beam_lps - beam_lps[0] * np.array([1.0, 0.0, 0.0])
    deep /= np.linalg.norm(deep)                                    # across the wire, in the plane of the beam
    for shift, err, along in ((2.0 * deep, 2.0, 2.0 * float(deep @ beam_lps)), (1.5 * side, 1.5, 0.0)):
        wire = SimpleNamespace(points_lps_mm=true[10:90] + shift, uncertainty_mm=np.full(80, 0.5))
        pe = point_errors(carm, pose, wire, true, tree)
        assert pe["err"] == pytest.approx(np.full(80, err), abs=0.02)
        assert pe["along"] == pytest.approx(np.full(80, along), abs=0.02)
        assert np.all(np.isin(pe["rad"], tree.radius_mm)) and np.median(pe["rad"]) > 4.0  # the tree's radius there
        assert np.all(pe["unc"] == 0.5)                                                     # the wire's own sigma


def test_entry_rooted_puts_the_root_where_the_wire_enters():
    from diagnose_real_frames import entry_rooted

    tree = _straight_tree()
    wire = np.array([[99.3, 0.4, 0.0], [70.0, 0.0, 0.0], [50.0, 0.0, 20.0]])  # enters at the narrow end x = 100
    t2 = entry_rooted(tree, wire)
    assert np.allclose(t2.points_lps_mm[t2.root], [99.0, 0.0, 0.0])
    assert t2.n_points == tree.n_points and np.allclose(t2.radius_mm, tree.radius_mm)
    # a wire walking from its entry into the branch now walks away from the root all the way
    s = t2.arclength_from_root_mm
    on_wire = [int(np.argmin(np.linalg.norm(t2.points_lps_mm - p, axis=1))) for p in wire]
    assert np.all(np.diff(s[on_wire]) > 0)
