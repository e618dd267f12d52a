"""Guidewire segmentation: shipped UNet and ridge detector against the simulator's truth masks."""
from __future__ import annotations

import numpy as np
import pytest

from guidewire3d.errors import InputError
from guidewire3d.metrics import dice
from guidewire3d.phantom import PhantomOptions, simulate
from guidewire3d.xray.segmentation import (
    DEFAULT_WEIGHTS_PATH,
    Backend,
    GuidewireSegmenter,
    SegMethod,
    collimator_field_of_view,
    frame_is_degenerate,
    guidewire_mask,
    load_unet,
    normalize_frame,
    ridge_probability,
    unet_probability,
)

# held-out seeds (training uses 1000-1999)
SEED_THIN, SEED_THICK = 7, 8
N_FRAMES = 10  # the tip advances over the sequence; consecutive frames are ~20 px apart
DICE_FRAMES = (0, 4, 9)
TRACK_FRAMES = (0, 1, 2)
# per-frame mean Dice floors on these held-out frames, by wire diameter (mm); the 0.014" wire's truth
# mask is 1-2 px wide, so its Dice is lower (full numbers: scripts/bench_segmentation.py)
UNET_MIN_DICE = {0.36: 0.88, 0.89: 0.95}
RIDGE_MIN_DICE = {0.36: 0.65, 0.89: 0.82}
ROI_VS_FULL_MIN_DICE = 0.97
GROW_SEED = 101  # a held-out seed (< 1000) whose tip advances beyond the ROI margin between frames
BACKEND_MAX_ABS_DIFF = 1e-3
COLLIMATED_MIN_DICE = 0.85   # UNet mask vs the truth inside a synthetic collimator (0.89 mm wire)


@pytest.fixture(scope="module")
def cases():
    out = {}
    for seed, diam in ((SEED_THIN, 0.36), (SEED_THICK, 0.89)):
        sim = simulate(PhantomOptions(seed=seed, n_frames=N_FRAMES, wire_diameter_mm=diam, dose=1.0), make_ct=False)
        out[diam] = (np.asarray(sim.frames), np.asarray(sim.wire_mask))
    return out


@pytest.fixture(scope="module")
def dice_cases(cases):
    out = {}
    for diam, (frames, masks) in cases.items():
        idx = list(DICE_FRAMES)
        out[diam] = (frames[idx], masks[idx])
    return out


def test_shipped_weights_are_small_safetensors():
    assert DEFAULT_WEIGHTS_PATH.is_file()
    assert DEFAULT_WEIGHTS_PATH.stat().st_size < 5 * 1024 * 1024
    header_len = int.from_bytes(DEFAULT_WEIGHTS_PATH.read_bytes()[:8], "little")
    assert DEFAULT_WEIGHTS_PATH.read_bytes()[8:9] == b"{" and header_len > 0  # safetensors JSON header


@pytest.mark.parametrize("diameter", [0.36, 0.89])
def test_unet_dice_on_heldout_frames(dice_cases, diameter):
    frames, masks = dice_cases[diameter]
    scores = [dice(guidewire_mask(f, method="unet"), m) for f, m in zip(frames, masks)]
    assert np.mean(scores) >= UNET_MIN_DICE[diameter], scores


@pytest.mark.parametrize("method", list(SegMethod))
def test_every_method_member_segments_the_wire(cases, method):
    frames, masks = cases[0.89]
    by_member = guidewire_mask(frames[0], method=method)
    by_string = guidewire_mask(frames[0], method=method.value)
    assert np.array_equal(by_member, by_string)
    floor = (UNET_MIN_DICE if method is SegMethod.UNET else RIDGE_MIN_DICE)[0.89]
    assert dice(by_member, masks[0]) >= floor


@pytest.mark.parametrize("diameter", [0.36, 0.89])
def test_ridge_quality(dice_cases, diameter):
    frames, masks = dice_cases[diameter]
    scores = [dice(guidewire_mask(f, method=SegMethod.RIDGE), m) for f, m in zip(frames, masks)]
    assert np.mean(scores) >= RIDGE_MIN_DICE[diameter], scores
    # the ridge response separates wire from background
    p = ridge_probability(frames[0])
    assert np.median(p[masks[0]]) > 0.8
    assert np.median(p[~masks[0]]) < 0.3


