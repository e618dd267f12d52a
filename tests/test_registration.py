"""Tests of the 3D-2D registration (issue 6) on small synthetic trees with known poses."""
import json

import numpy as np
import pytest

from guidewire3d import registration as reg
from guidewire3d.registration import model, problem, search, verdict
from guidewire3d.errors import InputError
from guidewire3d.geometry import CArm, Pose, nominal_pose, so3_log
from guidewire3d.metrics import mtre_mm, resample_polyline
from guidewire3d.vesseltree import VesselTree

EXACT_MM = 0.3  # noise-free recovery (depth along the beam is the weakest direction)
RECOVER_MM = 1.0
RECOVER_DEG = 0.5
INPLANE_MM = 0.3
ROUND_TRIP_MM = 0.5
GRADIENT_RTOL = 1e-4  # analytic vs central-difference gradient, relative to its largest entry


def _curve(rng, start, direction, length_mm, step=1.0, curl=0.08):
    pts = [np.asarray(start, float)]
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    w = np.zeros(3)
    for _ in range(int(length_mm / step)):
        w = 0.85 * w + rng.normal(scale=curl, size=3)
        d = d + 0.3 * step * w
        d /= np.linalg.norm(d)
        pts.append(pts[-1] + step * d)
    return np.array(pts)


def _tree(seed, centre=(10.0, -150.0, 1200.0), n_branches=8, extent=70.0):
    rng = np.random.default_rng(seed)
    centre = np.asarray(centre, float)
    d0 = rng.normal(size=3)
    d0 /= np.linalg.norm(d0)
    root = _curve(rng, centre - d0 * extent * 0.5, d0, extent * 1.1)
    polys, radii, parents = [root], [np.linspace(2.0, 1.2, len(root))], [None]
    for _ in range(1, n_branches):
        pb = int(rng.integers(0, len(polys)))
        pi = int(rng.integers(5, len(polys[pb]) - 5))
        base = polys[pb][pi]
        t = polys[pb][pi + 1] - polys[pb][pi - 1]
        t /= np.linalg.norm(t)
        side = rng.normal(size=3)
        side -= side @ t * t
        side /= np.linalg.norm(side)
        pl = _curve(rng, base, 0.6 * t + 0.8 * side, rng.uniform(20, 50))
        polys.append(pl)
        radii.append(np.linspace(1.3, 0.7, len(pl)))
        parents.append((pb, pi))
    return VesselTree.from_polylines(polys, radii, parents)


def _case(seed):
    rng = np.random.default_rng(seed)
    tree = _tree(seed)
    carm = CArm(rng.uniform(-40, 40), rng.uniform(-25, 25), 1200.0, 800.0, 0.3, (512, 512))
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    true = (Pose.from_rotvec_about(axis * np.radians(2.0), np.zeros(3)) @ Pose(np.eye(3), rng.normal(scale=3, size=3))
            @ nominal_pose(tree.centroid_lps_mm))
    return tree, carm, true


def _centerline(tree, carm, pose, rng=None, *, noise_px=0.0, ids=None):
    polys = [tree.points_lps_mm[b.point_ids] for b in tree.branches] if ids is None else [tree.points_lps_mm[ids]]
    uv = np.vstack([resample_polyline(carm.project(resample_polyline(p, 0.1), pose), 1.0) for p in polys])
    if noise_px:
        uv = uv + rng.normal(scale=noise_px, size=uv.shape)
    return uv[carm.in_image(uv)]


def _perturb(pose, tree, rot_deg, trans_mm, seed):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    c = pose.apply(tree.centroid_lps_mm)
    return Pose(np.eye(3), d * trans_mm) @ Pose.from_rotvec_about(axis * np.radians(rot_deg), c) @ pose


def _errors(est, true, tree, carm):
    """(mTRE mm, rotation error deg, in-plane centroid error mm)."""
    d = est @ true.inverse()
    c = true.apply(tree.centroid_lps_mm)
    shift = carm.axes @ (d.apply(c) - c)
    return mtre_mm(est, true, tree.points_lps_mm), float(np.degrees(np.linalg.norm(so3_log(d.R)))), float(np.linalg.norm(shift[:2]))


@pytest.fixture(scope="module")
def case0():
    return _case(0)


# ---------------------------------------------------------------------------------------------
def test_kernel_is_half_the_standard_pseudo_huber():
    s = np.r_[0.0, np.logspace(-6, 8, 50)]
    for delta in (0.5, 1.0, 3.0):
        rho, drho = reg.pseudo_huber(s, delta)
        standard = 2 * delta**2 * (np.sqrt(1 + s / delta**2) - 1)
        np.testing.assert_allclose(rho, 0.5 * standard, rtol=1e-9, atol=1e-12)
        h = 1e-6 * np.maximum(s, 1.0)
        numeric = (reg.pseudo_huber(s + h, delta)[0] - reg.pseudo_huber(np.maximum(s - h, 0), delta)[0]) / (
            (s + h) - np.maximum(s - h, 0))
        np.testing.assert_allclose(drho, numeric, rtol=1e-4)
    assert np.all(np.diff(reg.pseudo_huber(s)[0]) >= 0)  # monotone, no cancellation blow-up


