"""Wires composited onto real backgrounds (scripts/realbg.py, the data of bench_wire_realbg.py and of
``train_guidewire.py --real-backgrounds``) against the simulator's truth, and the training sampler's
mix of simulated and composited crops."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

SEED = 7                 # a held-out simulator seed (< 1000)
HIGH_DOSE = 1e4          # quantum noise ~1 % of the signal at most
SUM_RTOL = 0.05          # the wire's absorbed fraction, summed over the image
FAR_ATOL = 0.03          # relative intensity away from the wire


def _scene():
    import realbg

    return realbg.simulator_wire(SEED, wire_diameter_mm=0.89, catheter=True, background=False, dose=1.0)


def test_composite_truth_is_the_simulators_and_the_wire_absorbs_what_it_should():
    import realbg
    from guidewire3d.phantom.xray import _gain_field
    from scipy import ndimage

    scene, sim = _scene()
    att, mask, uv, vis = realbg.wire_attenuation(np.random.default_rng(1), scene)
    # the truth is the simulator's own: same mask, same projected points
    assert np.array_equal(mask, sim.wire_mask[0])
    assert np.allclose(uv, sim.wire_uv_px[0]) and np.array_equal(vis, sim.wire_visible[0])
    assert len(scene.catheter_lps_mm) >= 2            # the catheter is rendered too (outside the mask)
    # a flat background: the exposed frame divided by the gain field and the flat level is the
    # blurred transmission, so sum(1 - I / I0) = sum(1 - exp(-att)) (blur keeps sums), and I = I0 far
    # from the wire and catheter
    c = realbg.composite(np.random.default_rng(1), np.zeros(realbg.SHAPE, np.float32), scene, dose=HIGH_DOSE)
    assert np.array_equal(c.mask, mask)
    rel = c.frame / _gain_field(realbg.SHAPE)
    far = ~ndimage.binary_dilation(att > 0, iterations=6)
    rel = rel / np.median(rel[far])
    assert np.max(np.abs(np.median(rel[far]) - 1)) < FAR_ATOL and np.mean(np.abs(rel[far] - 1)) < FAR_ATOL
    absorbed = float(np.sum(1 - np.exp(-att)))
    assert abs(float(np.sum(1 - rel)) - absorbed) < SUM_RTOL * absorbed


def test_composite_adds_the_wire_to_the_background():
    """Attenuations add: the frame on a background of attenuation ``b`` is ``exp(-b)`` times the frame
    on none, the wire included (the same exposure draws, high dose)."""
    import realbg

    scene, _ = _scene()
    b = 0.8
    c0 = realbg.composite(np.random.default_rng(5), np.zeros(realbg.SHAPE, np.float32), scene, dose=HIGH_DOSE)
    c1 = realbg.composite(np.random.default_rng(5), np.full(realbg.SHAPE, b, np.float32), scene, dose=HIGH_DOSE)
    ratio = c1.frame / c0.frame
    assert abs(float(np.median(ratio)) - np.exp(-b)) < 0.01 * np.exp(-b)
    assert abs(float(np.median(ratio[c0.mask])) - np.exp(-b)) < 0.03 * np.exp(-b)
    # and the wire stays darker than its surroundings on the background
    assert np.median(c1.frame[c1.mask]) < 0.9 * np.median(c1.frame)


def test_angiogram_attenuation_is_relative_to_the_median_and_gain_free():
    import realbg

    rng = np.random.default_rng(0)
    img = rng.uniform(20, 200, (300, 300)).astype(np.float32)
    a = realbg.angiogram_attenuation(img)
    assert a.shape == realbg.SHAPE
    assert abs(float(np.median(a))) < 1e-3
    assert np.allclose(realbg.angiogram_attenuation(3.0 * img), a, atol=1e-5)
    # same size: exactly -ln(I / median); darker = more attenuation
    b = realbg.angiogram_attenuation(img, shape=img.shape)
    assert np.allclose(b, -np.log(img / np.median(img)), atol=1e-5)
    assert b[np.unravel_index(np.argmin(img), img.shape)] == b.max()


def test_training_composites_masks_are_the_turned_truth():
    import realbg

    scene, sim = _scene()
    truth = np.asarray(sim.wire_mask[0])
    turned = [realbg._d4(truth, k, f) for k in range(4) for f in (False, True)]
    bgs = [np.zeros(realbg.SHAPE, np.float32), np.full(realbg.SHAPE, 0.5, np.float32)]
    frames, masks = realbg.training_composites(np.random.default_rng(0), bgs, [scene], per_background=3,
                                               negatives_per_background=1)
    assert len(frames) == len(masks) == 8
    for i, m in enumerate(masks):
        if i % 4 == 3:
            assert not m.any()
        else:
            assert any(np.array_equal(m, t) for t in turned)
            # the wire is darker than the frame around it
            assert np.median(frames[i][m]) < 0.9 * np.median(frames[i])


def test_sample_batch_draws_the_real_fraction_from_the_composites():
    import train_guidewire as tg

    shape = (64, 64)
    sim = ([np.full(shape, -2.0, np.float16)] * 3, [np.zeros(shape, bool)] * 3)
    real = ([np.full(shape, 2.0, np.float16)] * 2, [np.zeros(shape, bool)] * 2)
    for frac, lo, hi in ((0.0, 0, 0), (1.0, 400, 400), (0.3, 90, 150)):   # 400 crops: 0.3 -> 120 +- 3 sigma
        xb, _ = tg.sample_batch(np.random.default_rng(1), *sim, 400, 32, real=real, real_fraction=frac)
        n_real = int(np.sum(xb.mean(axis=(1, 2, 3)) > 0))
        assert lo <= n_real <= hi
