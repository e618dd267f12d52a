"""The image beyond the traced tip (``live.continuation``): a wire that the trace lost over its
distal part is seen going on along the vessel, and a frame traced to its real tip is not flagged."""
import numpy as np
import pytest
from guidewire3d.geometry import CArm, Pose
from guidewire3d.live import continuation as C
from guidewire3d.live import session as live
from guidewire3d.phantom import PhantomOptions, simulate
from guidewire3d.registration import Verdict
from guidewire3d.vesseltree import VesselTree


def _straight_case(dark_beyond: bool, seed: int = 0):
    """A straight vessel across the image, a wire drawn along its first 60 % and, optionally, on to
    its end: the trace is the first 60 % (up to tree point ``tip``)."""
    carm = CArm(0.0, 0.0, 1000.0, 700.0, 0.3, (256, 256))
    pts = np.stack([np.linspace(-40, 40, 161), np.zeros(161), np.zeros(161)], axis=1)
    tree = VesselTree(pts, np.full(161, 1.5), np.arange(-1, 160))
    pose = Pose.identity()
    uv = np.asarray(carm.project(pts, pose))
    tip = 96
    rng = np.random.default_rng(seed)
    img = 1000.0 + 8.0 * rng.standard_normal((256, 256))
    vv, uu = np.mgrid[0:256, 0:256]
    end = len(uv) if dark_beyond else tip + 1
    line = np.asarray(uv[:end])
    # a 1.5 px wide dark line, 40 units deep, along the drawn part
    d = np.min(np.hypot(uu[..., None] - line[None, None, :, 0], vv[..., None] - line[None, None, :, 1]), axis=-1)
    img -= 40.0 * np.exp(-0.5 * (d / 0.75) ** 2)
    return img, tree, carm, pose, tip, uv[:tip + 1]


def test_a_dark_line_beyond_the_tip_is_seen():
    img, tree, carm, pose, tip, wire = _straight_case(True)
    c = C.wire_continuation(img, tree, carm, pose, tip, wire)
    assert c is not None and c.wire_goes_on, c
    assert c.contrast_ratio > 0.8 and c.length_px >= C.MIN_SAMPLES
    assert "continues along the vessel" in c.explain()


def test_no_line_beyond_the_tip_is_not_flagged():
    img, tree, carm, pose, tip, wire = _straight_case(False)
    c = C.wire_continuation(img, tree, carm, pose, tip, wire)
    assert c is not None and not c.wire_goes_on, c
    assert abs(c.contrast_ratio) < 0.3


def test_a_tip_at_a_leaf_has_nothing_to_measure():
    img, tree, carm, pose, tip, wire = _straight_case(False)
    assert C.wire_continuation(img, tree, carm, pose, tree.n_points - 1, wire) is None


@pytest.mark.parametrize("seed", [3, 11])
def test_a_trace_cut_short_on_a_simulated_frame_is_uncertain(seed):
    """Ground truth: the simulator's visible wire, projected, traced to its real tip is ``ok``;
    the same trace without its distal 40 % is made uncertain by what the image shows beyond it."""
    case = simulate(PhantomOptions(seed=seed, n_frames=1), make_ct=False)
    vis = np.asarray(case.wire_visible[0], bool)
    uv = np.asarray(case.carm.project(np.asarray(case.wire_lps_mm[0])[vis], case.pose))
    frame = np.asarray(case.frames[0])
    whole = live.Session(case.tree, case.carm, case.pose).process_wire(uv, image=frame)
    assert whole.verdict is Verdict.OK, whole.message
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(uv, axis=0), axis=1))])
    cut = uv[s <= 0.6 * s[-1]]
    short = live.Session(case.tree, case.carm, case.pose).process_wire(cut, image=frame)
    assert short.verdict is Verdict.UNCERTAIN, short.message
    assert "continues along the vessel" in short.message
