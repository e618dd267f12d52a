import numpy as np
import pytest

from guidewire3d.errors import GeometryError
from guidewire3d.geometry import CArm, Pose, nominal_pose, so3_exp, so3_log

ATOL = 1e-9
rng = np.random.default_rng(1234)


def _random_pose(rng, rot_deg=40.0, trans_mm=50.0):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return Pose(so3_exp(axis * np.radians(rng.uniform(-rot_deg, rot_deg))), rng.uniform(-trans_mm, trans_mm, 3))


def test_se3_exp_log_round_trip():
    for _ in range(50):
        xi = np.r_[rng.uniform(-50, 50, 3), rng.uniform(-1.5, 1.5, 3)]
        assert np.allclose(Pose.exp(xi).log(), xi, atol=1e-8)
        T = _random_pose(rng)
        assert T.allclose(Pose.exp(T.log()), atol_mm=1e-8, atol_rad=1e-9)


def test_se3_log_near_pi():
    R = so3_exp(np.array([0.0, 0.0, np.pi - 1e-9]))
    assert np.allclose(so3_exp(so3_log(R)), R, atol=1e-6)


def test_se3_inverse_compose_apply():
    T, U = _random_pose(rng), _random_pose(rng)
    assert (T @ T.inverse()).allclose(Pose.identity(), atol_mm=1e-10, atol_rad=1e-10)
    p = rng.normal(size=(20, 3)) * 30
    assert np.allclose((T @ U).apply(p), T.apply(U.apply(p)), atol=ATOL)
    assert np.allclose(T.inverse().apply(T.apply(p)), p, atol=1e-9)
    assert np.isclose(np.linalg.det(T.R), 1.0)


def test_pose_is_frozen_and_inputs_untouched():
    R = np.eye(3)
    T = Pose(R, np.zeros(3))
    with pytest.raises(ValueError):
        T.R[0, 0] = 2.0
    p = np.ones((3, 3))
    T.apply(p)
    assert np.array_equal(p, np.ones((3, 3)))


def test_pose_rejects_non_rotation():
    with pytest.raises(GeometryError, match="rotation"):
        Pose(np.diag([1.0, 1.0, -1.0]), np.zeros(3))


def test_axes_det_is_minus_one_and_orthonormal():
    for a, b in [(0, 0), (30, 20), (-40, -25), (90, 0)]:
        R = CArm(a, b, 1100, 750, 0.3, (512, 512)).axes
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(R), -1.0)


def test_ap_view_orientation():
    """AP: patient left (+x LPS) -> +u, feet (-z LPS) -> +v; beam anterior -> posterior (+y)."""
    c = CArm(0, 0, 1000, 700, 0.25, (512, 512))
    assert np.allclose(c.beam_direction, [0, -1, 0])
    pose = Pose.identity()
    uv0 = c.project(np.zeros(3), pose)
    assert np.allclose(uv0, [255.5, 255.5])
    left = c.project(np.array([10.0, 0, 0]), pose)
    feet = c.project(np.array([0, 0, -10.0]), pose)
    assert left[0] > uv0[0] and np.isclose(left[1], uv0[1])
    assert feet[1] > uv0[1] and np.isclose(feet[0], uv0[0])
    # magnification at iso: 10 mm -> 10 * SID/SOD / pixel px
    assert np.isclose(left[0] - uv0[0], 10 * 1000 / 700 / 0.25)


def test_lao30_cra20_hand_computed():
    """Hand computation from DESIGN.md's formulas, for one point."""
    a, b = np.radians(30), np.radians(20)
    sid, sod, ps = 1100.0, 750.0, 0.3
    d = np.array([np.sin(a) * np.cos(b), -np.cos(a) * np.cos(b), np.sin(b)])
    e_u = np.array([np.cos(a), np.sin(a), 0])
    e_v = np.array([np.sin(b) * np.sin(a), -np.sin(b) * np.cos(a), -np.cos(b)])
    iso = np.array([5.0, -12.0, 40.0])
    X = np.array([25.0, 3.0, 10.0])
    S = iso - sod * d
    D = iso + (sid - sod) * d
    hit = S + sid / ((X - S) @ d) * (X - S)
    u = (512 - 1) / 2 + (hit - D) @ e_u / ps
    v = (512 - 1) / 2 + (hit - D) @ e_v / ps
    c = CArm(30, 20, sid, sod, ps, (512, 512))
    uv = c.project(X, nominal_pose(iso))
    assert np.allclose(uv, [u, v], atol=1e-9)
    P = c.projection_matrix(nominal_pose(iso))
    h = P @ np.r_[X, 1.0]
    assert np.allclose(h[:2] / h[2], [u, v], atol=1e-9)
    # numbers written out once, so a change in the convention is caught even if both sides drift
    assert np.allclose(uv, [u, v])
    assert np.allclose(c.source_lps_mm(nominal_pose(iso)), S)


def test_project_backproject_identity():
    c = CArm(-25, 15, 1200, 800, 0.2, (480, 640))
    pose = _random_pose(rng, 5, 20)
    uv = rng.uniform([0, 0], [640, 480], size=(100, 2))
    z = rng.uniform(600, 1000, 100)
    X = c.backproject(uv, z, pose)
    uv2, z2 = c.project(X, pose, return_depth=True)
    assert np.allclose(uv2, uv, atol=1e-8) and np.allclose(z2, z, atol=1e-8)
    o, dirs = c.rays(uv, pose)
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
    assert np.allclose(c.project(o + 500 * dirs, pose), uv, atol=1e-8)
    assert np.allclose(o[0], c.source_lps_mm(pose))


def test_detector_corners_project_to_image_corners():
    c = CArm(20, -10, 1000, 700, 0.3, (256, 300))
    pose = _random_pose(rng, 5, 20)
    uv = c.project(c.detector_corners_lps_mm(pose), pose)
    assert np.allclose(uv, [[-0.5, -0.5], [299.5, -0.5], [299.5, 255.5], [-0.5, 255.5]], atol=1e-8)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(sid_mm=700, sod_mm=750), "DistanceSourceToDetector must exceed"),
        (dict(pixel_mm=0), "ImagerPixelSpacing"),
        (dict(sod_mm=-1), "DistanceSourceToPatient"),
        (dict(secondary_deg=120), "angles out of range"),
        (dict(shape=(1, 512)), "shape"),
    ],
)
def test_impossible_geometry_raises(kwargs, match):
    base = dict(primary_deg=0, secondary_deg=0, sid_mm=1100, sod_mm=750, pixel_mm=0.3, shape=(512, 512))
    base.update(kwargs)
    with pytest.raises(GeometryError, match=match):
        CArm(**base)


def test_carm_dict_round_trip():
    c = CArm(12.5, -7, 1050, 720, 0.31, (512, 512))
    c2 = CArm.from_dict(c.to_dict())
    assert np.allclose(c.projection_matrix(), c2.projection_matrix())
