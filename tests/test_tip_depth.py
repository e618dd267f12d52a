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


@pytest.fixture(scope="module")
def bcase():
    return simulate(PhantomOptions(seed=1, n_frames=3, biplane=True), make_ct=False)


def _visible(case, t):
    """Frame t's true 2D wires in view, at 1 px (the spacing of an ordered wire)."""
    ua, ub = case.wire_uv_px[t], case.heldout_wire_uv_px[t]
    return (resample_polyline(ua[case.carm.in_image(ua)], 1.0),
            resample_polyline(ub[case.heldout_carm.in_image(ub)], 1.0))


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