def test_search_truncated_distance_transform_is_exact():
    """The global search's stamped truncated DT equals min(EDT, tau) (scipy), borders included."""
    from scipy import ndimage as ndi

    rng = np.random.default_rng(3)
    shape = (3, 23, 31)
    occ = rng.random(shape) < 0.02
    occ[0, 0, 0] = occ[1, -1, 5] = occ[2, 7, -1] = True  # occupied cells on the borders
    ids = np.flatnonzero(occ)
    for tau in (reg.SEARCH_TRUNC_CELLS, 2.5):
        ref = np.stack([np.minimum(ndi.distance_transform_edt(~o), tau) for o in occ])
        got = search._truncated_dt_batch(ids, shape, tau)
        np.testing.assert_allclose(got, ref, atol=1e-6)
        np.testing.assert_allclose(search._truncated_dt_batch(ids, shape, tau, complement=True), tau - ref, atol=1e-6)


def test_analytic_gradient_matches_finite_differences(case0):
    """3D -> 2D term (fixed correspondences, pose-independent weights): g = dE/dtheta, H = J^T W J >= 0."""
    tree, carm, true = case0
    uv = _centerline(tree, carm, true, np.random.default_rng(5), noise_px=0.5)
    m3 = model._model_from_input(tree, carm)
    prob = problem._Problem(m3, model._model_2d(uv, None, carm), carm, lam=0.0, delta=1.0)
    pose = _perturb(true, tree, 0.5, 1.0, seed=4)
    for gate_px in (reg.GATE_WIDE_PX, reg.GATE_NARROW_PX):
        ev = prob.evaluate(pose, gate_px)
        h = 1e-5
        fd = np.array([(prob.evaluate(prob.step(pose, h * e), gate_px, need_jac=False, corr=ev.corr).energy
                        - prob.evaluate(prob.step(pose, -h * e), gate_px, need_jac=False, corr=ev.corr).energy) / (2 * h)
                       for e in np.eye(6)])
        np.testing.assert_allclose(ev.g, fd, atol=GRADIENT_RTOL * np.abs(fd).max())
        assert np.linalg.eigvalsh(ev.H).min() >= -1e-9 * np.abs(ev.H).max()


def test_exact_recovery_noise_free(case0):
    tree, carm, true = case0
    uv = _centerline(tree, carm, true)
    init = _perturb(true, tree, 2.0, 4.0, seed=1)
    r = reg.register(tree, uv, carm, init_pose=init)
    mtre, rot, inplane = _errors(r.pose, true, tree, carm)
    assert r.success, r.message
    assert mtre < EXACT_MM and rot < 0.1 and inplane < 0.05
    assert r.mean_residual_px < 0.5 and r.inlier_fraction > 0.98
    np.testing.assert_allclose(r.projection_matrix, carm.projection_matrix(r.pose))


@pytest.mark.parametrize("seed", [1, 2])
def test_recovery_from_perturbation_with_noise(seed):
    tree, carm, true = _case(seed)
    uv = _centerline(tree, carm, true, np.random.default_rng(seed), noise_px=0.5)
    init = _perturb(true, tree, 8.0, 15.0, seed=10 + seed)
    assert _errors(init, true, tree, carm)[0] > 10.0
    r = reg.register(tree, uv, carm, init_pose=init)
    mtre, rot, inplane = _errors(r.pose, true, tree, carm)
    assert r.success, r.message
    assert mtre < RECOVER_MM, (mtre, r.message)
    assert rot < RECOVER_DEG
    assert inplane < INPLANE_MM
    cov = r.covariance_6x6
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)


def test_nominal_start(case0):
    tree, carm, true = case0
    uv = _centerline(tree, carm, true, np.random.default_rng(3), noise_px=0.5)
    r = reg.register(tree, uv, carm)  # DICOM angles, isocentre at the tree centroid
    assert r.success and _errors(r.pose, true, tree, carm)[0] < RECOVER_MM


def test_wrong_start_without_search_is_flagged(case0):
    tree, carm, true = case0
    uv = _centerline(tree, carm, true)
    init = _perturb(true, tree, 35.0, 40.0, seed=5)
    r = reg.register(tree, uv, carm, init_pose=init, global_search=False)
    assert _errors(r.pose, true, tree, carm)[0] > 5.0
    assert not r.success and not r
    assert "untrustworthy" in r.message


def test_unrelated_tree_is_flagged(case0):
    tree, carm, true = case0
    uv = _centerline(tree, carm, true)
    other = _tree(99, centre=tree.centroid_lps_mm)
    r = reg.register(other, uv, carm)
    assert not r.success, r.message


