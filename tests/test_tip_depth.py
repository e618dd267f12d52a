"""Never silently wrong (issue 20): the tip's depth, and the two-view path's tip-end check.

* A biplane pair whose plane-A trace runs on past the wire's end along its vessel (a false stretch
  of the segmenter's mask, as at a low dose): the two-view wire takes the stretch from plane A alone
  (``triangulation.extend_distal``) and its tip lies mm beyond the true one. The one-view path's
  bare-tip check (``orderedwire.tip_end_check``: the trace's last px barely darker than the
  background) now runs in the two-view path too, and the pair is ``uncertain``; before it ran only
  the two-layer check, and the pair was ``ok`` with its tip off.
"""
from __future__ import annotations

import numpy as np
import pytest
from guidewire3d import metrics
from guidewire3d.app import biplane
from guidewire3d.metrics import resample_polyline
from guidewire3d.phantom import PhantomOptions, simulate
from guidewire3d.registration import Verdict

TIP_OFF_MM = 5.0   # bench_stress: an ok frame whose tip is farther than this from the true tip is wrong
PAST_PX = 30.0     # how far the false stretch runs on past the wire's end, along its vessel


from test_tip_along_beam import _visible, bcase  # noqa: E402,F401  (the biplane case of seed 1, its true wires)


def _past_the_end(case, t, ua):
    """Plane A's 2D wire continued ``PAST_PX`` px along its vessel beyond the true tip (the wire's tree
    path beyond the tip, projected), at 1 px."""
    path = case.tree.points_lps_mm[np.asarray(case.wire_path_point_ids)]
    tip = case.wire_lps_mm[t][-1]
    k = int(np.argmin(np.linalg.norm(path - tip, axis=1)))
    ahead = case.carm.project(np.vstack([tip, path[k + 1:]]), case.pose)
    ahead = resample_polyline(ahead, 1.0)[1: int(PAST_PX) + 1]
    return np.vstack([ua, ahead])


def test_a_biplane_trace_past_the_wire_end_is_uncertain(bcase):
    """The true 2D wires of a pair: ``ok`` and the tip right; plane A's wire run on ``PAST_PX`` px
    along the vessel past the wire's end: the two-view tip follows it (more than ``TIP_OFF_MM`` off)
    and the pair is ``uncertain``, the bare tip named."""
    s = biplane.BiplaneSession(bcase.tree, (bcase.carm, bcase.heldout_carm), bcase.pose, threads=1)
    t = 2
    ua, ub = _visible(bcase, t)
    imgs = (bcase.frames[t], bcase.heldout_frames[t])
    truth = bcase.wire_lps_mm[t][np.asarray(bcase.wire_visible[t], bool)]
    clean = s.process_wires(ua, ub, images=imgs, index=t)
    assert clean.views == "AB" and clean.result.verdict is Verdict.OK, clean.result.message
    assert metrics.wire_errors_mm(clean.result.wire3d.points_lps_mm, truth)["tip_error_mm"] < 2.0
    past = s.process_wires(_past_the_end(bcase, t, ua), ub, images=imgs, index=t)
    assert past.views == "AB"
    assert metrics.wire_errors_mm(past.result.wire3d.points_lps_mm, truth)["tip_error_mm"] > TIP_OFF_MM
    assert past.result.verdict is Verdict.UNCERTAIN, past.result.message
    assert "tip uncertain: the trace's last" in past.result.message


# --------------------------------------------------------------------------------------
# the tip's depth: another vessel that projects onto the 2D tip, and a prior that did not settle
# --------------------------------------------------------------------------------------
from guidewire3d.live import session as live  # noqa: E402
from guidewire3d.reconstruction import ReconOptions, WireTracker, reconstruct_wire  # noqa: E402
from guidewire3d.reconstruction import path as recon_path  # noqa: E402
from guidewire3d.reconstruction.context import build_context  # noqa: E402
from test_reconstruction import AP, _overlap_tree, _pose, _wire_on  # noqa: E402

DEPTH_TOL_MM = 2.0        # the rival's depth against the geometry's (perspective, the tree's sampling)


