"""Two layers of wire at the traced tip (issue 20, item 3): a wire that bends back over itself just
before its tip projects its distal part onto the part before it; the mask holds one line, the
trace stops at the bend, and the true tip lies back along the traced wire. ``tip_darkness``
measures the line's darkness at the tip against the wire's own, and the frame's verdict is
``uncertain`` when the tip is about twice as dark."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from guidewire3d.live import session as live
from guidewire3d.metrics import resample_polyline
from guidewire3d.registration import Verdict
from guidewire3d.xray.orderedwire import (BARE_END_RATIO, DOUBLED_END_RATIO, END_WINDOW_PX, BareTip, DoubledTip,
                                          doubled_tip, ordered_wire, tip_darkness, tip_end_check)
from scipy.spatial import cKDTree

SHAPE = (160, 320)
HINT_UV = (0.0, 80.0)
SHAFT = np.column_stack([np.linspace(30.0, 250.0, 440), np.full(440, 80.0)])      # proximal -> bend at u = 250


def _distance(points_uv, shape=SHAPE):
    dense = resample_polyline(np.asarray(points_uv, float), 0.1)
    vv, uu = np.mgrid[0:shape[0], 0:shape[1]]
    d, _ = cKDTree(dense).query(np.column_stack([uu.ravel(), vv.ravel()]))
    return d.reshape(shape)


def _frame(limbs, *, seed=0, noise=4.0, weights=None):
    """A live frame (the wire darker, each layer adding its own attenuation: Gaussian profile,
    sigma 0.9 px, times its weight: 1 for a limb in the image plane, 1 / cos(angle) for one running
    at an angle to it) and the segmenter's mask (every pixel within 1.5 px of a limb) of the polylines ``limbs``."""
    rng = np.random.default_rng(seed)
    img = np.full(SHAPE, 1000.0)
    mask = np.zeros(SHAPE, bool)
    for limb, weight in zip(limbs, weights or [1.0] * len(limbs)):
        d = _distance(limb)
        img -= weight * 60.0 * np.exp(-0.5 * (d / 0.9) ** 2)
        mask |= d <= 1.5
    return img + rng.normal(0.0, noise, SHAPE), mask