@pytest.mark.parametrize("method", list(SegMethod))
def test_roi_tracking_matches_full_frame(cases, method):
    frames = cases[0.36][0][list(TRACK_FRAMES)]
    seg = GuidewireSegmenter(method=method, roi_margin_px=32)
    modes = []
    for f in frames:
        tracked = seg.segment(f)
        modes.append(seg.last_mode)
        full = guidewire_mask(f, method=method)
        assert dice(tracked, full) >= ROI_VS_FULL_MIN_DICE
    assert modes[0] == "full" and modes[1:] == ["roi"] * (len(frames) - 1)
    seg.reset()
    seg.segment(frames[0])
    assert seg.last_mode == "full"


@pytest.mark.parametrize("margin_px", [24, 16])
def test_roi_tracking_grows_the_boxes_when_the_wire_moved_beyond_them(monkeypatch, margin_px):
    """In a sequence whose wire advances tens of px per frame (6 frames over the whole insertion),
    the wire leaves the boxes; boxes added where it left them find it without a full-frame pass,
    every tracked mask equals the full-frame one, and the added boxes are a local extension (the
    network is not run again over the whole band)."""
    from guidewire3d.xray import segmentation as S

    sim = simulate(PhantomOptions(seed=GROW_SEED, n_frames=6, wire_diameter_mm=0.36), make_ct=False)
    calls = []
    unet = S.SEGMENTERS[SegMethod.UNET]
    original = type(unet).mask

    def recording(self, frame, stats, boxes, **kw):
        calls.append(None if boxes is None else sum((v1 - v0) * (u1 - u0) for u0, v0, u1, v1 in boxes))
        return original(self, frame, stats, boxes, **kw)

    monkeypatch.setattr(type(unet), "mask", recording)
    seg = GuidewireSegmenter(method="unet", roi_margin_px=margin_px, predict_advance=False)
    modes = []
    for f in sim.frames:
        calls.clear()
        tracked = seg.segment(f)
        modes.append(seg.last_mode)
        if seg.last_mode == "roi-grown":
            first, *added = calls
            assert 1 <= len(added) <= S.ROI_GROW_ROUNDS and sum(added) < first, calls
        assert dice(tracked, guidewire_mask(f)) >= ROI_VS_FULL_MIN_DICE
    assert modes[0] == "full" and "full" not in modes[1:], modes
    assert "roi-grown" in modes, modes


def test_roi_tracking_predicts_the_advance_of_a_pushed_wire(monkeypatch):
    """Where the wire advanced in the last frame, the next frame's first pass already covers the cells
    ahead (``predict_advance``): on a sequence whose tip advances tens of px per frame, fewer frames
    need a growth round (an extra network call) and every mask still equals the full-frame one."""
    from guidewire3d.xray import segmentation as S

    sim = simulate(PhantomOptions(seed=GROW_SEED, n_frames=8, wire_diameter_mm=0.36), make_ct=False)
    grown = {}
    for predict in (False, True):
        seg = GuidewireSegmenter(method="unet", predict_advance=predict)
        modes = []
        for f in sim.frames:
            tracked = seg.segment(f)
            modes.append(seg.last_mode)
            assert dice(tracked, guidewire_mask(f)) >= ROI_VS_FULL_MIN_DICE
        assert modes[0] == "full" and "full" not in modes[1:], modes
        grown[predict] = modes.count("roi-grown")
    assert grown[True] < grown[False], grown


def test_roi_tracking_falls_back_to_full_frame_when_growing_does_not_catch_the_wire(cases, monkeypatch):
    """With no growth rounds allowed, a wire that leaves its boxes is segmented full-frame."""
    from guidewire3d.xray import segmentation as S

    sim = simulate(PhantomOptions(seed=GROW_SEED, n_frames=6, wire_diameter_mm=0.36), make_ct=False)
    monkeypatch.setattr(S, "ROI_GROW_ROUNDS", 0)
    seg = GuidewireSegmenter(method="unet", roi_margin_px=16, predict_advance=False)
    modes = []
    for f in sim.frames:
        tracked = seg.segment(f)
        modes.append(seg.last_mode)
        assert dice(tracked, guidewire_mask(f)) >= ROI_VS_FULL_MIN_DICE
    assert "roi-grown" not in modes and modes.count("full") >= 2, modes