def test_single_path_partial_2d(case0):
    tree, carm, true = case0
    leaf = int(tree.leaves[np.argmax(tree.arclength_from_root_mm[tree.leaves])])
    path = tree.path_to_root(leaf)
    uv = _centerline(tree, carm, true, np.random.default_rng(4), noise_px=0.3, ids=path)
    projected = carm.project(tree.points_lps_mm, true)
    assert len(path) < 0.6 * len(projected)  # the 2D covers a fraction of the tree only
    init = _perturb(true, tree, 3.0, 5.0, seed=6)
    r = reg.register(tree, uv, carm, init_pose=init)
    path_mtre = mtre_mm(r.pose, true, tree.points_lps_mm[path])
    assert path_mtre < RECOVER_MM * 2, path_mtre
    assert _errors(r.pose, true, tree, carm)[2] < 1.0
    # one path: recognised, and trusted only within the limit for the fraction of the tree it explains
    assert r.single_path and "single vessel path" in r.message
    assert r.mean_residual_px < reg.MAX_MEAN_RESIDUAL_PX
    assert r.max_pose_std_mm == reg.pose_std_limit_mm(r.explained_fraction, True)
    assert r.success == (r.pose_std_mm <= r.max_pose_std_mm and r.depth_scan_rise >= reg.DEPTH_SCAN_RISE), r.message
    assert r.fits_2d and r.verdict is (reg.Verdict.OK if r.success else reg.Verdict.UNCERTAIN)
    assert r.to_dict()["single_path"] is True
    full = reg.register(tree, _centerline(tree, carm, true), carm, init_pose=true, global_search=False)
    assert full.success and not full.single_path, full.message


def test_pose_std_limit_shrinks_with_the_explained_fraction():
    full, single = reg.MAX_POSE_STD_MM, reg.MAX_POSE_STD_MM_SINGLE_PATH
    f0 = reg.FULL_LIMIT_EXPLAINED_FRACTION
    assert reg.pose_std_limit_mm(1.0) == reg.pose_std_limit_mm(f0) == full
    assert reg.pose_std_limit_mm(1.0, True) == reg.pose_std_limit_mm(f0, True) == single
    assert reg.pose_std_limit_mm(f0 / 4) == reg.pose_std_limit_mm(f0 / 4, True) == pytest.approx(full / 4)
    assert reg.pose_std_limit_mm(0.0) == reg.pose_std_limit_mm(float("nan")) == 0.0
    f = np.linspace(0.0, 1.0, 41)
    for sp in (False, True):
        lim = np.array([reg.pose_std_limit_mm(x, sp) for x in f])
        assert np.all(np.diff(lim) >= 0) and np.all(lim <= (single if sp else full))  # never looser than before


def _by_depth_scan(r) -> bool:
    """OK by the depth scan's second route: the covariance too wide, the scan settling the depth."""
    return (r.success and r.fits_2d and r.pose_std_mm > reg.COVARIANCE_SCREEN_FACTOR * r.max_pose_std_mm
            and r.depth_scan_rise >= reg.DEPTH_SCAN_RISE and "settled by the scan" in r.message)


def test_single_path_explaining_much_of_the_tree_keeps_the_single_path_limit(case0, monkeypatch):
    """The longest root-to-leaf path of case 0 (38% of the tree), from starts 8 mm deep or shallow:
    registered to 0.2 mm, limit 1 mm (not shrunk: more than 30% explained). Its covariance (1-sigma
    about 1.6 mm) is too wide for that limit: UNCERTAIN; with the depth scan's second route on
    (``DEPTH_SCAN_SCREEN_FACTOR`` 2) the scan finds no other depth and it is OK."""
    tree, carm, true = case0
    leaf = int(tree.leaves[np.argmax(tree.arclength_from_root_mm[tree.leaves])])
    path = tree.path_to_root(leaf)
    uv = _centerline(tree, carm, true, np.random.default_rng(4), noise_px=0.3, ids=path)
    for depth_mm in (-8.0, 8.0):
        init = Pose(np.eye(3), depth_mm * carm.beam_direction) @ true
        r = reg.register(tree, uv, carm, init_pose=init)
        assert r.single_path and reg.FULL_LIMIT_EXPLAINED_FRACTION <= r.explained_fraction < 0.6, r.message
        assert r.max_pose_std_mm == reg.MAX_POSE_STD_MM_SINGLE_PATH
        assert mtre_mm(r.pose, true, tree.points_lps_mm) < 0.5
        assert r.pose_std_mm > r.max_pose_std_mm and r.verdict is reg.Verdict.UNCERTAIN, r.message
        with monkeypatch.context() as m:
            m.setattr(verdict, "DEPTH_SCAN_SCREEN_FACTOR", 2.0)
            r2 = reg.register(tree, uv, carm, init_pose=init)
        assert _by_depth_scan(r2), r2.message


