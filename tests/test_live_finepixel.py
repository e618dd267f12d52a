"""The frame verdict and the motion tracker on a finer detector: the same anatomy, the same verdict.

Their lengths in pixels (``live.session.TIP_STRETCH_PX``, ``reconstruction.path.TREE_END_MAX_PX``,
``motion.MOTION_PIXEL_OPTIONS`` and ``CROP_MARGIN_PX``) were tuned on the simulator's 512 px views, about
``geometry.REFERENCE_PIXEL_AT_ISO_MM`` at the isocentre. On a view finer than that they are widened to
their size in mm there (``geometry.fine_pixel_factor``), as the reconstruction's options are since stop 32
(``tests/test_reconstruction_pixel.py``); at the reference or coarser nothing changes.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from guidewire3d import geometry, metrics
from guidewire3d.errors import GeometryError
from guidewire3d.geometry import CArm, Pose
from guidewire3d.live import session as live
from guidewire3d.motion import MOTION_PIXEL_OPTIONS, MotionOptions, MotionTracker
from guidewire3d.phantom import PhantomOptions, simulate
from guidewire3d.registration import Verdict
from guidewire3d.vesseltree import VesselTree

TIP_OFF_MM = 5.0  # bench_stress: an ok frame whose tip is farther than this from the true tip is wrong


def test_the_factor_widens_only_below_the_reference():
    ref = geometry.REFERENCE_PIXEL_AT_ISO_MM
    assert geometry.fine_pixel_factor(ref) == 1.0
    assert geometry.fine_pixel_factor(0.6) == 1.0            # the real-anatomy case's panel: as before
    assert geometry.fine_pixel_factor(ref / 2) == pytest.approx(2.0)
    with pytest.raises(GeometryError, match="positive"):
        geometry.fine_pixel_factor(0.0)
    opt = MotionOptions()
    assert geometry.options_in_mm(opt, MOTION_PIXEL_OPTIONS, ref) is opt
    wide = geometry.options_in_mm(opt, MOTION_PIXEL_OPTIONS, ref / 2)
    for name in MOTION_PIXEL_OPTIONS:
        assert getattr(wide, name) == pytest.approx(2 * getattr(opt, name))
    assert wide.sigma_cc_mm == opt.sigma_cc_mm and wide.settle_rival_cost == opt.settle_rival_cost
    assert wide.sigma_px == opt.sigma_px and wide.inlier_px == opt.inlier_px     # the 2D noise model stays in px
    # a tracker widens its own options on a fine view only (the same object on the reference view)
    z = np.linspace(-20.0, 20.0, 41)
    tree = VesselTree(np.column_stack([0 * z, 0 * z, z]), np.full(len(z), 2.0), np.r_[-1, np.arange(len(z) - 1)])
    for detector, k in ((512, 1.0), (1024, 2.0)):
        carm = CArm(0.0, 0.0, 1000.0, 700.0, ref * 1000.0 / 700.0 * 512 / detector, (detector, detector))
        trk = MotionTracker(tree, carm, Pose.identity(), options=opt)
        assert trk.options.gate_px == pytest.approx(k * opt.gate_px) and trk.options.sigma_px == opt.sigma_px
        assert (trk.options is opt) == (k == 1.0)


def test_the_tips_stretch_is_measured_over_the_same_mm():
    """A wire 0.2 mm per px in the image plane, its last 8 px along the beam (1.5 mm per px), seen at the
    reference pixel and at half of it (the same wire: twice the px, each px half the mm): the stretch over
    the tip's last mm is the same, and so is the verdict."""
    def wire(scale):
        n_plane, n_beam = 100 * scale, 8 * scale
        u = np.arange(n_plane + n_beam, dtype=float)
        x = np.r_[np.arange(n_plane) * 0.2 / scale, (n_plane - 1) * 0.2 / scale + np.arange(1, n_beam + 1) * 0.05 / scale]
        z = np.r_[np.zeros(n_plane), np.arange(1, n_beam + 1) * 1.5 / scale]
        X = np.column_stack([x, np.zeros_like(x), z])
        return SimpleNamespace(points_lps_mm=X, uncertainty_mm=np.full(len(X), 0.5), message="ok",
                               reversed_input=False), np.column_stack([u, np.full_like(u, 100.0)])
    ref = geometry.REFERENCE_PIXEL_AT_ISO_MM
    coarse, fine = wire(1), wire(2)
    v_coarse = live.frame_verdict(*coarse, None, image_shape=(512, 512), pixel_at_iso_mm=ref)
    v_fine = live.frame_verdict(*fine, None, image_shape=(1024, 1024), pixel_at_iso_mm=ref / 2)
    assert v_coarse[0] is Verdict.UNCERTAIN and v_fine[0] is Verdict.UNCERTAIN, (v_coarse, v_fine)
    assert "runs along the beam" in v_fine[1] and "last 7.5 mm" in v_coarse[1] and "last 7.5 mm" in v_fine[1]
    # in px (no pixel size given) the fine view's last 5 px span half the mm
    assert live.tip_stretch_mm(fine[0], fine[1]) == pytest.approx(7.5 / 2, rel=1e-3)


def test_a_1024_px_tip_on_a_vessel_along_the_beam_is_not_ok():
    """``bench_stress`` seed 3505 simulated at 512 and at 1024 px (true tree and pose). Frame 1's tip
    enters a vessel that runs along the beam: at 512 px its last 5 px span 5.1 mm and the frame is
    ``uncertain``; at 1024 px the last 5 px spanned 3.5 mm, under the limit, and the frame was ``ok``
    with its tip 5.5 mm off. Over the same mm (7.5 px at 0.106 mm) it is ``uncertain`` at both sizes;
    frame 0 (its tip's vessel in the image plane) stays ``ok`` and right at both."""
    for detector in (512, 1024):
        case = simulate(PhantomOptions(seed=3505, n_frames=8, detector_px=detector), make_ct=False)
        ses = live.Session(case.tree, case.carm, case.pose)
        for t in range(2):
            fr = ses.process(case.frames[t])
            assert fr.wire3d, fr.message
            seen = np.asarray(case.wire_visible[t], bool)
            tip_mm = metrics.wire_errors_mm(fr.wire3d.points_lps_mm, np.asarray(case.wire_lps_mm[t])[seen])["tip_error_mm"]
            if t == 0:
                assert fr.verdict is Verdict.OK and tip_mm < 2.0, (detector, fr.message, tip_mm)
            else:
                assert tip_mm > TIP_OFF_MM                                # the 3D tip is wrong ...
                assert fr.verdict is Verdict.UNCERTAIN and "runs along the beam" in fr.message, (detector, fr.message)
