"""Never silently wrong: a frame whose wire leaves the path of the previous ``ok`` frame.

A wire advances and retracts along one path through the vessels. When the reconstruction drops the
previous frame's path as its prior (``Wire3D.prior_dropped``: the wire fits another path much better),
either that frame, this one or the pose they share is wrong. ``bench_stress`` 6104 f2 (rigid motion
10 mm, no catheter): the tracked pose drifted 5 mm off, the path switched branch and the tip was put
9.8 mm off, reported ``ok`` right after an ``ok`` frame. Such a frame is now ``uncertain`` ("path
changed"); after a frame that was not ``ok`` a change of path is the expected correction.
"""
from __future__ import annotations

import numpy as np
from guidewire3d.live import session as live
from guidewire3d.metrics import resample_polyline
from guidewire3d.registration import Verdict
from test_reconstruction import AP, _overlap_tree, _pose, _wire_on


def _two_wires():
    tree, _ = _overlap_tree()
    pose = _pose(tree)
    uv = {}
    for name, b in (("A", 1), ("B", 2)):
        W, _ = _wire_on(tree, tree.branches[b].point_ids[-1])
        uv[name] = resample_polyline(AP.project(W, pose), 1.0)
    return tree, pose, uv


def test_a_wire_that_leaves_the_previous_ok_path_is_uncertain():
    tree, pose, uv = _two_wires()
    s = live.Session(tree, AP, pose)
    first = s.process_wire(uv["A"])
    assert first.verdict is Verdict.OK, first.message
    second = s.process_wire(uv["B"])          # the same tree and pose; the wire now in B, which diverges from A
    assert second.wire3d.prior_dropped
    tip_b = tree.points_lps_mm[tree.branches[2].point_ids[-1]]
    assert np.linalg.norm(second.wire3d.points_lps_mm[-1] - tip_b) < 2.0     # B's wire is put in B ...
    assert second.verdict is Verdict.UNCERTAIN and "path changed" in second.message   # ... but it is not ok
    third = s.process_wire(uv["B"])           # the new path, now the prior, is kept: ok again
    assert not third.wire3d.prior_dropped and third.verdict is Verdict.OK, third.message


def test_a_path_change_after_a_frame_that_was_not_ok_is_the_correction():
    tree, pose, uv = _two_wires()
    s = live.Session(tree, AP, pose)
    s.process_wire(uv["A"])
    second = s.process_wire(uv["B"])
    assert second.wire3d.prior_dropped
    verdict, why = live.frame_verdict(second.wire3d, uv["B"], second.orientation, prior_was_ok=False)
    assert verdict is Verdict.OK, why         # the previous frame not ok: the change of path is no doubt
    s.reset()                                 # a reset forgets the prior
    assert not s.process_wire(uv["A"]).wire3d.prior_dropped
