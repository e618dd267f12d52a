"""The vessel stage's blob rule (issue 17): a chamber thicker than the widest vessel is cut off, a tube whose radius
exceeds that limit at a voxel or two (the ascending aorta against 16 mm, through partial volume) is not."""
from __future__ import annotations

import numpy as np
import pytest

from guidewire3d import io
from guidewire3d.cta import segment
from guidewire3d.cta.segment import VesselOptions, segment_vessels

SP_ZYX = np.array([1.0, 1.0, 1.0])
RADIUS_MM = 5.2          # the blob rule's limit (max_vessel_radius_mm)
TUBE_MM = 4.0            # the tube, narrower than the limit ...
WIDE_MM = 4.6            # ... and a stretch of it about as wide as the limit (its axis 5.0 mm deep: a ridge, no core)
BULGE_MM = 5.6           # ... with a local widening whose centre is deeper than the limit (a core of a few voxels)
CHAMBER_MM = 9.0         # a chamber at the tube's end: a blob
SHAPE = (72, 36, 36)
AXIS_YX = (18.0, 18.0)
WIDE_Z = (14, 40)
BULGE_Z = 27
CHAMBER_Z = 56
KEPT_MIN = 0.99          # fraction of the tube's lumen away from the chamber that the rule must keep
CHAMBER_REMOVED_MIN = 0.9


def _scene():
    """``(mask, tube, chamber)``: a tube along z (radius TUBE_MM, WIDE_MM on WIDE_Z, a ball of BULGE_MM at
    BULGE_Z) entering a ball of CHAMBER_MM; ``tube`` its voxels farther than the rule's reach (the limit plus a
    voxel) from the chamber's core, ``chamber`` the ball's voxels."""
    z, y, x = np.meshgrid(*[np.arange(n, dtype=float) for n in SHAPE], indexing="ij")
    rho = np.hypot(y - AXIS_YX[0], x - AXIS_YX[1])
    r_tube = np.where((z >= WIDE_Z[0]) & (z < WIDE_Z[1]), WIDE_MM, TUBE_MM)
    tube = (rho <= r_tube) & (z >= 2) & (z <= CHAMBER_Z)
    bulge = np.sqrt(rho ** 2 + (z - BULGE_Z) ** 2) <= BULGE_MM
    chamber = np.sqrt(rho ** 2 + (z - CHAMBER_Z) ** 2) <= CHAMBER_MM
    mask = tube | bulge | chamber
    reach = CHAMBER_MM - RADIUS_MM + RADIUS_MM + SP_ZYX.max() + 1.0   # the chamber's core dilated, plus a voxel
    far = np.sqrt(rho ** 2 + (z - CHAMBER_Z) ** 2) > reach
    return mask, (tube | bulge) & far, chamber


def test_scene_has_a_tube_core_and_a_chamber_core():
    """The scene is what the tests below need: voxels deeper than the limit at the bulge and in the chamber only."""
    mask, _, chamber = _scene()
    thick = segment._deeper_than(mask, RADIUS_MM, SP_ZYX)
    z = np.argwhere(thick)[:, 0]
    at_bulge = np.abs(z - BULGE_Z) <= 1
    assert at_bulge.any() and (~at_bulge).any()
    assert chamber[thick].sum() == (~at_bulge).sum()


def test_the_tube_core_is_not_a_blob_but_the_chamber_is():
    """The tube's lumen survives the blob rule, the bulge included; the chamber's deep part is cut off."""
    mask, tube, chamber = _scene()
    zone = segment._blob_zone(mask, RADIUS_MM, SP_ZYX)
    assert 1.0 - zone[tube].mean() >= KEPT_MIN
    deep = segment._deeper_than(mask, RADIUS_MM, SP_ZYX) & chamber
    assert zone[deep].all()
    assert zone[chamber].mean() >= CHAMBER_REMOVED_MIN


def test_a_vessel_wider_than_the_limit_by_more_than_a_voxel_is_a_blob():
    """A cylinder of radius limit + 2 voxels: its ridge is as wide as a chamber's, all of it is removed."""
    z, y, x = np.meshgrid(*[np.arange(n, dtype=float) for n in (60, 30, 30)], indexing="ij")
    cyl = (np.hypot(y - 15.0, x - 15.0) <= RADIUS_MM + 2.0) & (z >= 5) & (z < 55)
    zone = segment._blob_zone(cyl, RADIUS_MM, SP_ZYX)
    assert zone[cyl & (z >= 15) & (z < 45)].all()


def test_the_rule_without_cores_removes_nothing():
    mask, _, _ = _scene()
    assert not segment._blob_zone(mask, CHAMBER_MM + 1.0, SP_ZYX).any()


@pytest.mark.parametrize("chamber", [True, False])
def test_segment_vessels_keeps_the_tube_lumen_at_its_core(chamber):
    """End to end on a CT of the scene (lumen 400 HU on 40 HU tissue, noise 10 HU): the segmented mask holds
    the tube's lumen around the bulge (the old rule removed it over the limit plus a voxel either side)."""
    mask, tube, ch = _scene()
    if not chamber:
        mask = mask & ~ch
    rng = np.random.default_rng(3)
    hu = np.where(mask, 400.0, 40.0) + rng.normal(0.0, 10.0, mask.shape)
    vol = io.Volume(hu.astype(np.float32), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), np.eye(3), source="blob scene")
    out = segment_vessels(vol, options=VesselOptions(max_vessel_radius_mm=RADIUS_MM))
    z = np.arange(SHAPE[0])[:, None, None]
    near_bulge = tube & (np.abs(z - BULGE_Z) <= RADIUS_MM + 1.0)
    assert out[near_bulge].mean() >= 0.9
    if chamber:
        assert not out[segment._deeper_than(mask, RADIUS_MM, SP_ZYX) & ch].any()
