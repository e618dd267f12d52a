"""Seeds in separate vessel structures (found at stop 43 on the head phantom of ``scripts/bench_head_cta.py``).

The tree is one connected structure, the first seed's. A second seed in the other carotid system (a circle of Willis
broken at the threshold) had its lumen in the mask and the surface but not in the tree, and ``vessels`` exited 0
without a word. Now it is a one-line refusal naming the seed; seeds in one structure are unchanged.
"""
from __future__ import annotations

import numpy as np
import pytest

from guidewire3d import io
from guidewire3d.cta import vessels3d
from guidewire3d.errors import SegmentationError

SPACING_MM = 0.5
RADIUS_MM = 2.0
APART_MM = 20.0  # between the two tubes' axes


def _two_tubes() -> io.Volume:
    """Two straight parallel tubes (400 HU, radius 2 mm) along z in 40 HU tissue, 20 mm apart, with noise."""
    n = (60, 80, 80)
    z, y, x = np.meshgrid(*[SPACING_MM * np.arange(k) for k in n], indexing="ij", sparse=True)
    v = np.full(n, 40.0, np.float32)
    for xc in (10.0, 10.0 + APART_MM):
        r = np.sqrt((x - xc) ** 2 + (y - 20.0) ** 2)
        v += (360.0 * np.clip(RADIUS_MM + 0.5 * SPACING_MM - r, 0, SPACING_MM) / SPACING_MM).astype(np.float32)
    v += np.random.default_rng(0).normal(0, 10, n).astype(np.float32)
    return io.Volume(v, (SPACING_MM,) * 3, (0.0, 0.0, 0.0), np.eye(3), source="two tubes")


def test_a_seed_in_a_separate_structure_is_refused_naming_it():
    vol = _two_tubes()
    with pytest.raises(SegmentationError, match=r"--seed-lps=30,20,15 lies in a vessel structure apart from the first"):
        vessels3d.extract_vessels(vol, seeds_lps_mm=[[10.0, 20.0, 15.0], [30.0, 20.0, 15.0]])


def test_seeds_in_one_structure_give_its_tree():
    vol = _two_tubes()
    one = vessels3d.extract_vessels(vol, seeds_lps_mm=[[10.0, 20.0, 5.0], [10.0, 20.0, 25.0]])
    p = one.tree.points_lps_mm
    assert np.all(np.abs(p[:, 0] - 10.0) < 1.0)  # the first tube's axis only
    assert p[:, 2].max() - p[:, 2].min() > 20.0
