"""Biplane: the other plane's image as a second opinion on a distal part taken from one plane alone.

``app.biplane.other_plane_image_support`` / ``_other_plane_image_reasons``: where plane A's 2D wire stops
short, the two-view wire's distal part comes from plane B alone (``triangulation.extend_distal``) at the
vessel prior's depth. Projected into plane A, that part must lie along a wire in plane A's image. Ground
truth from the simulator (seed 1, plane B 90 deg from plane A): the true wire lies along its projection;
the same wire moved along plane B's rays (the depth plane B does not see; its projection in B is
unchanged) does not.
"""
from dataclasses import replace

import numpy as np
import pytest

from guidewire3d import metrics
from guidewire3d.app import biplane
from guidewire3d.phantom import PhantomOptions, simulate
from guidewire3d.reconstruction import triangulation as tri

FRAME = 2  # the frame of the case used throughout
CUT = 0.35  # plane A's 2D wire loses this fraction of its length at the tip (its segmenter "lost" it)
WRONG_DEPTH_MM = 6.0  # the distal part moved this far along plane B's rays: a wrong depth
SAME_PX = 1e-6  # a move along plane B's rays leaves its projection in B where it was
REASON = "image shows no wire along its projection"


@pytest.fixture(scope="module")
def bcase():
    """A biplane case without CT (fast): seed 1, 3 frames, plane B 90 deg from plane A."""
    return simulate(PhantomOptions(seed=1, n_frames=3, biplane=True), make_ct=False)


def _visible(case, t):
    ua, ub = case.wire_uv_px[t], case.heldout_wire_uv_px[t]
    va, vb = case.carm.in_image(ua), case.heldout_carm.in_image(ub)
    return ua[va], ub[vb], np.asarray(case.wire_lps_mm[t])[va & vb]


def _along_rays_of_b(ctx, X, depth_mm):
    """``X`` moved ``depth_mm`` (per point, or one number) along plane B's rays through its points."""
    src = ctx.pose.inverse().apply(ctx.carms[1].source_room_mm[None])[0]
    ray = (X - src) / np.linalg.norm(X - src, axis=1)[:, None]
    return X + np.broadcast_to(np.asarray(depth_mm, float), (len(X),))[:, None] * ray


def _images(case, t):
    return np.asarray(case.frames[t]), np.asarray(case.heldout_frames[t])


def test_true_distal_part_is_seen_in_the_other_plane_and_a_wrong_depth_is_not(bcase):
    ctx = tri.TwoViewContext(bcase.tree, (bcase.carm, bcase.heldout_carm), bcase.pose)
    _, _, truth = _visible(bcase, FRAME)
    X = metrics.resample_polyline(truth, 0.5)
    distal = X[int((1 - CUT) * len(X)):]
    img_a, _ = _images(bcase, FRAME)
    right = biplane.other_plane_image_support(img_a, distal, ctx, 1)
    assert right["length_mm"] > biplane.IMAGE_CHECK_MIN_MM
    assert right["shown"] - right["chance"] >= biplane.IMAGE_CHECK_MARGIN
    assert right["best_offset_mm"] == 0.0
    wrong_pts = _along_rays_of_b(ctx, distal, WRONG_DEPTH_MM)
    assert np.abs(ctx.project(1, wrong_pts) - ctx.project(1, distal)).max() < SAME_PX
    wrong = biplane.other_plane_image_support(img_a, wrong_pts, ctx, 1)
    assert wrong["shown"] - wrong["chance"] < biplane.IMAGE_CHECK_MARGIN
    # the scan finds the wire back where the true depth is (-WRONG_DEPTH_MM, within the offsets' step)
    assert wrong["best_offset_mm"] < 0
    # a part outside the other plane's image is not judged
    far = distal + 1e4 * (ctx.pose.inverse().R @ ctx.carms[0].axes[0])
    assert biplane.other_plane_image_support(img_a, far, ctx, 1)["length_mm"] == 0.0


def _cut_pair(case, t):
    ua, ub, truth = _visible(case, t)
    return ua[: int((1 - CUT) * len(ua))], ub, truth


