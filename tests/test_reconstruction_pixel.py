"""The single-view reconstruction on a finer detector: the same anatomy, the same answer.

The reconstruction's options in pixels (``context.PIXEL_OPTIONS``: the Viterbi's anchor step, its
sigmas, the tree's candidate spacing, the spline's knots, the paper's geometric uncertainty) were
tuned on images whose pixel at the isocentre is about ``REFERENCE_PIXEL_AT_ISO_MM``. On a finer
detector (a 1024 px panel: 0.09-0.12 mm) the same registration error in mm spans twice the pixels and
there are twice the anchors: the path costs doubled or more, and the branch check (an absolute extra
cost, ``live.session.BRANCH_EXTRA_MAX``) no longer saw an equally good path through another branch.
``bench_stress --draws wide`` 5201 f0 and 6002 f0 (1024 px) were ``ok`` with their tips 11.9 and 9.1 mm
off in a vessel that overlaps the true one in projection. The options are now widened to their size
in mm at the reference (``context.options_at_pixel``).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from guidewire3d.geometry import CArm, Pose
from guidewire3d.live import session as live
from guidewire3d.metrics import resample_polyline
from guidewire3d.reconstruction import ReconOptions, reconstruct_wire
from guidewire3d.reconstruction import context
from guidewire3d.registration import Verdict
from guidewire3d.vesseltree import VesselTree
from scipy.spatial import cKDTree
from test_reconstruction import _overlap_tree, _pose, _wire_on

TIP_OFF_MM = 5.0   # bench_stress: an ok frame whose tip is farther than this from the true tip is wrong


def _views():
    """The same C-arm at the reference pixel (512 px) and at half of it (1024 px, the same field)."""
    px = context.REFERENCE_PIXEL_AT_ISO_MM * 1000.0 / 700.0
    return CArm(0.0, 0.0, 1000.0, 700.0, px, (512, 512)), CArm(0.0, 0.0, 1000.0, 700.0, px / 2, (1024, 1024))


def test_options_widen_only_on_a_finer_detector():
    opt = ReconOptions()
    coarse, fine = _views()
    assert context.options_at_pixel(opt, coarse.pixel_at_iso_mm) is opt
    assert context.options_at_pixel(opt, 2 * coarse.pixel_at_iso_mm) is opt
    wide = context.options_at_pixel(opt, fine.pixel_at_iso_mm)
    for name in context.PIXEL_OPTIONS:
        np.testing.assert_allclose(getattr(wide, name), 2 * getattr(opt, name))
    assert wide.sigma_jump_mm == opt.sigma_jump_mm and wide.skip_cost == opt.skip_cost  # mm and costs stay


def test_a_finer_detector_gives_the_same_wire_costs_and_uncertainty():
    """A wire 30 mm into A of two branches that overlap in projection for 20 mm, seen by the same C-arm
    at 512 and 1024 px (a pose 0.7 mm off, as a registration leaves it): the 3D wires agree to 0.1 mm,
    and the path through B costs the same extra (on the old code 1.7 x at 1024 px: 154 against 91) and
    the tip's 1-sigma is the same."""
    tree, _ = _overlap_tree()
    leaf_a = tree.branches[1].point_ids[-1]
    W, _ = _wire_on(tree, leaf_a)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(W, axis=0), axis=1))]
    W = W[s <= 70.0]
    pose = _pose(tree)
    off = np.eye(4)
    off[:3, 3] = [0.6, 0.0, -0.4]
    seen = Pose.from_matrix(pose.matrix @ off)               # the frame, as the true pose renders it
    out = []
    for carm in _views():
        uv = resample_polyline(carm.project(W, seen), 1.0)
        w = reconstruct_wire(uv, pose, carm, tree)
        assert w.success and np.linalg.norm(w.points_lps_mm[-1] - W[-1]) < 1.5
        out.append(w)
    coarse, fine = out
    a = resample_polyline(coarse.points_lps_mm, 0.5)
    b = resample_polyline(fine.points_lps_mm, 0.5)
    assert min(len(a), len(b)) > 10 and cKDTree(b).query(a)[0].mean() < 0.1
    assert abs(fine.branch_extra_cost - coarse.branch_extra_cost) < 0.1 * coarse.branch_extra_cost, \
        (coarse.branch_extra_cost, fine.branch_extra_cost)
    assert abs(fine.uncertainty_mm[-1] - coarse.uncertainty_mm[-1]) < 0.05 * coarse.uncertainty_mm[-1]


def test_a_1024_px_frame_whose_tip_lies_in_an_overlapping_vessel_is_not_ok():
    """bench_stress --draws wide 5201 f0 (1024 px, low dose) and 6002 f0 (1024 px, breathing 20 mm,
    distractors, the large CT): the 2D trace is right to its tip, but the wire's last 10 mm project onto
    another branch at another depth, and the path took that branch. Both were ``ok`` with their tips
    11.9 and 9.1 mm off (extra cost of the right path 8.7 and 7.0, above the limit 4). The fixture holds
    the reconstruction's inputs as the live session gave them (its tree, view, pose and covariance, the
    2D wire, the root's pixel) and the true wire; recorded from the kept cases."""
    d = np.load(Path(__file__).parent / "data" / "recon_finepixel.npz")
    for seed in ("5201", "6002"):
        k = f"s{seed}_"
        tree = VesselTree(d[k + "tree_points_lps_mm"].astype(float), d[k + "tree_radius_mm"].astype(float),
                          d[k + "tree_parent"])
        carm = CArm.from_dict(json.loads(str(d[k + "carm_json"])))
        assert carm.shape == (1024, 1024) and carm.pixel_at_iso_mm < context.REFERENCE_PIXEL_AT_ISO_MM
        uv = d[k + "wire_uv_px"].astype(float)
        w = reconstruct_wire(uv, Pose.from_matrix(d[k + "pose"]), carm, tree,
                             registration_covariance=d[k + "covariance"])
        assert w.success
        verdict, why = live.frame_verdict(w, uv, live.orientation_of(w, uv, root_uv_px=d[k + "root_uv_px"]),
                                          image_shape=carm.shape)
        tip_off_mm = float(np.linalg.norm(w.points_lps_mm[-1] - d[k + "true_tip_lps_mm"]))
        assert verdict is not Verdict.OK or tip_off_mm <= TIP_OFF_MM, (seed, tip_off_mm, why)
