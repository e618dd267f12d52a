"""A path that reaches the tip's vessel by a skip (issue 20, ``bench_stress`` 7207 f3 and 7223 f3): between two
anchors near the tip, the tree route the path takes projects onto many px more than the 2D wire's step. Ground
truth: a trunk whose child branch turns back alongside it at another depth; the route excess of a path that
follows the wire and of one that jumps into the child, against the projected length of the route itself."""
from dataclasses import replace

import numpy as np
import pytest
from guidewire3d.geometry import fine_pixel_factor
from guidewire3d.live import session as live
from guidewire3d.live.session import Verdict, frame_verdict
from guidewire3d.reconstruction import (
    TIP_SKIP_NEAR_PX,
    ReconOptions,
    build_context,
    reconstruct_wire,
    route_excess_px,
    tip_skip_px,
)
from guidewire3d.vesseltree import VesselTree
from test_reconstruction import AP, _chain, _pose

GATE_PX = 20.0  # the limit the gate was measured with (``live.TIP_SKIP_MAX_PX``'s comment)

ROUTE_TOL_PX = 2.0      # the route's projected length from the dense tree against the polyline's (sampling, corners)
FOLLOWS_PX = 3.0        # a path that follows the wire: its steps' route excess stays within this (the pairwise
                        # cost's sigma_step_px; the tree points are 0.5 mm = 2.4 px apart here)
TIP_Z_MM = 10.0         # the wire's tip: 10 mm above the bifurcation, in the trunk
SKIP_Z_MM = 16.0        # the skipping path leaves the trunk for the turned-back child here (29 px before the tip)


def _turned_back_tree():
    """A trunk down -z to a bifurcation J at the origin; child A goes on down; child B turns back up alongside
    the trunk, 3 mm beside it across the AP beam and 5 mm deeper (``bench_stress`` 7207: a side branch that
    leaves the wire's vessel just beyond its tip and runs back over it in the image)."""
    trunk = _chain([0, 0, 60], [0, 0, 0])
    a = _chain([0, 0, 0], [0, 0, -40])
    b = _chain([0, 0, 0], [3, -5, -3], [3, -5, 40])
    tree = VesselTree.from_polylines([trunk, a, b], [np.full(len(trunk), 1.5), np.full(len(a), 1.5),
                                                     np.full(len(b), 1.2)],
                                     [None, (0, len(trunk) - 1), (0, len(trunk) - 1)])
    return tree


def _wire():
    """The wire in the trunk from z = 60 mm to its tip at ``TIP_Z_MM``, every 0.2 mm."""
    return _chain([0, 0, 60], [0, 0, TIP_Z_MM], step=0.2)


def _paths(ctx, W, uv, dp_px):
    """Anchors every ``dp_px`` of the 2D wire; the dense tree point of each along the trunk (the right path) and,
    below ``SKIP_Z_MM``, along the turned-back child B at the same height (a path that jumps into B)."""
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(uv, axis=0), axis=1))]
    aidx = np.unique(np.r_[np.searchsorted(arc, np.arange(0.0, arc[-1], dp_px)), len(uv) - 1])
    trunk = np.flatnonzero((np.abs(ctx.points[:, 0]) < 1e-6) & (ctx.points[:, 2] >= 0))
    in_b = np.flatnonzero(np.abs(ctx.points[:, 1] + 5.0) < 1e-6)
    right = np.array([trunk[np.argmin(np.abs(ctx.points[trunk, 2] - W[i, 2]))] for i in aidx])
    skip = np.array([right[k] if W[i, 2] > SKIP_Z_MM else in_b[np.argmin(np.abs(ctx.points[in_b, 2] - W[i, 2]))]
                     for k, i in enumerate(aidx)])
    return aidx, arc, right, skip