def test_short_path_registered_wrong_is_not_ok():
    """Half of the longest path of case 1 (28% of the tree): the overlay fits, the pose is 8.7 mm off
    along the beam, pose 1-sigma 2.3 mm above the limit: UNCERTAIN."""
    tree, carm, true = _case(1)
    leaf = int(tree.leaves[np.argmax(tree.arclength_from_root_mm[tree.leaves])])
    path = tree.path_to_root(leaf)
    path = path[: len(path) // 2]
    uv = _centerline(tree, carm, true, np.random.default_rng(5), noise_px=0.3, ids=path)
    r = reg.register(tree, uv, carm, init_pose=true)
    assert mtre_mm(r.pose, true, tree.points_lps_mm) > 4.0
    assert r.fits_2d and r.explained_fraction < reg.FULL_LIMIT_EXPLAINED_FRACTION
    assert r.max_pose_std_mm == reg.pose_std_limit_mm(r.explained_fraction, True) <= reg.MAX_POSE_STD_MM_SINGLE_PATH
    assert r.verdict is reg.Verdict.UNCERTAIN and not r, r.message


def test_single_path_predicate_on_known_visibility(case0):
    tree = case0[0]
    m3 = model._model_from_input(tree, CArm(0.0, 0.0, 1200.0, 800.0, 0.3, (512, 512)))
    branches = tree.branches
    leaf_branch = max((b for b in branches if b.is_leaf), key=lambda b: len(tree.path_to_root(b.point_ids[-1])))
    on_path, b = [], leaf_branch.index
    while b >= 0:  # the branches from that leaf to the root
        on_path.append(b)
        b = branches[b].parent
    path_vis = np.isin(m3.branch, on_path)
    assert verdict._explains_single_path(m3, path_vis)
    assert not verdict._explains_single_path(m3, np.ones(len(m3.branch), bool))  # the whole tree
    assert not verdict._explains_single_path(m3, np.zeros(len(m3.branch), bool))  # nothing explained
    # a short stub of one side branch (its first 3 samples) leaves it a path
    side = next(b.index for b in branches if b.index not in on_path and b.parent in on_path)
    stub = path_vis | (np.isin(np.arange(len(m3.branch)), np.flatnonzero(m3.branch == side)[:3]))
    assert verdict._explains_single_path(m3, stub)
    # a point cloud has no topology: never a "single path"
    cloud = model._model_from_input(tree.points_lps_mm, CArm(0.0, 0.0, 1200.0, 800.0, 0.3, (512, 512)))
    assert not verdict._explains_single_path(cloud, np.ones(len(cloud.points), bool))


def test_inputs_are_not_modified(case0):
    tree, carm, true = case0
    uv = _centerline(tree, carm, true)
    rad = np.full(len(uv), 2.0)
    uv0, rad0, t0, R0 = uv.copy(), rad.copy(), true.t.copy(), true.R.copy()
    pts = tree.points_lps_mm.copy()
    init = _perturb(true, tree, 2.0, 3.0, seed=7)
    reg.register(tree.points_lps_mm.copy(), uv, carm, init_pose=init, centerline_radius_px=rad)
    reg.register(tree, uv, carm, init_pose=init, centerline_radius_px=rad, global_search=False)
    reg.score(tree, uv, carm, true)
    reg.nudge(true, carm, centroid_lps_mm=tree.centroid_lps_mm, translate_mm=(1, 2, 3), rotate_deg=(1, 0, 0))
    assert np.array_equal(uv, uv0) and np.array_equal(rad, rad0)
    assert np.array_equal(true.t, t0) and np.array_equal(true.R, R0) and np.array_equal(tree.points_lps_mm, pts)


def test_point_cloud_input_matches_tree_input(case0):
    tree, carm, true = case0
    dense = np.vstack([resample_polyline(tree.points_lps_mm[b.point_ids], 0.5) for b in tree.branches])
    uv = _centerline(tree, carm, true)
    init = _perturb(true, tree, 2.0, 4.0, seed=8)
    r = reg.register(dense, uv, carm, init_pose=init)
    assert r.success and _errors(r.pose, true, tree, carm)[0] < RECOVER_MM


def test_nudge_semantics(case0):
    tree, carm, true = case0
    c = tree.centroid_lps_mm
    uv0 = carm.project(c, true)
    moved = reg.nudge(true, carm, centroid_lps_mm=c, translate_mm=(2.0, 0.0, 0.0))
    du = carm.project(c, moved) - uv0
    assert du[0] > 0 and abs(du[1]) < 1e-6  # along e_u: image right only
    z = (true.apply(c) - carm.source_room_mm) @ carm.beam_direction
    assert np.isclose(du[0], 2.0 * carm.focal_px / z, rtol=1e-6)
    spun = reg.nudge(true, carm, centroid_lps_mm=c, rotate_deg=(0.0, 0.0, 10.0))
    assert np.allclose(carm.project(c, spun), uv0, atol=1e-6)  # rotation about the centroid
    assert np.isclose((spun @ true.inverse()).rotation_angle_deg(), 10.0)
    back = reg.nudge(moved, carm, centroid_lps_mm=c, translate_mm=(-2.0, 0.0, 0.0))
    assert back.allclose(true, atol_mm=1e-9)


def test_nudge_then_refine_round_trip(case0):
    tree, carm, true = case0
    uv = _centerline(tree, carm, true, np.random.default_rng(9), noise_px=0.5)
    r0 = reg.register(tree, uv, carm, init_pose=_perturb(true, tree, 1.0, 2.0, seed=9))
    away = reg.nudge(r0.pose, carm, centroid_lps_mm=tree.centroid_lps_mm, translate_mm=(3.0, -2.0, 4.0),
                     rotate_deg=(2.0, -1.0, 3.0))
    assert mtre_mm(away, r0.pose, tree.points_lps_mm) > 3.0
    r1 = reg.refine(tree, uv, carm, away)
    assert r1.success
    assert mtre_mm(r1.pose, r0.pose, tree.points_lps_mm) < ROUND_TRIP_MM


def test_score_decreases_toward_truth(case0):
    tree, carm, true = case0
    uv = _centerline(tree, carm, true)
    far = _perturb(true, tree, 5.0, 8.0, seed=11)
    xi = (far @ true.inverse()).log()
    scores = [reg.score(tree, uv, carm, Pose.exp(a * xi) @ true) for a in np.linspace(1.0, 0.0, 9)]
    assert np.all(np.diff(scores) < 0), scores
    assert scores[-1] < 0.3


def test_score_equals_result_mean_residual(case0):
    tree, carm, true = case0
    uv = _centerline(tree, carm, true)
    # a partial roadmap plus a distractor vessel the CTA does not have: score and the result
    # must report the same (inlier) residual, and the distractor must not inflate it
    rng = np.random.default_rng(21)
    distractor = np.column_stack([np.linspace(20, 200, 150), np.full(150, 30.0)]) + rng.normal(0, 0.3, (150, 2))
    uv2 = np.vstack([uv, distractor])
    r = reg.register(tree, uv2, carm, init_pose=_perturb(true, tree, 2.0, 4.0, seed=22))
    s_in = reg.score(tree, uv2, carm, r.pose, inliers_only=True)
    assert s_in == r.mean_residual_px
    assert s_in < reg.MAX_MEAN_RESIDUAL_PX
    # the default (viewer) score counts the distractor with its full distance
    s_all = reg.score(tree, uv2, carm, r.pose)
    assert s_all == float(reg.residuals_px(tree, uv2, carm, r.pose).mean())
    assert s_all > s_in + 1.0


def test_epnp_baseline_exact_and_mirror(case0):
    tree, carm, true = case0
    rng = np.random.default_rng(13)
    X = tree.centroid_lps_mm + rng.uniform(-30, 30, size=(12, 3))
    uv = carm.project(X, true)
    r = reg.register_epnp(X, uv, carm)
    assert r.success and np.linalg.det(r.pose.R) > 0
    assert mtre_mm(r.pose, true, X) < 0.05
    assert r.mean_residual_px < 0.01
    few = reg.register_epnp(X[:3], uv[:3], carm)
    assert not few.success and "4" in few.message


def test_match_bifurcations_under_shifted_start(case0):
    tree, carm, true = case0
    bif = tree.bifurcations
    uv = carm.project(tree.points_lps_mm[bif], true)
    order = np.random.default_rng(14).permutation(len(bif))
    start = reg.nudge(true, carm, centroid_lps_mm=tree.centroid_lps_mm, translate_mm=(4.0, -3.0, 0.0))
    i3, i2 = reg.match_bifurcations(tree, uv[order], carm, start)
    assert len(i3) == len(bif)
    assert np.array_equal(i3, bif[order][i2])


def test_result_to_dict_is_json(case0):
    tree, carm, true = case0
    uv = _centerline(tree, carm, true)
    r = reg.register(tree, uv, carm, init_pose=true, global_search=False)
    d = json.loads(json.dumps(r.to_dict()))
    assert d["success"] is True and len(d["projection_matrix"]) == 3
    assert Pose.from_dict(d["pose"]).allclose(r.pose, atol_mm=1e-9)
    failed = reg.register(tree, uv[:5], carm)
    assert not failed.success and json.loads(json.dumps(failed.to_dict()))["mean_residual_px"] is None
    assert failed.verdict is reg.Verdict.FAILED and r.verdict is reg.Verdict.OK and d["fits_2d"] is True
    assert {v.value for v in reg.Verdict} == {"ok", "uncertain", "failed"}  # UNCERTAIN: test_single_path_*, viewer


def test_bad_inputs_raise(case0):
    tree, carm, true = case0
    uv = _centerline(tree, carm, true)
    with pytest.raises(InputError, match="centerline_uv_px"):
        reg.register(tree, uv[:, :1], carm)
    with pytest.raises(InputError, match="non-finite"):
        reg.register(tree, np.vstack([uv, [np.nan, 1.0]]), carm)
    with pytest.raises(InputError, match="tree"):
        reg.register(np.zeros((5, 2)), uv, carm)
    with pytest.raises(InputError, match="carm"):
        reg.register(tree, uv, "not a carm")
    with pytest.raises(InputError, match="centerline_radius_px"):
        reg.register(tree, uv, carm, centerline_radius_px=np.ones(3))
    with pytest.raises(InputError, match="lam"):
        reg.register(tree, uv, carm, lam=-1)
    with pytest.raises(InputError, match="translate_mm"):
        reg.nudge(true, carm, centroid_lps_mm=tree.centroid_lps_mm, translate_mm=(1, 2))
    with pytest.raises(InputError, match="landmarks"):
        reg.register_epnp(np.zeros((5, 3)), np.zeros((4, 2)), carm)


def test_jackknife_refuses_a_pose_that_rests_on_part_of_the_roadmap():
    """Issue 20 item 4, a false acceptance of the covariance alone: `bench_registration.py --verdict`
    seed 105, the "partial" roadmap (the catheterised path and 1-3 other branches, its
    roadmap_centerline) against the CTA-extracted tree. The pose lands 10.7 mm off along the beam with a
    1-sigma of 1.4 mm (under the 2 mm limit); leaving out parts of the roadmap moves it by several mm,
    so the verdict is UNCERTAIN and says why."""
    from pathlib import Path

    d = np.load(Path(__file__).parent / "data" / "registration_seed105_partial.npz")
    tree = VesselTree(d["points_lps_mm"], d["radius_mm"], d["parent"])
    carm = CArm.from_dict(json.loads(str(d["carm"])))
    true = Pose(d["true_pose"][:3, :3], d["true_pose"][:3, 3])
    r = reg.register(tree, d["uv_px"], carm, centerline_radius_px=d["uv_radius_px"])
    assert mtre_mm(r.pose, true, d["true_points_lps_mm"]) > 5.0                      # wrong, and ...
    assert r.fits_2d and r.pose_std_mm <= r.max_pose_std_mm                          # ... the 1-sigma alone accepts it
    assert r.jackknife_std_mm > reg.JACKKNIFE_FACTOR * r.max_pose_std_mm
    assert r.verdict is reg.Verdict.UNCERTAIN and not r.success
    assert "jackknife" in r.message and "rests on part of the roadmap" in r.message
    assert r.to_dict()["jackknife_std_mm"] == pytest.approx(r.jackknife_std_mm)


def test_jackknife_keeps_a_right_pose_ok(case0):
    tree, carm, true = case0
    q = _centerline(tree, carm, true, np.random.default_rng(4), noise_px=0.3)
    r = reg.register(tree, q, carm)
    assert r.verdict is reg.Verdict.OK
    assert 0.0 <= r.jackknife_std_mm <= r.max_pose_std_mm                             # computed, and small
    assert mtre_mm(r.pose, true, tree.points_lps_mm) < RECOVER_MM


def _large_tree_case():
    """A 420 mm trunk with 12 side branches seen through a view of its upper end (issue 17's chest-abdomen
    tree through an arch view): ``(tree, carm, true pose)``."""
    rng = np.random.default_rng(5)
    root = _curve(rng, (0.0, -150.0, 1000.0), (0.0, 0.1, 1.0), 420.0, curl=0.03)   # along the body axis
    polys, radii, parents = [root], [np.full(len(root), 4.0)], [None]
    for i in range(12):
        pi = 15 + 30 * i
        side = rng.normal(size=3)
        side[2] = 0.0
        pl = _curve(rng, root[pi], side / np.linalg.norm(side), rng.uniform(30, 60))
        polys.append(pl)
        radii.append(np.linspace(2.0, 1.0, len(pl)))
        parents.append((0, pi))
    tree = VesselTree.from_polylines(polys, radii, parents)
    carm = CArm(20.0, 10.0, 1200.0, 800.0, 0.3, (512, 512))
    viewed = root[340]                                     # 340 mm along a 420 mm trunk
    true = Pose.from_rotvec_about(np.radians([1.0, -2.0, 1.5]), np.zeros(3)) @ Pose(np.eye(3), [4.0, -3.0, 5.0]) \
        @ nominal_pose(viewed)
    return tree, carm, true


def test_search_range_covers_a_tree_much_larger_than_the_view():
    """Issue 17: a tree far larger than the view (a chest-abdomen tree, an arch view) puts its centroid,
    and the nominal start's isocentre, far from the part in view; the search widens its in-plane range
    to the tree's projected reach and registration lands on the viewed part."""
    tree, carm, true = _large_tree_case()
    P = tree.points_lps_mm
    in_view = carm.in_image(carm.project(P, true))
    start = nominal_pose(tree.centroid_lps_mm)
    m3 = model._model_from_input(tree, carm)
    su, sv = search.shift_range_mm(m3, carm, start)
    offset = carm.axes @ (true.apply(P[in_view]).mean(0) - start.apply(P[in_view]).mean(0))
    assert max(abs(offset[:2])) > 2 * search.SEARCH_SHIFT_MM          # far beyond the default range ...
    assert abs(offset[0]) < su and abs(offset[1]) < sv                 # ... inside the widened one
    small, small_carm, _ = _case(0)
    assert search.shift_range_mm(model._model_from_input(small, small_carm), small_carm,
                                 nominal_pose(small.centroid_lps_mm)) == (search.SEARCH_SHIFT_MM,) * 2  # view-sized
    r = reg.register(tree, _centerline(tree, carm, true), carm)
    assert mtre_mm(r.pose, true, P[in_view]) < RECOVER_MM


def test_in_view_points_are_those_projecting_into_the_image():
    tree, carm, true = _large_tree_case()
    P = tree.points_lps_mm
    uv = carm.project(P, true)
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= carm.cols - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= carm.rows - 0.5)
    got = verdict._in_view(P, carm, true)
    assert 0 < got.sum() < len(P) and np.array_equal(got, inside)
    behind = true.inverse().apply(carm.source_room_mm - 50.0 * carm.beam_direction)   # 50 mm behind the source
    assert not verdict._in_view(behind[None], carm, true)[0]