def test_roi_restricts_the_mask(cases):
    frames, masks = cases[0.89]
    vv, uu = np.nonzero(masks[0])
    roi = (int(uu.min()) - 10, int(vv.min()) - 10, int(np.median(uu)), int(vv.max()) + 10)
    m = guidewire_mask(frames[0], roi_uv=roi)
    outside = np.ones_like(m)
    outside[roi[1]:roi[3], roi[0]:roi[2]] = False
    assert not m[outside].any()
    full = guidewire_mask(frames[0])
    inner = (slice(roi[1] + 16, roi[3] - 16), slice(roi[0] + 16, roi[2] - 16))
    assert dice(m[inner], full[inner]) >= ROI_VS_FULL_MIN_DICE


@pytest.mark.parametrize("method", list(SegMethod))
def test_bad_frames_give_an_empty_mask(method):
    rng = np.random.default_rng(0)
    blank = np.zeros((256, 256), np.uint16)
    flat = np.full((256, 256), 1234.0)
    saturated = np.full((256, 256), 65535, np.uint16)
    saturated[:10, :10] = rng.integers(0, 65535, (10, 10))
    noise_only = rng.poisson(3000.0, (256, 256)).astype(np.float32)  # a flat field: no wire
    for frame, degenerate in ((blank, True), (flat, True), (saturated, True), (noise_only, False)):
        assert frame_is_degenerate(frame) == degenerate
        assert not guidewire_mask(frame, method=method).any()
        seg = GuidewireSegmenter(method=method)
        assert not seg.segment(frame).any()


def test_ordered_wire_reports_failure_on_empty_mask():
    from guidewire3d.xray.orderedwire import ordered_wire

    mask = guidewire_mask(np.zeros((128, 128), np.float32))
    ow = ordered_wire(mask)
    assert not ow and not ow.success and ow.message


def test_normalisation_is_invariant_to_gain_and_offset(cases):
    frame = cases[0.36][0][0]
    z = normalize_frame(frame)
    z2 = normalize_frame(frame * 3.7 + 250.0)
    np.testing.assert_allclose(z, z2, atol=1e-4)
    m1 = guidewire_mask(frame)
    m2 = guidewire_mask((frame * 0.25).astype(np.uint16))  # rescaled and quantised
    assert dice(m1, m2) >= ROI_VS_FULL_MIN_DICE


def test_loader_uses_no_pickle(monkeypatch, cases):
    import pickle

    import torch

    def forbidden(*a, **k):
        raise AssertionError("pickle-based loading was used")

    monkeypatch.setattr(torch, "load", forbidden)
    monkeypatch.setattr(pickle, "load", forbidden)
    monkeypatch.setattr(pickle, "loads", forbidden)
    model = load_unet()
    frames, masks = cases[0.89]
    c = 16  # reflected context, as in guidewire_mask
    z = np.pad(normalize_frame(frames[0]), c, mode="reflect")[None, None]
    with torch.inference_mode():
        p = torch.sigmoid(model(torch.from_numpy(z)))[0, 0, c:-c, c:-c].numpy() > model.config.threshold
    assert dice(p, masks[0]) >= UNET_MIN_DICE[0.89]


@pytest.mark.parametrize("backend", list(Backend))
def test_backends_agree(cases, backend):
    frame = cases[0.36][0][1]
    ref = unet_probability(frame, backend="torch")
    p = unet_probability(frame, backend=backend)
    assert np.abs(p - ref).max() <= BACKEND_MAX_ABS_DIFF


def test_collimator_edge_is_not_a_wire(cases):
    from scipy import ndimage as ndi

    from guidewire3d.xray.segmentation import _unet_mask_from_prob, load_unet

    frames, masks = cases[0.89]
    frame, truth = frames[DICE_FRAMES[0]], masks[DICE_FRAMES[0]]
    assert collimator_field_of_view(frame) is None               # the simulator has no collimator
    h, w = frame.shape
    vv, uu = np.mgrid[:h, :w]
    circle = np.hypot(uu - w / 2, vv - h / 2) < 0.47 * w            # a round collimator, corners dark
    collimated = np.where(circle, frame, 0.03 * frame)
    fov = collimator_field_of_view(collimated)
    edge_band = circle & ~ndi.binary_erosion(circle, iterations=4)
    # The network alone answers the collimator's edge; the mask does not.
    raw = _unet_mask_from_prob(unet_probability(collimated), load_unet().config.threshold)
    assert (raw & edge_band).any()
    for mask in (guidewire_mask(collimated), GuidewireSegmenter().segment(collimated)):
        assert not (mask & ~fov).any() and not (mask & edge_band).any()
        assert dice(mask, truth & fov) >= COLLIMATED_MIN_DICE


