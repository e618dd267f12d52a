"""Model-based guidewire mask: rendering against the simulator's truth masks, radius estimation,
the catheter / loop handling, and ``guidewire_mask(..., wire_model=True)``."""
from __future__ import annotations

import numpy as np
import pytest

from guidewire3d.errors import InputError
from guidewire3d.metrics import dice
from guidewire3d.phantom import PhantomOptions, simulate
from guidewire3d.xray.segmentation import GuidewireSegmenter, SegMethod, guidewire_mask
from guidewire3d.xray.wiremask import (
    RESIDUAL_MIN_PX,
    model_wire_mask,
    projected_wire_radius_px,
    render_wire_mask,
    wire_radius_px,
    wire_width_profile_px,
)

HELD_OUT_SEED = 21            # simulator seeds < 1000 are never trained on
RENDER_MIN_DICE = 0.98        # tube of the true radius around the true projection vs the truth mask
RADIUS_TOL_PX = 0.1           # estimated vs rendered radius
UNET_WIRE_MIN_DICE = 0.92     # 0.014" wire, radius from the wire's diameter and the C-arm geometry
SHAPE = (160, 200)


@pytest.fixture(scope="module")
def sims():
    return {d: simulate(PhantomOptions(seed=HELD_OUT_SEED, n_frames=3, wire_diameter_mm=d, dose=1.0), make_ct=False)
            for d in (0.36, 0.89)}


def _arc(n=240, r=70.0, centre=(100.0, 120.0), a0=0.3, a1=2.6):
    a = np.linspace(a0, a1, n)
    return np.column_stack([centre[0] + r * np.cos(a), centre[1] - r * np.sin(a)])


@pytest.mark.parametrize("diameter", [0.36, 0.89])
def test_render_reproduces_the_simulators_truth_mask(sims, diameter):
    """The tube of the wire's true projected radius around its true projection is the simulator's
    truth mask (the same partial-volume rule); a 20 % wrong radius is clearly worse."""
    sim = sims[diameter]
    uv, depth = sim.carm.project(sim.wire_lps_mm[0], sim.pose, return_depth=True)
    r_true = 0.5 * diameter * sim.carm.focal_px / float(np.median(depth))
    truth = sim.wire_mask[0]
    d = dice(render_wire_mask(uv, r_true, truth.shape), truth)
    assert d >= RENDER_MIN_DICE
    assert dice(render_wire_mask(uv, 1.2 * r_true, truth.shape), truth) < d - 0.02
    assert dice(render_wire_mask(uv, 0.8 * r_true, truth.shape), truth) < d - 0.02


def test_projected_radius_is_the_isocentre_magnification(sims):
    sim = sims[0.36]
    r = projected_wire_radius_px(sim.carm, 0.36)
    assert r == pytest.approx(0.18 * sim.carm.focal_px / sim.carm.sod_mm, rel=1e-12)
    # the simulated wire lies near the isocentre: the true radius is within 10 %
    _, depth = sim.carm.project(sim.wire_lps_mm[0], sim.pose, return_depth=True)
    assert r == pytest.approx(0.18 * sim.carm.focal_px / np.median(depth), rel=0.1)
    with pytest.raises(InputError, match="wire_diameter_mm"):
        projected_wire_radius_px(sim.carm, 0.0)


@pytest.mark.parametrize("radius", [0.8, 1.3, 2.7])
def test_radius_estimate_recovers_a_rendered_tube(radius):
    uv = _arc()
    mask = render_wire_mask(uv, radius, SHAPE)
    assert wire_radius_px(mask, uv) == pytest.approx(radius, abs=RADIUS_TOL_PX)
    # a soft map of the same width gives the same answer
    assert wire_radius_px(mask.astype(np.float32), uv) == pytest.approx(radius, abs=RADIUS_TOL_PX)
    w = wire_width_profile_px(mask, uv)
    assert np.median(w) == pytest.approx(2 * radius + 0.3, abs=0.5)   # ~2 r + partial-volume rim


