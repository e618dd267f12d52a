"""The real-anatomy benchmark's X-ray renderer (scripts/real_anatomy.py), without its 40 MB CT:
line integrals through a voxelised tube equal the simulator's exact tube chords, whatever the
volume's axis directions, and cropping / block-averaging the volume changes nothing."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))


@pytest.mark.parametrize("direction", [np.eye(3), np.diag([1.0, -1.0, 1.0])])
def test_ray_integral_matches_tube_chords(direction):
    import real_anatomy as ra
    from guidewire3d import io
    from guidewire3d.geometry import CArm, Pose
    from guidewire3d.phantom.xray import render_tube_line_integral

    n, sp = 96, 0.5
    origin = np.array([-24.0, 24.0 if direction[1, 1] < 0 else -24.0, -24.0])
    vol = io.Volume(np.zeros((n, n, n), np.float32), (sp, sp, sp), origin, direction, source="tube")
    # a tube of radius 6 mm along (1, 0.3, 1), through the volume's centre, sampled at sub-voxels
    centre = vol.index_zyx_to_lps(np.array([[(n - 1) / 2] * 3]))[0]
    axis = np.array([1.0, 0.3, 1.0]) / np.linalg.norm([1.0, 0.3, 1.0])
    zz, yy, xx = np.meshgrid(*[np.arange(n)] * 3, indexing="ij")
    frac = np.zeros((n, n, n), np.float32)
    o = (-0.25, 0.25)  # 2 x 2 x 2 sub-voxel samples: the lumen fraction of each voxel
    for dz in o:
        for dy in o:
            for dx in o:
                p = vol.index_zyx_to_lps(np.column_stack([(zz + dz).ravel(), (yy + dy).ravel(), (xx + dx).ravel()]))
                r = np.linalg.norm(np.cross(p - centre, axis), axis=1)
                frac += (r <= 6.0).reshape(frac.shape) / 8.0
    carm = CArm(20.0, -10.0, 1000.0, 700.0, 0.6, (96, 96))
    pose = Pose(np.eye(3), -centre)
    L = ra.ray_integral(carm, pose, frac, vol, step_mm=0.25)
    ends = centre + np.array([-40.0, 40.0])[:, None] * axis  # beyond the volume: clipped by it
    tube = np.linspace(ends[0], ends[1], 81)
    T = render_tube_line_integral(carm, pose, [(tube, np.full(len(tube), 6.0))], supersample=3)
    core = T > 8.0  # well inside the tube's projection, where the volume holds the whole chord
    assert core.sum() > 100
    assert np.median(np.abs(L[core] - T[core]) / T[core]) < 0.03
    # cropped and block-averaged copies give the same integrals
    lo = np.argwhere(frac > 0).min(0)
    Lc = ra.ray_integral(carm, pose, np.ascontiguousarray(frac[lo[0]:, lo[1]:, lo[2]:]), vol, step_mm=0.25,
                         offset_zyx=lo)
    assert np.allclose(Lc, L, atol=0.05 * L.max())
    half = frac.reshape(n, n // 2, 2, n // 2, 2).mean(axis=(2, 4))
    Lh = ra.ray_integral(carm, pose, half, vol, step_mm=0.25, offset_zyx=(0.0, 0.5, 0.5), factor_zyx=(1, 2, 2))
    assert np.median(np.abs(Lh[core] - L[core]) / L[core]) < 0.03