def test_explained_fraction_and_limit_count_the_tree_in_view(monkeypatch):
    """Issue 17: a roadmap of everything in view explains the tree in view, whatever the tree holds outside
    the view; the whole-tree fraction (the old rule) is the in-view share of the tree, and its 1-sigma limit
    proportionally stricter. The pose 1-sigma is over the in-view points: at most the whole tree's."""
    tree, carm, true = _large_tree_case()
    P = tree.points_lps_mm
    share = verdict._in_view(P, carm, true).mean()
    uv = _centerline(tree, carm, true)
    r = reg.refine(tree, uv, carm, true)
    assert mtre_mm(r.pose, true, P[verdict._in_view(P, carm, true)]) < RECOVER_MM
    assert r.explained_fraction > 0.85 and share < 0.5
    assert r.max_pose_std_mm == reg.pose_std_limit_mm(r.explained_fraction, r.single_path)
    monkeypatch.setattr(verdict, "IN_VIEW_ONLY", False)
    whole = reg.refine(tree, uv, carm, true)
    assert whole.explained_fraction == pytest.approx(share * r.explained_fraction, abs=0.05)
    assert whole.pose_std_mm >= r.pose_std_mm


def _verdict_case(name):
    from pathlib import Path

    d = np.load(Path(__file__).parent / "data" / name)
    tree = VesselTree(d["points_lps_mm"], d["radius_mm"], d["parent"])
    carm = CArm.from_dict(json.loads(str(d["carm"])))
    true = Pose(d["true_pose"][:3, :3], d["true_pose"][:3, 3])
    r = reg.register(tree, d["uv_px"], carm, centerline_radius_px=d["uv_radius_px"])
    return r, mtre_mm(r.pose, true, d["true_points_lps_mm"])