def test_route_excess_of_a_path_that_follows_the_wire_and_of_one_that_skips():
    """Ground truth: the path along the trunk follows the wire (every step's route excess ~0); the path that
    jumps into B at ``SKIP_Z_MM`` takes, for one step, the route down the trunk to J and back up B, whose
    projection is ~2 x 16 mm long where the wire moves one anchor step. Its excess is that route's own projected
    length (the polyline's) minus the wire's step; ``tip_skip_px`` finds it within ``TIP_SKIP_NEAR_PX`` of the tip,
    where it lies."""
    tree = _turned_back_tree()
    pose = _pose(tree)
    ctx = build_context(pose, AP, tree)
    W = _wire()
    uv = AP.project(W, pose)
    dp_px = ReconOptions().dp_step_px
    aidx, arc, right, skip = _paths(ctx, W, uv, dp_px)
    ex_right = route_excess_px(ctx, right, arc[aidx])
    assert np.abs(ex_right).max() < FOLLOWS_PX
    ex_skip = route_excess_px(ctx, skip, arc[aidx])
    k = int(np.argmax(ex_skip))
    # the route of that step, as a polyline: from the trunk point down to J, out to B's bend and up B
    za, zb = ctx.points[skip[k], 2], ctx.points[skip[k + 1], 2]
    route = np.array([[0, 0, za], [0, 0, 0], [3, -5, -3], [3, -5, zb]])
    truth_px = float(np.linalg.norm(np.diff(AP.project(route, pose), axis=0), axis=1).sum()) - (arc[aidx[k + 1]]
                                                                                                  - arc[aidx[k]])
    assert ex_skip[k] == pytest.approx(truth_px, abs=ROUTE_TOL_PX)
    assert ex_skip[k] > 4 * GATE_PX          # far beyond a bifurcation's few px
    others = np.delete(ex_skip, k)
    assert np.abs(others).max() < FOLLOWS_PX            # before and after the jump both follow the wire
    factor = fine_pixel_factor(AP.pixel_at_iso_mm)
    px, from_tip = tip_skip_px(ctx, skip, arc[aidx], float(arc[-1]))
    assert px == pytest.approx(ex_skip[k] / factor)
    assert from_tip == pytest.approx((arc[-1] - arc[aidx[k + 1]]) / factor)
    assert from_tip <= TIP_SKIP_NEAR_PX
    assert tip_skip_px(ctx, right, arc[aidx], float(arc[-1]))[0] < FOLLOWS_PX


def test_a_skip_far_from_the_tip_is_not_the_tips():
    """The same jump with the wire going on 60 mm further along B: the skip now lies more than
    ``TIP_SKIP_NEAR_PX`` before the tip, and ``tip_skip_px`` does not count it (the wire's long distal part on B
    is the evidence for B)."""
    tree = _turned_back_tree()
    pose = _pose(tree)
    ctx = build_context(pose, AP, tree)
    W = _wire()
    uv = AP.project(W, pose)
    aidx, arc, _, skip = _paths(ctx, W, uv, ReconOptions().dp_step_px)
    far = np.asarray(arc[-1] + TIP_SKIP_NEAR_PX * fine_pixel_factor(AP.pixel_at_iso_mm) + 20.0)
    # the wire's tip moved on past the skip by more than the tip's region: the same anchors, a longer wire
    px_far, _ = tip_skip_px(ctx, skip, arc[aidx], float(far))
    assert px_far < FOLLOWS_PX


def test_the_reconstruction_reports_no_skip_on_a_wire_it_follows_and_the_verdict_reads_it(monkeypatch):
    """The reconstruction of the exact wire (its tip 10 mm before J, B turned back over it) follows the trunk: its
    tip within 1 mm, no skip, ``ok``. With the gate set (``TIP_SKIP_MAX_PX``, off by default: measured, not gated),
    the same wire with a skip beyond it (as the path that jumps into B measures it) is ``uncertain`` for that reason
    alone, and one just below the limit stays ``ok``; without the gate both stay ``ok``."""
    tree = _turned_back_tree()
    pose = _pose(tree)
    W = _wire()
    uv = AP.project(W, pose)
    w = reconstruct_wire(uv, pose, AP, tree)
    assert w.success
    assert np.linalg.norm(w.points_lps_mm[-1] - W[-1]) < 1.0
    assert w.tip_skip_px < FOLLOWS_PX
    assert frame_verdict(w, uv, None)[0] is Verdict.OK
    assert frame_verdict(replace(w, tip_skip_px=4 * GATE_PX, tip_skip_from_tip_px=15.0), uv, None)[0] is Verdict.OK
    monkeypatch.setattr(live, "TIP_SKIP_MAX_PX", GATE_PX)
    skipped = replace(w, tip_skip_px=live.TIP_SKIP_MAX_PX + 1.0, tip_skip_from_tip_px=15.0)
    verdict, why = frame_verdict(skipped, uv, None)
    assert verdict is Verdict.UNCERTAIN
    assert why.startswith("tip uncertain: the path through the vessel tree reaches the tip's vessel by a skip")
    assert len(why.split("; ")) == 1
    assert frame_verdict(replace(w, tip_skip_px=live.TIP_SKIP_MAX_PX - 1.0, tip_skip_from_tip_px=15.0), uv,
                         None)[0] is Verdict.OK
    d = skipped.to_dict()
    assert d["tip_skip_px"] == pytest.approx(live.TIP_SKIP_MAX_PX + 1.0)
    assert d["tip_skip_from_tip_px"] == pytest.approx(15.0)