def test_model_mask_drops_a_catheter_blob_and_keeps_a_second_wire_stretch():
    """Where the segmentation is too wide (a catheter around the wire) the rendered tube replaces it;
    a long segmented stretch away from the traced path (a loop) is kept; a small speck is dropped."""
    uv = _arc()
    tube = render_wire_mask(uv, 1.0, SHAPE)
    vv, uu = np.mgrid[:SHAPE[0], :SHAPE[1]]
    blob = (uu - uv[40, 0]) ** 2 + (vv - uv[40, 1]) ** 2 <= 4.5 ** 2
    loop_uv = np.column_stack([np.linspace(20, 180, 100), np.full(100, 150.0)])
    loop = render_wire_mask(loop_uv, 1.0, SHAPE)
    speck = (uu >= 100) & (uu < 104) & (vv >= 100) & (vv < 104)
    assert speck.sum() < RESIDUAL_MIN_PX
    seg = tube | blob | loop | speck
    out = model_wire_mask(seg, uv, radius_px=1.0)
    assert np.array_equal(out.tube, tube)
    assert np.array_equal(out.mask, tube | loop)
    # estimated radius: the blob covers a few profiles only, the median ignores it
    est = model_wire_mask(seg, uv)
    assert est.radius_px == pytest.approx(1.0, abs=RADIUS_TOL_PX)


@pytest.mark.parametrize("method", list(SegMethod))
def test_wire_model_beats_the_pixel_mask_on_a_thin_wire(sims, method):
    sim = sims[0.36]
    r = projected_wire_radius_px(sim.carm, 0.36)
    plain, model, est = [], [], []
    for f, truth in zip(sim.frames, sim.wire_mask):
        plain.append(dice(guidewire_mask(f, method=method), truth))
        model.append(dice(guidewire_mask(f, method=method, wire_model=True, wire_radius_px=r), truth))
        est.append(dice(guidewire_mask(f, method=method, wire_model=True), truth))
    if method is SegMethod.UNET:
        assert np.mean(model) >= UNET_WIRE_MIN_DICE
    assert np.mean(model) > np.mean(plain)
    assert np.mean(est) > np.mean(plain)
    # the tracker returns the same model mask
    seg = GuidewireSegmenter(method=method, wire_model=True, wire_radius_px=r)
    for f in sim.frames:
        assert dice(seg.segment(f), guidewire_mask(f, method=method, wire_model=True, wire_radius_px=r)) >= 0.97


def test_bad_input_raises():
    uv = _arc()
    with pytest.raises(InputError, match="points_uv_px"):
        render_wire_mask(uv[:1], 1.0, SHAPE)
    with pytest.raises(InputError, match="points_uv_px"):
        render_wire_mask(np.where(np.arange(len(uv))[:, None] == 3, np.nan, uv), 1.0, SHAPE)
    with pytest.raises(InputError, match="zero length"):
        render_wire_mask(np.repeat(uv[:1], 5, axis=0), 1.0, SHAPE)
    with pytest.raises(InputError, match="radius_px"):
        render_wire_mask(uv, 0.0, SHAPE)
    with pytest.raises(InputError, match="shape"):
        render_wire_mask(uv, 1.0, (0, 10))
    with pytest.raises(InputError, match="seg"):
        wire_radius_px(np.zeros(10), uv)
    with pytest.raises(InputError, match="width_seg"):
        model_wire_mask(np.zeros(SHAPE, bool), uv, width_seg=np.zeros((5, 5)))
    with pytest.raises(InputError, match="radius_px"):
        model_wire_mask(np.zeros(SHAPE, bool), uv, radius_px=-2.0)
    with pytest.raises(InputError, match="wire_radius_px"):
        guidewire_mask(np.ones((64, 64)), wire_model=True, wire_radius_px=-1.0)
    with pytest.raises(InputError, match="wire_radius_px"):
        GuidewireSegmenter(wire_model=True, wire_radius_px=float("nan"))