def test_depth_profile_refuses_a_pose_the_jackknife_accepted():
    """Issue 20 item 4, a false acceptance of covariance and jackknife: `bench_registration.py --verdict`
    seed 119, the full tree seen from the case's second view ("view2"). The pose lands 5.3 mm off along
    the beam with a 1-sigma of 1.8 mm and a jackknife 1-sigma of 3.9 mm (both within their limits, 2 and
    4 mm); moved 2.6 mm toward the source with the rest re-fitted, the vessels fit as well: UNCERTAIN."""
    r, err = _verdict_case("registration_seed119_view2.npz")
    assert err > 5.0                                                                # wrong, and ...
    assert r.fits_2d and r.pose_std_mm <= r.max_pose_std_mm                         # ... the covariance and
    assert r.jackknife_std_mm <= verdict.JACKKNIFE_FACTOR * r.max_pose_std_mm       # the jackknife accept it
    assert r.verdict is reg.Verdict.UNCERTAIN and not r.success
    assert "does not settle the depth along the beam" in r.message and "depth profile" in r.message


def test_depth_scan_refuses_a_wrong_pose_the_other_checks_accepted():
    """Issue 20 item 4, a false acceptance of covariance, jackknife and two-point profile: seed 613 of
    `bench_registration.py --verdict`, the path and other branches ("partial"), 3.4 mm off along the beam.
    Moved 5 mm or more along the beam with the rest re-fitted, the vessels fit almost as well (the energy
    rises by less than DEPTH_SCAN_RISE x the rise the covariance predicts at its depth 1-sigma): UNCERTAIN."""
    r, err = _verdict_case("registration_seed613_partial.npz")
    assert err > 3.0 and r.fits_2d
    assert r.pose_std_mm <= r.max_pose_std_mm                                              # the covariance and
    assert r.jackknife_std_mm <= verdict.JACKKNIFE_FACTOR * r.max_pose_std_mm               # the jackknife accept it
    assert "depth profile 1-sigma" in r.message and "does not settle the depth along" not in r.message  # and the profile
    assert r.depth_scan_rise < reg.DEPTH_SCAN_RISE
    assert r.verdict is reg.Verdict.UNCERTAIN and "the depth scan finds another depth" in r.message


