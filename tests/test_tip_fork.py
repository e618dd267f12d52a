"""A wire whose tip is bent back thins into a skeleton with two ends, and the trace may take the bend instead of the
tip (``bench_stress`` 7215 f1: the trace ended at the fold, the 3D tip 8 mm short, reported ``ok``). The mask's
fork just before the traced tip makes the tip uncertain (``orderedwire.TipFork``); a straight wire, a short spur,
a blunt end and a hook the trace follows to its end do not."""
import numpy as np
from guidewire3d import live
from guidewire3d.registration import Verdict
from guidewire3d.xray.orderedwire import TIP_FORK_MIN_PX, TipFork, ordered_wire
from skimage.draw import disk

WIRE_UV = [(40, 20), (70, 80), (100, 130)]   # proximal -> distal, (u, v) px


def _mask(*polylines, blob_px: float = 0.0, shape=(200, 200), half_width_px: float = 1.5):
    """A wire mask: discs of ``half_width_px`` along the polylines ((u, v) px), and a round blob of ``blob_px`` at the
    wire's distal end (two layers of wire where it folds)."""
    m = np.zeros(shape, bool)
    for pts in polylines:
        for a, b in zip(pts[:-1], pts[1:]):
            for t in np.linspace(0.0, 1.0, int(np.ceil(np.hypot(b[0] - a[0], b[1] - a[1]))) * 2 + 1):
                rr, cc = disk((a[1] + t * (b[1] - a[1]), a[0] + t * (b[0] - a[0])), half_width_px, shape=shape)
                m[rr, cc] = True
    if blob_px:
        rr, cc = disk((WIRE_UV[-1][1], WIRE_UV[-1][0]), blob_px, shape=shape)
        m[rr, cc] = True
    return m


def test_a_tip_bent_back_at_a_fold_is_a_fork_before_the_traced_tip():
    hook = [(99, 127), (97, 110)]                   # 17 px back up from the fold
    w = ordered_wire(_mask(WIRE_UV, hook, blob_px=3.5), proximal_hint_uv=WIRE_UV[0])
    assert w
    assert np.linalg.norm(w.tip_uv_px - WIRE_UV[-1]) < 3.0     # the trace ended at the fold ...
    assert isinstance(w.tip_fork, TipFork)                     # ... and says the mask forks before it
    assert w.tip_fork.reach_px >= TIP_FORK_MIN_PX and w.tip_fork.from_tip_px <= 15.0
    # the true tip (the hook's end) is as far from the traced one as the fork reaches, roughly
    assert abs(np.linalg.norm(np.subtract(hook[-1], w.tip_uv_px)) - 20.0) < 5.0


def test_no_fork_on_a_straight_wire_a_short_spur_a_blunt_end_or_a_hook_followed_to_its_end():
    cases = {
        "straight": _mask(WIRE_UV),
        "short spur": _mask(WIRE_UV, [(100, 130), (103, 127)]),
        "blunt end": _mask(WIRE_UV, blob_px=3.5),
        "hook followed": _mask(WIRE_UV, [(100, 130), (98, 112)]),
    }
    for name, m in cases.items():
        w = ordered_wire(m, proximal_hint_uv=WIRE_UV[0])
        assert w, name
        assert w.tip_fork is None, (name, w.tip_fork)
    # the hook without a fold is traced to its true end
    w = ordered_wire(cases["hook followed"], proximal_hint_uv=WIRE_UV[0])
    assert np.linalg.norm(w.tip_uv_px - [98, 112]) < 3.0


def test_the_frame_verdict_names_the_fork():
    from types import SimpleNamespace

    uv = np.column_stack([np.linspace(100, 400, 301), np.full(301, 300.0)])
    w3 = SimpleNamespace(success=True, message="ok", reversed_input=False, uncertainty_mm=np.full(301, 0.5),
                         points_lps_mm=np.column_stack([np.linspace(0, 90, 301), np.zeros(301), np.zeros(301)]),
                         method="vessel")
    fork = TipFork(reach_px=8.0, from_tip_px=6.0)
    verdict, message = live.frame_verdict(w3, uv, None, tip_fork=fork, image_shape=(1024, 1024))
    assert verdict is Verdict.UNCERTAIN and "mask forks 6 px before the traced tip" in message, message
    # a reconstruction that reversed the 2D order has its tip at the other end: the fork is not at its tip
    w3.reversed_input = True
    assert "mask forks" not in live.frame_verdict(w3, uv, None, tip_fork=fork, image_shape=(1024, 1024))[1]


def test_a_wire_leaving_the_image_is_no_fork():
    """The mask is replicated beyond the border before thinning (so the skeleton does not fork at the cut); that
    replication is not the wire's, and a fork in it is none."""
    for end in ((199, 150), (150, 199), (199, 199), (60, 199)):
        w = ordered_wire(_mask([(40, 20), (90, 90), end], half_width_px=2.0), proximal_hint_uv=(40, 20))
        assert w, end
        assert w.tip_fork is None, (end, w.tip_fork)