def test_lost_wire_in_one_plane_with_the_right_depth_passes(bcase):
    """The opposite failure: plane A's segmenter lost the distal wire but the 3D is right; plane A's
    image shows the wire along the projection, so the pair is not made uncertain by this check."""
    s = biplane.BiplaneSession(bcase.tree, (bcase.carm, bcase.heldout_carm), bcase.pose, threads=1)
    ua, ub, truth = _cut_pair(bcase, FRAME)
    pair = s.process_wires(ua, ub, images=_images(bcase, FRAME), index=0)
    tv = tri.extend_distal(tri.triangulate_wire(ua, ub, s.context), ua, ub, s.context, s._single_view)
    assert pair.views == "AB" and tv.distal_plane == 1 and tv.single_view_distal_mm > biplane.IMAGE_CHECK_MIN_MM
    assert metrics.wire_errors_mm(pair.result.wire3d.points_lps_mm, truth)["tip_error_mm"] < 1.0
    assert REASON not in pair.result.message
    assert biplane._other_plane_image_reasons(tv, _images(bcase, FRAME), s.context) == ""


def _bent_single_view(session, depth_mm):
    """Plane B's single-view reconstruction with its depth going wrong towards the tip: each point moved
    along plane B's rays by ``depth_mm`` x (its arclength share)^2 (the projection in B is unchanged)."""
    real = session._single_view

    def single_view(k, uv):
        w = real(k, uv)
        if k != 1 or not w:
            return w
        a = np.asarray(w.arclength_mm, float)
        return replace(w, points_lps_mm=_along_rays_of_b(session.context, w.points_lps_mm, depth_mm * (a / a[-1]) ** 2))

    return single_view


def test_distal_part_at_a_wrong_depth_makes_the_pair_uncertain(bcase):
    s = biplane.BiplaneSession(bcase.tree, (bcase.carm, bcase.heldout_carm), bcase.pose, threads=1)
    s._single_view = _bent_single_view(s, 3 * WRONG_DEPTH_MM)
    ua, ub, truth = _cut_pair(bcase, FRAME)
    tv = tri.extend_distal(tri.triangulate_wire(ua, ub, s.context), ua, ub, s.context, s._single_view)
    assert metrics.wire_errors_mm(tv.wire3d.points_lps_mm, truth)["tip_error_mm"] > 5.0  # wrong indeed
    pair = s.process_wires(ua, ub, images=_images(bcase, FRAME), index=0)
    assert pair.views == "AB"
    assert pair.result.verdict.value == "uncertain"
    assert "distal part from plane B alone: plane A's " + REASON in pair.result.message
    # without plane A's image nothing is judged: the same pair is silently wrong
    blind = s.process_wires(ua, ub, images=(None, None), index=1)
    assert REASON not in blind.result.message and blind.result.verdict.value == "ok"


def test_the_depth_of_a_one_plane_part_is_read_in_the_other_planes_image(bcase):
    """The same wrong depth (18 mm at the tip, along plane B's rays): plane A's image shows where the wire is, and
    ``depth_from_other_image`` moves the part there along plane B's rays (its projection in B stays); the pair's
    verdict stays the one-plane part's (``uncertain``). A flat plane A image moves nothing."""
    s = biplane.BiplaneSession(bcase.tree, (bcase.carm, bcase.heldout_carm), bcase.pose, threads=1)
    s._single_view = _bent_single_view(s, 3 * WRONG_DEPTH_MM)
    ua, ub, truth = _cut_pair(bcase, FRAME)
    img_a, img_b = _images(bcase, FRAME)
    tv = tri.extend_distal(tri.triangulate_wire(ua, ub, s.context), ua, ub, s.context, s._single_view)
    before = metrics.wire_errors_mm(tv.wire3d.points_lps_mm, truth)
    moved, offsets = biplane.depth_from_other_image(tv, img_a, s.context)
    after = metrics.wire_errors_mm(moved.wire3d.points_lps_mm, truth)
    assert len(offsets) > 0 and before["tip_error_mm"] > 5.0
    assert after["tip_error_mm"] < 2.5 and after["mean_error_mm"] < 0.25 * before["mean_error_mm"]
    same = np.abs(s.context.project(1, moved.wire3d.points_lps_mm) - s.context.project(1, tv.wire3d.points_lps_mm))
    assert same.max() < 1e-6
    assert moved.wire3d.length_mm == pytest.approx(metrics.polyline_length(moved.wire3d.points_lps_mm))
    assert "read in plane A's image" in moved.wire3d.message
    pair = s.process_wires(ua, ub, images=(img_a, img_b), index=0)
    assert pair.result.verdict.value == "uncertain" and "read in plane A's image" in pair.result.message
    assert metrics.wire_errors_mm(pair.result.wire3d.points_lps_mm, truth)["tip_error_mm"] < 2.5
    flat = np.full_like(img_a, np.median(img_a))
    unmoved, none = biplane.depth_from_other_image(tv, flat, s.context)
    assert len(none) == 0 and unmoved is tv