def test_depth_scan_accepts_right_single_path_poses_the_covariance_refused(monkeypatch):
    """Issue 20 item 4, false refusals: seed 117, the catheterised path alone seen from the second view
    ("view2-path"), 0.2 mm off with a pose 1-sigma of 1.2 mm (limit 1 mm), and seed 304, the path alone
    ("path"), 0.5 mm off with 2.2 mm (limit 2 mm), were refused by the covariance. Moved 5-20 mm along the
    beam with the rest re-fitted, the vessels fit much worse (at least DEPTH_SCAN_RISE x the rise the
    covariance predicts at its own depth 1-sigma), and no depth fits better: OK with the scan's second route on
    (``DEPTH_SCAN_SCREEN_FACTOR`` 2; off by default, so they stay UNCERTAIN: the price of the path mode's
    biased poses, see the constant)."""
    for name, most_mm in (("registration_seed117_view2-path.npz", 0.5), ("registration_seed304_path.npz", 1.0)):
        assert _verdict_case(name)[0].verdict is reg.Verdict.UNCERTAIN                     # by default
        with monkeypatch.context() as m:
            m.setattr(verdict, "DEPTH_SCAN_SCREEN_FACTOR", 2.0)
            r, err = _verdict_case(name)
        assert err < most_mm                                                               # right ...
        assert r.fits_2d and r.pose_std_mm > r.max_pose_std_mm                             # ... covariance too wide
        assert r.depth_scan_rise >= reg.DEPTH_SCAN_RISE, r.message
        assert r.verdict is reg.Verdict.OK and "settled by the scan" in r.message
        assert r.to_dict()["depth_scan_rise"] == pytest.approx(r.depth_scan_rise)


