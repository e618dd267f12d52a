"""A stretch of wire the ROI-tracked segmentation lost inside its boxes is found again full-frame
(``live.Session.wire2d_of``, ``GuidewireSegmenter.segment_again_full``), against the simulator's true wire.

``bench_stress`` 8112 f4: the network run on small boxes lost a faint stretch of a 0.25 mm wire inside a
box that the full frame shows; the wire was left in two pieces 100 px apart, 311 px of its 508 px traced,
the tip 27 mm off and reported ``ok``. Here the tracked pass of the second frame is made to lose such a
stretch.
"""
import numpy as np
import pytest

from guidewire3d.live import Session
from guidewire3d.live import session as live_session
from guidewire3d.metrics import polyline_length
from guidewire3d.xray.segmentation import GuidewireSegmenter, guidewire_mask

HOLE_PX = 50.0   # the stretch lost: every mask pixel within this of a point 60 % along the true wire


class _LosesAStretch(GuidewireSegmenter):
    """The tracked pass (boxes around the previous mask) loses the pixels within ``HOLE_PX`` of ``hole_uv``."""

    hole_uv = None

    def _tracked(self, a, prev, stats):
        m = super()._tracked(a, prev, stats)
        if m is not None and self.hole_uv is not None:
            v, u = np.mgrid[: m.shape[0], : m.shape[1]]
            m = m & ((u - self.hole_uv[0]) ** 2 + (v - self.hole_uv[1]) ** 2 > HOLE_PX ** 2)
        return m


def _hole_at(uv: np.ndarray, fraction: float) -> np.ndarray:
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(uv, axis=0), axis=1))]
    return uv[int(np.searchsorted(s, fraction * s[-1]))]


@pytest.mark.parametrize("again", [True, False])
def test_a_stretch_the_tracked_pass_lost_is_segmented_again_full_frame(small_case, monkeypatch, again):
    case = small_case
    if not again:
        monkeypatch.setattr(live_session, "TRACKED_SHRINK_MIN_PX", float("inf"))
    seg = _LosesAStretch(method="unet")
    session = Session(case.tree, case.carm, case.pose, segmenter=seg)
    first = session.process(case.frames[0], index=0)
    assert seg.last_mode == "full" and first.wire2d
    k = 1
    true_uv = np.asarray(case.wire_uv_px[k])[np.asarray(case.wire_visible[k], bool)]
    seg.hole_uv = _hole_at(true_uv, 0.6)
    res = session.process(case.frames[k], index=k)
    true_len_px = polyline_length(true_uv)
    traced = np.asarray(res.wire2d.points_uv_px)
    tip_px = float(np.linalg.norm(traced[-1] - true_uv[-1]))
    if again:
        # segmented again full-frame: the whole wire, its tip where the true tip is, and the mask that of
        # the full frame (the tracking state goes on from it)
        assert session.n_segmented_again == 1
        assert seg.last_mode == "full"
        assert tip_px < 3.0, tip_px
        assert res.wire2d.length_px > 0.95 * true_len_px
        assert res.verdict.value != "failed"
        tip_mm = float(np.linalg.norm(res.wire3d.points_lps_mm[-1] - np.asarray(case.wire_lps_mm[k])[-1]))
        assert tip_mm < 2.0, tip_mm
        full = guidewire_mask(case.frames[k])
        assert np.array_equal(seg._prev, full)
    else:
        # without it the trace stops at the hole, 100 px short of the tip, with no flag on the 2D wire
        assert session.n_segmented_again == 0
        assert seg.last_mode in ("roi", "roi-grown")
        assert tip_px > 0.3 * true_len_px, tip_px
        assert res.wire2d.beyond_tip is None