def test_plane_a_image_without_the_wire_contradicts_the_distal_part(bcase):
    """Plane A's frame replaced by one that shows no wire (flat, with noise): the distal part's projection
    meets a wire there no more often than anywhere else, and the pair is uncertain."""
    rng = np.random.default_rng(7)
    s = biplane.BiplaneSession(bcase.tree, (bcase.carm, bcase.heldout_carm), bcase.pose, threads=1)
    ua, ub, _ = _cut_pair(bcase, FRAME)
    img_a, img_b = _images(bcase, FRAME)
    flat = np.median(img_a) + rng.normal(0.0, np.std(img_a) * 0.05, img_a.shape)
    pair = s.process_wires(ua, ub, images=(flat, img_b), index=0)
    assert pair.result.verdict.value == "uncertain" and REASON in pair.result.message


def test_plane_must_be_a_or_b(bcase):
    from guidewire3d.errors import InputError

    ctx = tri.TwoViewContext(bcase.tree, (bcase.carm, bcase.heldout_carm), bcase.pose)
    _, _, truth = _visible(bcase, FRAME)
    with pytest.raises(InputError, match="plane must be 0 .A. or 1 .B."):
        biplane.other_plane_image_support(_images(bcase, FRAME)[0], truth, ctx, 2)


@pytest.mark.parametrize("limit_mm", [None, float("inf")])
def test_a_part_moved_far_from_the_vessel_priors_depth_makes_the_pair_uncertain(monkeypatch, limit_mm):
    """``bench_biplane`` seed 5 (4 frames), frame 2: plane A's last 50 mm are taken from plane A alone, and the depth
    search moves them 7.0 mm (median) along plane A's rays into another vessel where plane B's image shows wire: 11 mm
    off on average, the tip 29 mm off. The image and the CTA tree disagree by more than ``DEPTH_MOVE_MAX_MM``: the pair
    is ``uncertain``; without that limit it was ``ok``."""
    if limit_mm is not None:
        monkeypatch.setattr(biplane, "DEPTH_MOVE_MAX_MM", limit_mm)
    case = simulate(PhantomOptions(seed=5, n_frames=4, biplane=True), make_ct=False)
    s = biplane.BiplaneSession(case.tree, (case.carm, case.heldout_carm), case.pose, threads=1)
    pairs = [s.process(case.frames[t], case.heldout_frames[t], index=t) for t in range(3)]
    r = pairs[2].result
    t = 2
    seen = case.carm.in_image(case.wire_uv_px[t]) | case.heldout_carm.in_image(case.heldout_wire_uv_px[t])
    e = metrics.wire_errors_mm(r.wire3d.points_lps_mm, np.asarray(case.wire_lps_mm[t])[seen])
    assert e["mean_error_mm"] > 5.0 and e["tip_error_mm"] > 10.0          # the moved part is wrong
    assert "read in plane B's image (moved" in r.message
    if limit_mm is None:
        assert r.verdict.value == "uncertain"
        assert "the image and the CTA tree disagree on its depth" in r.message
    else:
        assert r.verdict.value == "ok"                                      # silently wrong