def test_a_wire_bent_back_over_itself_before_its_tip_is_flagged():
    """The distal 30 px run back alongside the shaft, 1.5 px from it (one line in the mask), and
    towards the viewer (45 deg out of the image plane, as where a vessel turns back in projection:
    the simulator's cases): the trace ends at the bend, 30 px from the true tip, and its last px
    are 1 + 1.41 times as dark as the wire. An in-plane fold (exactly two layers) measures 2.0, the
    limit ``DOUBLED_END_RATIO`` itself: flagged or not by the noise (the frames with the tip right
    measured up to 1.98 below 2.3 on seeds 0-179; folds nearly flat in the image, 2.06 and 2.20)."""
    folded = np.column_stack([np.linspace(250.0, 220.0, 60), np.full(60, 81.5)])
    img, mask = _frame([SHAFT, folded], weights=[1.0, np.sqrt(2.0)])
    ow = ordered_wire(mask, image=img, proximal_hint_uv=HINT_UV)
    assert ow
    true_tip = folded[-1]
    assert np.linalg.norm(ow.tip_uv_px - true_tip) > 25.0                  # the trace stops at the bend ...
    uv = ow.points_uv_px
    assert tip_darkness(img, uv) == pytest.approx(1 + np.sqrt(2.0), abs=0.4)      # ... where two layers of wire lie
    assert tip_darkness(img, uv, at_end=False) == pytest.approx(1.0, abs=0.3)     # the proximal end: one layer
    assert tip_darkness(img, uv[::-1], at_end=False) == tip_darkness(img, uv)
    doubled = doubled_tip(img, uv)
    assert doubled is not None and doubled.darkness_ratio >= DOUBLED_END_RATIO
    assert "tip uncertain" in doubled.explain() and f"last {END_WINDOW_PX} px" in doubled.explain()
    assert doubled_tip(img, uv, at_end=False) is None
    in_plane, _ = _frame([SHAFT, folded])
    ratio = tip_darkness(in_plane, ordered_wire(mask, image=in_plane, proximal_hint_uv=HINT_UV).points_uv_px)
    assert ratio == pytest.approx(2.0, abs=0.3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_free_tip_is_not_flagged(seed):
    """A wire that ends where it ends (also one that bends sharply, without running back over itself,
    and one crossing a darker structure proximally): its tip is no darker than the wire."""
    bent = np.vstack([SHAFT, np.column_stack([np.full(30, 250.0), np.linspace(81.0, 110.0, 30)])])
    blob = np.column_stack([np.full(40, 120.0), np.linspace(60.0, 100.0, 40)])   # a crossing line, proximally
    for limbs, wire in (([SHAFT], SHAFT), ([bent], bent), ([SHAFT, blob], SHAFT)):
        img, _ = _frame(limbs, seed=seed)
        _, mask = _frame([wire], seed=seed)
        ow = ordered_wire(mask, image=img, proximal_hint_uv=HINT_UV)
        assert ow and np.linalg.norm(ow.tip_uv_px - wire[-1]) < 2.0
        assert tip_darkness(img, ow.points_uv_px) < 1.3
        assert doubled_tip(img, ow.points_uv_px) is None


def test_too_short_or_without_contrast_there_is_no_measure_and_no_flag():
    img, _ = _frame([SHAFT])
    assert np.isnan(tip_darkness(img, SHAFT[:3 * END_WINDOW_PX - 1]))
    assert np.isnan(tip_darkness(np.full(SHAPE, 1000.0), SHAFT))
    assert doubled_tip(np.full(SHAPE, 1000.0), SHAFT) is None


def test_the_frame_verdict_says_so_at_the_output_tip():
    """A doubled tip makes the frame uncertain with its reason; when the reconstruction reversed the
    2D order, the 2D start is the output's tip (Session passes ``doubled_tip(..., at_end=False)``)."""
    uv = np.column_stack([np.linspace(100, 300, 50), np.full(50, 200.0)])
    w3 = SimpleNamespace(uncertainty_mm=np.full(50, 0.5), message="ok: 50 points", reversed_input=False)
    assert live.frame_verdict(w3, uv, None, image_shape=(512, 512))[0] is Verdict.OK
    verdict, message = live.frame_verdict(w3, uv, None, doubled_tip=DoubledTip(2.4), image_shape=(512, 512))
    assert verdict is Verdict.UNCERTAIN
    assert message.startswith("tip uncertain: the wire's last") and "2.4 x as dark" in message


@pytest.mark.parametrize("seed", [0, 1])
def test_a_trace_running_past_the_wire_end_over_a_false_mask_is_flagged(seed):
    """The segmenter's mask goes on 30 px past the wire's end where the image shows no wire (a false
    stretch, as at a low dose): the trace follows the mask, its last px are background
    (``tip_end_check`` gives a ``BareTip``), and the frame's verdict says why; the same wire with a
    right mask is not flagged, nor is a folded tip taken for a bare one."""
    past = np.vstack([SHAFT, np.column_stack([np.linspace(250.5, 280.0, 60), np.full(60, 80.0)])])
    img, _ = _frame([SHAFT], seed=seed)
    _, mask = _frame([past], seed=seed)
    ow = ordered_wire(mask, image=img, proximal_hint_uv=HINT_UV)
    assert ow and ow.tip_uv_px[0] > 275.0                                 # the trace runs past the wire's end
    bare = tip_end_check(img, ow.points_uv_px)
    assert isinstance(bare, BareTip) and bare.darkness_ratio < BARE_END_RATIO
    assert tip_darkness(img, ow.points_uv_px) == pytest.approx(0.0, abs=0.15)
    w3 = SimpleNamespace(uncertainty_mm=np.full(len(ow.points_uv_px), 0.5), message="ok", reversed_input=False)
    verdict, message = live.frame_verdict(w3, ow.points_uv_px, None, doubled_tip=bare, image_shape=SHAPE)
    assert verdict is Verdict.UNCERTAIN and message.startswith("tip uncertain: the trace's last")
    _, right = _frame([SHAFT], seed=seed)
    ok = ordered_wire(right, image=img, proximal_hint_uv=HINT_UV)
    assert ok and tip_end_check(img, ok.points_uv_px) is None
    folded = np.column_stack([np.linspace(250.0, 220.0, 60), np.full(60, 81.5)])
    img2, mask2 = _frame([SHAFT, folded], weights=[1.0, np.sqrt(2.0)], seed=seed)
    assert isinstance(tip_end_check(img2, ordered_wire(mask2, image=img2, proximal_hint_uv=HINT_UV).points_uv_px),
                      DoubledTip)