def test_depth_scan_refuses_a_wrong_single_path_pose_with_a_second_minimum(monkeypatch):
    """The other side of the scan: seed 312, the path alone from the second view ("view2-path"), 7.6 mm off
    along the beam with a pose 1-sigma of 1.6 mm (as narrow as right ones): its depth scan rises only
    1.6 x U beyond 5 mm (a second minimum near the truth), so with the scan's second route on it stays
    UNCERTAIN and says why."""
    monkeypatch.setattr(verdict, "DEPTH_SCAN_SCREEN_FACTOR", 2.0)
    r, err = _verdict_case("registration_seed312_view2-path.npz")
    assert err > 5.0 and r.single_path and r.fits_2d
    assert r.pose_std_mm < 2.0 * r.max_pose_std_mm                                        # the scan is asked ...
    assert r.depth_scan_rise < reg.DEPTH_SCAN_RISE                                         # ... and finds the other depth
    assert r.verdict is reg.Verdict.UNCERTAIN and not r.success
    assert "the depth scan does not settle the depth" in r.message


def test_lm_with_the_depth_held_refits_the_rest(case0):
    """The profile's LM (``fixed``): started 3 mm deeper than the truth and 1 mm off sideways, it
    brings the projection back in the image plane while the tree's centroid stays 3 mm deep; without
    ``fixed`` (noise-free roadmap) the depth returns to the truth."""
    tree, carm, true = case0
    uv = _centerline(tree, carm, true)
    m3 = model._model_from_input(tree, carm)
    prob = problem._Problem(m3, model._model_2d(uv, None, carm), carm, lam=problem.LAMBDA, delta=problem.DELTA)
    d, e_u = carm.beam_direction, carm.axes[0]
    c_true = true.apply(m3.centroid)
    start = Pose(np.eye(3), 3.0 * d + 1.0 * e_u) @ true
    a = np.concatenate([d, np.cross(start.apply(m3.centroid), d) / m3.r_g])
    out = problem._levenberg_marquardt(prob, start, gate_px=problem.GATE_WIDE_PX, max_iterations=50, fixed=a)
    moved = out.pose.apply(m3.centroid) - c_true
    assert float(moved @ d) == pytest.approx(3.0, abs=0.05)                       # depth held
    assert abs(float(moved @ e_u)) < 0.3                                            # sideways offset re-fitted
    assert out.ev.energy < prob.evaluate(start, problem.GATE_WIDE_PX).energy
    free = problem._levenberg_marquardt(prob, start, gate_px=problem.GATE_WIDE_PX, max_iterations=50)
    assert abs(float((free.pose.apply(m3.centroid) - c_true) @ d)) < 0.3           # unheld, the depth returns