def test_a_frame_saved_as_rgb_gives_the_grey_frames_mask(cases):
    frames, _ = cases[0.36]
    grey = frames[DICE_FRAMES[0]]
    scaled = (255.0 * (grey - grey.min()) / np.ptp(grey)).astype(np.uint8)   # as an 8-bit export would
    ref = guidewire_mask(scaled)
    assert ref.any()
    assert np.array_equal(guidewire_mask(np.repeat(scaled[..., None], 3, axis=2)), ref)


def test_bad_input_raises(tmp_path):
    with pytest.raises(InputError, match="frame"):
        guidewire_mask(np.zeros((4, 5, 6)))
    with pytest.raises(InputError, match="method"):
        guidewire_mask(np.zeros((64, 64)), method="fcn")
    with pytest.raises(InputError, match="roi_uv"):
        guidewire_mask(np.ones((64, 64)), roi_uv=(10, 10, 5, 5))
    with pytest.raises(InputError, match="sigmas_px"):
        ridge_probability(np.ones((64, 64)), sigmas_px=(0.0,))
    with pytest.raises(InputError, match="not found"):
        load_unet(tmp_path / "missing.safetensors")
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a safetensors file")
    with pytest.raises(InputError, match="safetensors"):
        load_unet(bad)


def test_every_segmentation_method_has_a_segmenter_and_a_cli_choice():
    from guidewire3d.app import batch2d
    from guidewire3d.app import cli
    from guidewire3d.xray.segmentation import SEGMENTERS

    assert set(SEGMENTERS) == set(SegMethod)
    assert cli.SEGMENTERS == tuple(m.value for m in SegMethod)
    parser = cli._Parser(prog="segment")
    batch2d.add_cli_options(parser)
    seg = next(a for a in parser._actions if a.dest == "segmenter")
    assert tuple(seg.choices) == cli.SEGMENTERS


@pytest.mark.parametrize("method", list(SegMethod))
def test_the_registry_gives_the_same_mask_as_guidewire_mask(cases, method):
    """A segmenter's full-frame mask is guidewire_mask's (no collimator in the simulated frame)."""
    from guidewire3d.xray.segmentation import SEGMENTERS, UNET_CONTEXT_PX, Backend, _frame_stats

    frames = cases[0.89][0]
    a = np.asarray(frames[0])
    med, spread, _ = _frame_stats(a)
    m = SEGMENTERS[method].mask(a, (med, spread), None, backend=Backend.AUTO, num_threads=None,
                                context_px=UNET_CONTEXT_PX)
    assert m.shape == a.shape and m.dtype == bool and m.any()
    assert np.array_equal(m, guidewire_mask(frames[0], method=method))


# --- the live path's shortcuts against the plain code they replace ------------------------------------

@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint16, np.uint8])
def test_frame_stats_are_numpys_percentiles(dtype):
    from guidewire3d.xray import segmentation as S

    rng = np.random.default_rng(3)
    for shape in [(512, 512), (37, 61), (8, 9)]:
        a = (rng.gamma(2.0, 300.0, shape) + (rng.random(shape) < 0.05) * 2000).astype(dtype)
        sub = np.asarray(a[::S.STATS_STEP, ::S.STATS_STEP], np.float32)
        p0, p1, p50, p99, p100 = np.percentile(sub, [0.1, 1.0, 50.0, 99.0, 99.9])
        med, spread, degenerate, dark = S._frame_stats_dark(a)
        assert med == float(p50) and spread == max(float(p99 - p1), 1e-6 * max(abs(float(p50)), float(sub.max())))
        assert dark == float(np.mean(a[::S.STATS_STEP, ::S.STATS_STEP] < S.COLLIMATOR_DARK_FRACTION * med))
        assert not degenerate
    assert S._frame_stats(np.full((32, 32), 7, dtype))[2]                    # blank
    nan = rng.random((64, 64)).astype(np.float32)
    nan[::3, ::5] = np.nan
    fixed = np.nan_to_num(np.asarray(nan[::S.STATS_STEP, ::S.STATS_STEP]), nan=0.0)
    assert S._frame_stats(nan)[0] == float(np.percentile(fixed, 50.0))


