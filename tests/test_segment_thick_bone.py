"""A 3DRA's bone is told from its thin arteries by thickness, not by level (stop 66;
``segment.VesselOptions.thick_bone_hu``, ``IntensityModel.thick_floor``).

In a 3D rotational angiogram the intra-arterial contrast (2500 HU) is brighter than bone (1000-1700 HU), and a thin
artery's partial volume puts its axis at the bone's level: the head phantom's 0.8 mm arteries at 0.7 mm voxels read
1550-2200 HU beside a petrous ridge at 1700. Before this stop no lumen lay below a quarter of the way from the bone
class to the contrast (1875 HU here), and the arteries beyond the first centimetres were lost (the selective 3DRA
``dra1`` of ``scripts/bench_head_cta.py``: 0.39 of its arteries; 0.87 now). The volume here: a wide artery (2 mm
radius) against a thick block of bone, a thin branch (0.8 mm) leaving it, whose end touches a thin plate of bone
(a skull's table, 2.1 mm), all at 0.7 mm with a 0.5 mm blur.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage as ndi

from guidewire3d import io
from guidewire3d.cta import segment, vesselmodel

SP = 0.7  # mm
SHAPE_ZYX = (60, 100, 100)  # 42 x 70 x 70 mm
WIDE_YX_MM = (35.0, 20.0)  # the wide artery's axis, along z
WIDE_RADIUS_MM = 2.0
THIN_Z_MM = 21.0  # the thin branch leaves it along +x, at this height
THIN_RADIUS_MM = 0.8
THIN_END_X_MM = 60.0
PLATE_X_MM = (60.5, 62.6)  # the thin plate, across y and z
BLOCK_X_MM = (4.0, 17.6)  # the thick block, beside the wide artery
BLOCK_Y_MM = (28.0, 42.0)
LEVELS = dict(tissue=40.0, contrast=2500.0, block=1700.0, plate=1400.0)


def _rotational_angiogram() -> io.Volume:
    z, y, x = np.meshgrid(*[SP * np.arange(n) for n in SHAPE_ZYX], indexing="ij", sparse=True)
    v = np.full(SHAPE_ZYX, LEVELS["tissue"], np.float32)
    v = np.where((x >= PLATE_X_MM[0]) & (x <= PLATE_X_MM[1]), np.float32(LEVELS["plate"]), v)
    block = (x >= BLOCK_X_MM[0]) & (x <= BLOCK_X_MM[1]) & (y >= BLOCK_Y_MM[0]) & (y <= BLOCK_Y_MM[1])
    v = np.where(block, np.float32(LEVELS["block"]), v)
    # the arteries' signed distance, and their partial volume over a voxel's width
    d_wide = np.hypot(y - WIDE_YX_MM[0], x - WIDE_YX_MM[1]) - WIDE_RADIUS_MM
    along = (x >= WIDE_YX_MM[1]) & (x <= THIN_END_X_MM)
    d_thin = np.where(along, np.hypot(y - WIDE_YX_MM[0], z - THIN_Z_MM), np.inf) - THIN_RADIUS_MM
    frac = np.clip(0.5 - np.minimum(d_wide, d_thin) / SP, 0.0, 1.0).astype(np.float32)
    v = v * (1 - frac) + LEVELS["contrast"] * frac
    v = ndi.gaussian_filter(v, 0.5 / SP).astype(np.float32)
    v += np.random.default_rng(0).normal(0, 12, SHAPE_ZYX).astype(np.float32)
    return io.Volume(v, (SP, SP, SP), (0.0, 0.0, 0.0), np.eye(3), source="rotational angiogram")


def _index(x_mm, y_mm, z_mm) -> tuple:
    return tuple(np.rint(np.asarray(c, float) / SP).astype(int) for c in (z_mm, y_mm, x_mm))


@pytest.fixture(scope="module")
def vol():
    return _rotational_angiogram()


@pytest.fixture(scope="module")
def model():
    """The reading of such a volume: its bone class (the floor) below the contrast, cut (``_brighter_reading``,
    ``_seeded_floor``)."""
    return vesselmodel.IntensityModel(background=LEVELS["tissue"], lumen=2400.0, noise=12.0, bone=None, hu=True,
                                      lumen_radius_mm=1.0, tubular_cm3=1.0, floor=LEVELS["block"], floor_cut=True)


def test_the_thin_branch_lies_at_the_bones_level(vol, model):
    """The case is the one meant: the thin branch's axis is below the floor's cut, the wide artery's above."""
    cut = model.floor + vesselmodel.LUMEN_BAND_FRACTION * (model.lumen - model.floor)
    xs = np.arange(WIDE_YX_MM[1] + 6.0, THIN_END_X_MM - 2.0, SP)
    axis = vol.array_zyx[_index(xs, WIDE_YX_MM[0], THIN_Z_MM)]
    assert np.median(axis) < cut < 2400.0
    assert model.thick_floor


def test_a_3dras_thin_branch_is_lumen_and_its_bone_is_not(vol, model):
    opt = model.vessel_options()
    assert np.isfinite(opt.thick_bone_hu) and opt.lumen_min_hu < model.floor
    seed = [(WIDE_YX_MM[1], WIDE_YX_MM[0], 5.0)]
    mask = segment.segment_vessels(vol, seeds_lps_mm=seed, options=opt)
    xs = np.arange(WIDE_YX_MM[1] + 4.0, THIN_END_X_MM - 1.0, SP)
    assert mask[_index(xs, WIDE_YX_MM[0], THIN_Z_MM)].mean() >= 0.95  # the thin branch, all along
    zs = np.arange(2.0, 40.0, SP)
    assert mask[_index(WIDE_YX_MM[1], WIDE_YX_MM[0], zs)].all()  # the wide artery
    block = mask[_index(BLOCK_X_MM[0] + 2.0, np.arange(BLOCK_Y_MM[0] + 2, BLOCK_Y_MM[1] - 2, SP)[:, None], zs)]
    assert not block.any()  # the thick block it lies against
    plate = mask[int(round(THIN_Z_MM / SP)) - 15:int(round(THIN_Z_MM / SP)) + 15, :,
                 int(round(PLATE_X_MM[0] / SP)) + 1:int(round(PLATE_X_MM[1] / SP))]
    assert plate.sum() <= 0.02 * plate.size  # the thin plate the branch's end touches: at most where it touches


def test_cut_by_level_the_thin_branch_was_lost(vol, model):
    """The reading before stop 66: no lumen below the floor's cut, anywhere."""
    opt = model.vessel_options()
    old = replace(opt, thick_bone_hu=float("inf"), thick_bone_max_hu=float("inf"),
                  lumen_min_hu=float(opt.thick_bone_max_hu))
    mask = segment.segment_vessels(vol, seeds_lps_mm=[(WIDE_YX_MM[1], WIDE_YX_MM[0], 5.0)], options=old)
    xs = np.arange(WIDE_YX_MM[1] + 6.0, THIN_END_X_MM - 1.0, SP)
    assert mask[_index(xs, WIDE_YX_MM[0], THIN_Z_MM)].mean() < 0.5