def _overlap_wires():
    """The overlap tree, its pose, the true 3D wire along A, and its 2D wire cut inside the overlap
    (``broken``: its tip could as well be in B) and whole (it leaves the overlap on A)."""
    tree, _ = _overlap_tree()
    pose = _pose(tree)
    W, _ = _wire_on(tree, int(tree.leaves[0]))
    uv = AP.project(W, pose)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(W, axis=0), axis=1))]
    keep = s < 40.0 + 15.0
    return tree, pose, W[keep], uv[keep], uv


def test_the_tip_rival_is_the_other_vessel_at_the_tips_depth():
    """At the tip of a wire cut inside the overlap, a path ending in B (the mirror image of A in
    depth, ``y -> -y``: 2 |y| deeper along about the same ray) costs about nothing more:
    ``tip_rival`` finds it there, and the verdict names the branch ambiguity; at the tip of the
    whole wire (A has left B behind in projection) there is none."""
    tree, pose, W, broken_uv, full_uv = _overlap_wires()
    opt = ReconOptions(ambiguity_scale=0.0)
    ctx = build_context(pose, AP, tree, options=opt)
    for uv, rival in ((broken_uv, True), (full_uv, False)):
        from guidewire3d.reconstruction.candidates import anchor_indices, tree_candidates
        aidx = anchor_indices(uv, opt.dp_step_px)
        cand, outside = tree_candidates(ctx, uv[aidx], opt)
        has = (cand >= 0).any(axis=1)
        costs = recon_path.viterbi_costs(ctx, uv[aidx][has], cand[has], outside[has], opt, None)
        nodes, total, _ = recon_path.viterbi_path(ctx, uv[aidx][has], cand[has], outside[has], opt, None, costs=costs)
        extra, shift = recon_path.tip_rival(ctx, costs, nodes, opt)
        if rival:
            assert extra < 1.0 and shift == pytest.approx(2.0 * abs(W[-1][1]), abs=DEPTH_TOL_MM)
            assert shift > live.BRANCH_SHIFT_MIN_MM
        else:
            assert not extra < 10 * live.BRANCH_EXTRA_MAX
    broken = reconstruct_wire(broken_uv, pose, AP, tree, options=opt)
    verdict, why = live.frame_verdict(broken, broken_uv, None)
    assert verdict is Verdict.UNCERTAIN and "branch ambiguous" in why


def test_a_previous_frame_that_did_not_settle_its_branch_is_no_prior():
    """A frame whose tip could as well be in B (a rival path as good, ending 24 mm away) gives the
    next frame no tracking prior; a frame whose wire settled its branch (the whole wire on A) does."""
    tree, pose, W, broken_uv, full_uv = _overlap_wires()
    opt = ReconOptions(ambiguity_scale=0.0)
    ctx = build_context(pose, AP, tree, options=opt)
    broken = reconstruct_wire(broken_uv, pose, AP, tree, options=opt)
    full = reconstruct_wire(full_uv, pose, AP, tree, options=opt)
    assert broken.branch_extra_cost < live.BRANCH_EXTRA_MAX < full.branch_extra_cost
    assert recon_path.tracking_tip(ctx, broken) is None
    assert recon_path.tracking_tip(ctx, full) is not None
    tracker = WireTracker(pose, AP, tree, options=opt)
    assert tracker.update(broken_uv)
    again = tracker.update(broken_uv)           # the same wire again: still not settled, still said
    assert live.frame_verdict(again, broken_uv, None)[0] is Verdict.UNCERTAIN


def test_a_coin_toss_is_not_carried_on_by_the_tracking_prior():
    """Simulator truth, ``PhantomOptions(seed=113, n_frames=4)`` at the true pose: frame 1's tip could
    be in either of two branches (``uncertain``, and it took the wrong one); before, its path held
    frame 2 in that branch as a prior, and frame 2 was ``ok`` with its tip 18.8 mm off. No frame is
    ``ok`` with its tip more than ``TIP_OFF_MM`` off now, and frames 0 and 3 stay ``ok`` and right."""
    case = simulate(PhantomOptions(seed=113, n_frames=4), make_ct=False)
    session = live.Session(case.tree, case.carm, case.pose)
    for t, frame in enumerate(case.frames):
        fr = session.process(frame)
        vis = np.asarray(case.wire_visible[t], bool)
        tip_mm = float(np.linalg.norm(fr.tip_lps_mm - case.wire_lps_mm[t][vis][-1]))
        assert not (fr.verdict is Verdict.OK and tip_mm > TIP_OFF_MM), (t, tip_mm, fr.message)
        if t in (0, 3):
            assert fr.verdict is Verdict.OK and tip_mm < 2.0, (t, tip_mm, fr.message)


