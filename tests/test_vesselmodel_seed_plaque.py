"""A seed in a CT's contrast lumen beside a calcified plaque reads the lumen, not the plaque.

The seeds' own intensity model (used when the automatic stage refuses a volume, as it refuses a tight crop around
the heart, or when its tree misses the seed) reads the lumen level where a steepest ascent from the seed ends. Next
to a calcified plaque (1200 HU at the wall of a 400 HU lumen) the ascent climbed into the plaque and read 614 HU:
every threshold of the volume then moved with it. In a CT in HU, a seed below ``HU_LUMEN_MAX`` now neither climbs
into nor reads what lies at or above that level, or within ``SEED_CEILING_MARGIN_MM`` of it.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage as ndi

from guidewire3d import io
from guidewire3d.cta import vesselmodel

SPACING_MM = 0.5
N = 96
LUMEN_HU, TISSUE_HU, PLAQUE_HU = 400.0, 40.0, 1200.0


def _tube_ct(plaque_hu: float | None) -> tuple[io.Volume, float]:
    """A 2 mm radius lumen along z through a 48 mm cube of tissue (a CT in HU, 0.4 mm blur, 10 HU noise), with a
    1.5 mm ball of ``plaque_hu`` centred on its wall at mid-height; returns the volume and the axis' x = y (mm)."""
    h = SPACING_MM
    z, y, x = np.meshgrid(*(np.arange(N) * h,) * 3, indexing="ij", sparse=True)
    c = N * h / 2
    v = np.full((N, N, N), TISSUE_HU, np.float32)
    v[np.broadcast_to(np.hypot(x - c, y - c) < 2.0, v.shape)] = LUMEN_HU
    if plaque_hu is not None:
        v[np.broadcast_to(np.sqrt((x - (c + 2.0)) ** 2 + (y - c) ** 2 + (z - c) ** 2) < 1.5, v.shape)] = plaque_hu
    v = ndi.gaussian_filter(v, 0.4 / h) + np.random.default_rng(0).normal(0, 10, v.shape).astype(np.float32)
    return io.Volume(v.astype(np.float32), (h, h, h), (0.0, 0.0, 0.0), np.eye(3), source="plaque phantom"), c


@pytest.mark.parametrize("offset_mm", [-1.0, 0.0])
def test_a_seed_beside_a_plaque_reads_the_lumen(offset_mm):
    clean, c = _tube_ct(None)
    plaqued, _ = _tube_ct(PLAQUE_HU)
    seed = [(c + offset_mm, c, c)]  # LPS x, y, z: 1-2 mm from the plaque's edge, inside the lumen
    ref = vesselmodel.estimate_intensity_model(clean, seeds_lps_mm=seed).lumen
    got = vesselmodel.estimate_intensity_model(plaqued, seeds_lps_mm=seed)
    assert abs(ref - LUMEN_HU) < 0.1 * (LUMEN_HU - TISSUE_HU), ref
    # the plaque does not move the level (before: 614 HU)
    assert abs(got.lumen - ref) < 0.05 * (LUMEN_HU - TISSUE_HU), (got.lumen, ref)
    assert got.bone is not None and got.bone < PLAQUE_HU


def test_a_seed_inside_the_plaque_is_not_moved_out_of_it():
    """The rule is for a seed in a contrast lumen: a seed whose own voxel is at or above ``HU_LUMEN_MAX`` (here the
    plaque itself) reads where it lies, as before (612 HU)."""
    plaqued, c = _tube_ct(PLAQUE_HU)
    got = vesselmodel.estimate_intensity_model(plaqued, seeds_lps_mm=[(c + 2.0, c, c)])
    assert got.lumen > LUMEN_HU + 0.5 * (LUMEN_HU - TISSUE_HU)


def test_the_seeded_tree_leaves_the_plaque_out():
    """The whole chain from such a seed: the tree runs the cube's length and no plaque voxel is lumen."""
    plaqued, c = _tube_ct(PLAQUE_HU)
    r = vesselmodel.extract_vessels_auto(plaqued, seeds_lps_mm=[(c - 1.0, c, c)])
    assert r.vessels.tree.total_length_mm > 0.8 * N * SPACING_MM
    assert not np.any(r.vessels.mask_zyx & (plaqued.array_zyx >= vesselmodel.HU_LUMEN_MAX))


def test_a_seed_wholly_inside_a_plaques_shell_still_reads_a_level():
    """A seed whose whole 1.5 mm box lies within ``SEED_CEILING_MARGIN_MM`` of voxels at or above ``HU_LUMEN_MAX`` (a
    ring of calcification around it) reads the box as it is rather than a level of nothing."""
    h, n = SPACING_MM, 40
    v = np.full((n, n, n), TISSUE_HU, np.float32)
    v[::4, :, :] = PLAQUE_HU  # calcified sheets 2 mm apart: every voxel within 1 mm of one above 650 HU
    seed = np.array([21.0, 20.0, 20.0])  # between two sheets, its smoothed value about 230 HU: a ceiling applies
    c, level = vesselmodel._seed_lumen_level(v, seed, np.full(3, h), hu=True)
    assert np.isfinite(level) and level > TISSUE_HU
