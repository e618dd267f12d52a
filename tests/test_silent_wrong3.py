"""Never silently wrong (issue 20): a CTA tree that joins touching vessels at the wrong place.

Where two vessels touch, their segmented lumens merge and the centerline extraction joins them at
one place or another. In ``bench_stress`` 3914 f5/f6 the tree cut the wire's vessel where it touched
another one and joined its distal part to that other vessel, 130 mm round through the tree; the
wire's path had to jump there, and the Viterbi took a connected vessel that overlaps the distal part
in projection at another depth instead: the tip 13-16 mm off, reported ``ok``. The branch check now
counts the path that crosses where two lumens touch as a rival (``path.touching_rival``).
"""
from __future__ import annotations

import numpy as np
from guidewire3d.live import session as live
from guidewire3d.metrics import resample_polyline
from guidewire3d.reconstruction import ReconOptions, reconstruct_wire
from guidewire3d.reconstruction import path as recon_path
from guidewire3d.registration import Verdict
from guidewire3d.vesseltree import VesselTree
from test_reconstruction import AP, _chain, _pose
from test_tip_depth import assert_a_rival_flags_the_wrong_tip

TIP_OFF_MM = 5.0   # bench_stress: an ok frame whose tip is farther than this from the true tip is wrong
GAP_MM = 1.5       # the tree's cut: the wire's vessel ends this far from where the other vessel passes


def _miswired_tree():
    """A trunk down -z, then A (to depth y = +12) which really goes on up to ``[35, 12, 12]``. The tree
    has A stop at ``[20, 12, 0]``; its distal part belongs to C instead, a vessel from the trunk's top
    that comes up from below and passes ``GAP_MM`` from A's end (the lumens, 2 mm in radius, touch).
    B goes on from A's end and projects onto A's distal part at another depth (y = -4 at its end).
    Returns the tree and the true wire (trunk, A and its distal part)."""
    trunk = _chain([0, 0, 40], [0, 0, 0])
    a = _chain([0, 0, 0], [20, 12, 0])
    b = _chain([20, 12, 0], [35, -4, 12])
    c = _chain([0, 0, 40], [-20, 30, 40], [-20, 30, -20], [20, 12, -20], [20, 12, -GAP_MM], [35, 12, 12])
    tree = VesselTree.from_polylines(
        [trunk, a, b, c], [np.full(len(trunk), 3.0), np.full(len(a), 2.0), np.full(len(b), 2.0), np.full(len(c), 2.0)],
        [None, (0, len(trunk) - 1), (1, len(a) - 1), (0, 0)])
    wire = resample_polyline(np.vstack([trunk, a[1:], _chain([20, 12, 0], [20, 12, -GAP_MM], [35, 12, 12])[1:]]), 0.2)
    return tree, wire


def test_a_wire_going_on_where_the_tree_joined_its_vessel_elsewhere_is_uncertain(monkeypatch):
    """The true wire runs into A's distal part, which the tree joined to C. The chosen path goes on
    into B, which projects onto it (the truth: the tip more than ``TIP_OFF_MM`` off). Crossing from
    A's end into C where the lumens touch explains the wire as well: the frame is ``uncertain``
    (branch ambiguous, the rival ending more than 5 mm away); without that rival it was ``ok``."""
    tree, W = _miswired_tree()
    assert_a_rival_flags_the_wrong_tip(tree, W, monkeypatch, "TOUCH_GEODESIC_MM", np.inf)


def test_no_rival_where_a_touching_vessel_does_not_explain_the_wire():
    """The tree right (A goes on to ``[35, 12, 12]``, no B), and C coming up from below to end where
    its lumen touches A's: a path may cross into C there, but C runs away from the rest of the 2D
    wire. The tip is right, the frame ``ok``, and the crossing is no rival (it costs far more)."""
    trunk = _chain([0, 0, 40], [0, 0, 0])
    a = _chain([0, 0, 0], [20, 12, 0], [20, 12, -GAP_MM], [35, 12, 12])
    c = _chain([0, 0, 40], [-20, 30, 40], [-20, 30, -20], [20, 12, -20], [20, 12, -2 * GAP_MM])
    tree = VesselTree.from_polylines([trunk, a, c], [np.full(len(trunk), 3.0), np.full(len(a), 2.0), np.full(len(c), 2.0)],
                                     [None, (0, len(trunk) - 1), (0, 0)])
    W = resample_polyline(np.vstack([trunk, a[1:]]), 0.2)
    pose = _pose(tree)
    uv = AP.project(W, pose)
    opt = ReconOptions()
    w3 = reconstruct_wire(uv, pose, AP, tree, options=opt)
    assert np.linalg.norm(w3.points_lps_mm[-1] - W[-1]) < 2.0
    assert live.frame_verdict(w3, uv, None)[0] is Verdict.OK, live.frame_verdict(w3, uv, None)[1]
    from guidewire3d.reconstruction.candidates import anchor_indices, tree_candidates
    from guidewire3d.reconstruction.context import build_context
    ctx = build_context(pose, AP, tree, options=opt)
    aidx = anchor_indices(uv, opt.dp_step_px)
    cand, outside = tree_candidates(ctx, uv[aidx], opt)
    costs = recon_path.viterbi_costs(ctx, uv[aidx], cand, outside, opt, None)
    nodes, _, _ = recon_path.viterbi_path(ctx, uv[aidx], cand, outside, opt, None, costs=costs)
    extra, _ = recon_path.touching_rival(ctx, costs, nodes, opt)
    assert not extra < 10 * live.BRANCH_EXTRA_MAX, extra