def test_band_cells_are_the_cells_of_the_dilated_mask():
    import cv2

    from guidewire3d.xray import segmentation as S

    rng = np.random.default_rng(5)
    for shape in [(512, 512), (100, 131), (9, 17)]:
        for margin in (0, 5, 8, 12, 24, 72):
            m = np.zeros(shape, bool)
            for _ in range(rng.integers(1, 4)):
                v, u = rng.integers(0, shape[0]), rng.integers(0, shape[1])
                m[v:v + rng.integers(1, 30), u:u + rng.integers(1, 4)] = True
            k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * margin + 1, 2 * margin + 1))
            band = cv2.dilate(m.astype(np.uint8), k) > 0
            np.testing.assert_array_equal(S.band_cells(m, margin, 8), S._cells_of(band, 8))
    assert not S.band_cells(np.zeros((64, 64), bool), 24).any()


def test_crop_reflect_is_the_crop_of_the_reflect_padded_frame():
    from guidewire3d.xray import segmentation as S

    a = np.arange(40 * 53, dtype=np.float32).reshape(40, 53)
    c = 16
    padded = np.pad(a, c, mode="reflect")
    for v0, v1, u0, u1 in [(0, 40, 0, 53), (-16, 10, -16, 69), (30, 56, 40, 69), (5, 20, 7, 30), (-3, 2, 50, 60)]:
        np.testing.assert_array_equal(S._crop_reflect(a, v0, v1, u0, u1), padded[v0 + c:v1 + c, u0 + c:u1 + c])


def test_inner_border_test_on_the_boxes_union():
    from guidewire3d.xray import segmentation as S

    boxes = [(0, 0, 40, 24), (32, 16, 64, 64)]
    m = np.zeros((64, 100), bool)
    m[10, 0] = True                        # the frame's left border: not an inner border
    assert not S._touches_inner_border(m, boxes)
    m[10, 39] = True                       # box 1's right border, outside box 2
    assert S._touches_inner_border(m, boxes)
    m[10, 39] = False
    m[20, 39] = True                       # inside the union (box 2 covers it)
    assert not S._touches_inner_border(m, boxes)
    m[63, 50] = True                       # the frame's bottom border
    assert not S._touches_inner_border(m, boxes)
    m[40, 63] = True                       # box 2's right border, inside the frame
    assert S._touches_inner_border(m, boxes)


def _touches_inner_border_plain(mask, boxes):
    """The inner-border test as it was first written: on whole-frame arrays."""
    return bool(_inner_border_pixels_plain(mask, boxes).any())


def _inner_border_pixels_plain(mask, boxes):
    """The mask's pixels on the inner border of the boxes' union, on whole-frame arrays."""
    covered = np.zeros(mask.shape, bool)
    for u0, v0, u1, v1 in boxes:
        covered[v0:v1, u0:u1] = True
    inner = covered.copy()
    inner[1:, :] &= covered[:-1, :]
    inner[:-1, :] &= covered[1:, :]
    inner[:, 1:] &= covered[:, :-1]
    inner[:, :-1] &= covered[:, 1:]
    edge = covered & ~inner
    edge[0, :] = edge[-1, :] = False
    edge[:, 0] = edge[:, -1] = False
    return mask & edge


def test_inner_border_test_is_the_whole_frame_one():
    from guidewire3d.xray import segmentation as S

    rng = np.random.default_rng(11)
    agree = {True: 0, False: 0}
    for _ in range(400):
        h, w = int(rng.integers(9, 60)), int(rng.integers(9, 60))
        boxes = []
        for _ in range(int(rng.integers(1, 5))):
            u0, v0 = int(rng.integers(0, w - 1)), int(rng.integers(0, h - 1))
            boxes.append((u0, v0, int(rng.integers(u0 + 1, w + 1)), int(rng.integers(v0 + 1, h + 1))))
        covered = np.zeros((h, w), bool)
        for u0, v0, u1, v1 in boxes:
            covered[v0:v1, u0:u1] = True
        mask = covered & (rng.random((h, w)) < rng.choice([0.002, 0.02, 0.2]))
        want = _touches_inner_border_plain(mask, boxes)
        assert S._touches_inner_border(mask, boxes) == want, (boxes, np.argwhere(mask))
        touches = S._inner_border_touches(mask, boxes)
        np.testing.assert_array_equal(np.zeros_like(mask) if touches is None else touches,
                                      _inner_border_pixels_plain(mask, boxes))
        agree[want] += 1
    assert min(agree.values()) > 50          # both answers exercised