A_OFFSET_MM = 2.0  # branch A runs this far beside B in projection (z), B's wire 0.5 mm outside A's lumen


def _cut_overlap_tree(cut_mm: float):
    """Like ``_overlap_tree`` (branches A and B at depths y = +12 and -12 mm), with A moved
    ``A_OFFSET_MM`` aside in the image (a wire in B lies just outside A's projected lumen: B explains
    it better) and B cut ``cut_mm`` along from the bifurcation (a CTA tree that lost B's distal
    part). Returns the tree and B's whole polyline with the trunk (where the vessel really runs)."""
    from guidewire3d.vesseltree import VesselTree
    from test_reconstruction import _chain
    trunk = _chain([0, 0, 40], [0, 0, 0])
    a = _chain([0, 0, 0], [5, 3, A_OFFSET_MM], [20, 12, A_OFFSET_MM], [35, 12, 12])
    b = _chain([0, 0, 0], [20, -12, 0], [35, -12, -12])
    sb = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(b, axis=0), axis=1))]
    n_b = int((sb <= cut_mm).sum())
    tree = VesselTree.from_polylines([trunk, a, b[:n_b]],
                                     [np.full(len(trunk), 3.0), np.full(len(a), 1.5), np.full(n_b, 1.5)],
                                     [None, (0, len(trunk) - 1), (0, len(trunk) - 1)])
    return tree, np.vstack([trunk, b[1:]])


def assert_a_rival_flags_the_wrong_tip(tree, W, monkeypatch, constant: str, off_value):
    """The wire ``W`` reconstructed in ``tree`` has its tip more than ``TIP_OFF_MM`` off (the truth), the
    frame is ``uncertain`` (branch ambiguous, a rival within ``BRANCH_EXTRA_MAX`` ending more than
    ``BRANCH_SHIFT_MIN_MM`` away), and with ``path.<constant>`` set to ``off_value`` (that rival off) it
    was ``ok``: silently wrong. Returns ``(pose, uv, options)``."""
    pose = _pose(tree)
    uv = AP.project(W, pose)
    opt = ReconOptions()
    w3 = reconstruct_wire(uv, pose, AP, tree, options=opt)
    assert w3.success and np.linalg.norm(w3.points_lps_mm[-1] - W[-1]) > TIP_OFF_MM   # the truth: the tip is wrong
    verdict, why = live.frame_verdict(w3, uv, None)
    assert verdict is Verdict.UNCERTAIN and "branch ambiguous" in why, why
    assert w3.branch_extra_cost < live.BRANCH_EXTRA_MAX and w3.branch_tip_shift_mm > live.BRANCH_SHIFT_MIN_MM
    with monkeypatch.context() as m:
        m.setattr(recon_path, constant, off_value)                           # without the rival: silently wrong
        assert live.frame_verdict(reconstruct_wire(uv, pose, AP, tree, options=opt), uv, None)[0] is Verdict.OK
    return pose, uv, opt


def test_a_tip_beyond_the_end_of_its_vessel_in_the_tree_is_uncertain(monkeypatch):
    """The wire runs down the trunk into B, 19 mm along it; the tree has lost B beyond 15 mm (its
    distal part, as a CTA extraction does), and A projects beside B, 2|y| mm away in depth. The only
    path that reaches the 2D tip is A's: the tip is put there, about 20 mm off. B explains the wire
    as well up to its end in the tree, 4 mm before the tip (``tree_end_rival``): the frame is
    ``uncertain``, not ``ok`` (it was ``ok`` without that rival)."""
    tree, b_full = _cut_overlap_tree(15.0)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(b_full, axis=0), axis=1))]
    W = resample_polyline(b_full[s <= 40.0 + 19.0], 0.2)           # the trunk and 19 mm of B
    pose, uv, opt = assert_a_rival_flags_the_wrong_tip(tree, W, monkeypatch, "TREE_END_MAX_PX", 0.0)
    whole, _ = _cut_overlap_tree(100.0)                                  # the whole tree: B reaches the tip
    right = reconstruct_wire(uv, pose, AP, whole, options=opt)
    assert np.linalg.norm(right.points_lps_mm[-1] - W[-1]) < 2.0
