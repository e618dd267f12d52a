"""Per-frame pose tracking (``guidewire3d.motion.tracking``) against ground truth and real data (issue 18)."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from guidewire3d.live import session as live
from guidewire3d.motion import tracking as motion
from guidewire3d.errors import InputError
from guidewire3d.geometry import Pose
from guidewire3d.metrics import mtre_mm
from guidewire3d.phantom import PhantomOptions, load_truth, simulate, write_case
from guidewire3d.registration import RegistrationResult, Verdict

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
SHIFT_TOL_MM = 0.5  # in-plane shift recovered from an exact curve
#: RMS pose error / RMS reported 1 sigma that counts as calibrated (the Hessian's own: ~5)
CALIBRATED_RATIO = (0.5, 2.0)


@pytest.fixture(scope="module")
def still_case():
    return simulate(PhantomOptions(seed=3, n_frames=2), make_ct=False)


def _centroid_shift_cam(case, pose_a, pose_b):
    c = case.tree.points_lps_mm.mean(axis=0)
    return case.carm.axes @ (pose_a.apply(c[None])[0] - pose_b.apply(c[None])[0])


def test_a_cranio_caudal_shift_is_recovered_from_one_curve(still_case):
    case = still_case
    tracker = motion.MotionTracker(case.tree, case.carm, case.pose)
    # the anatomy moved 8 mm along the patient's axis (breathing): the wire path seen in the frame
    moved = case.pose @ Pose(np.eye(3), [0.0, 0.0, 8.0])
    path = case.tree.points_lps_mm[case.wire_path_point_ids]
    res = tracker.update(case.carm.project(path, moved))
    assert isinstance(res, RegistrationResult) and res.verdict is Verdict.OK, res.message
    err = _centroid_shift_cam(case, res.pose, moved)
    assert np.linalg.norm(err[:2]) < SHIFT_TOL_MM, err
    # and the next frame starts from there (temporal prior): no motion, no change
    again = tracker.update(case.carm.project(path, moved))
    assert np.linalg.norm(_centroid_shift_cam(case, again.pose, res.pose)) < SHIFT_TOL_MM


def test_track_poses_returns_one_result_per_frame_and_holds_on_empty_ones(still_case):
    case = still_case
    path = case.tree.points_lps_mm[case.wire_path_point_ids]
    curves = [case.carm.project(path, case.pose), np.zeros((0, 2)), case.carm.project(path, case.pose)]
    res = motion.track_poses(case.tree, curves, case.carm, case.pose)
    assert len(res) == 3
    assert res[0].verdict is Verdict.OK and mtre_mm(res[0].pose, case.pose, path) < SHIFT_TOL_MM
    assert res[1].verdict is Verdict.FAILED and "pose held" in res[1].message
    assert res[1].pose.allclose(res[0].pose, atol_mm=1e-9)


def test_a_curve_off_the_tree_does_not_move_the_pose(still_case):
    case = still_case
    tracker = motion.MotionTracker(case.tree, case.carm, case.pose)
    path = case.tree.points_lps_mm[case.wire_path_point_ids]
    first = tracker.update(case.carm.project(path, case.pose))
    # a curve far beyond the acquisition range and the gate: no tree sample projects near it
    far = case.carm.project(path, case.pose) + np.array([3000.0, 0.0])
    res = tracker.update(far)
    assert not res.success and "pose held" in res.message
    assert res.pose.allclose(first.pose, atol_mm=1e-9)
    # and a curve seen while the patient has not moved keeps the pose
    assert tracker.update(case.carm.project(path, case.pose)).pose.allclose(first.pose, atol_mm=0.05, atol_rad=1e-4)


def test_bad_options_are_refused():
    with pytest.raises(InputError, match="sigma_depth_mm"):
        motion.MotionOptions(sigma_depth_mm=0.0)
    with pytest.raises(InputError, match="iterations"):
        motion.MotionOptions(iterations=0)
    with pytest.raises(InputError, match="settle_every"):
        motion.MotionOptions(settle_every=-1)
    with pytest.raises(InputError, match="cov_correlation_mm"):
        motion.MotionOptions(cov_correlation_mm=-1.0)
    with pytest.raises(InputError, match="fit_correlation_mm"):
        motion.MotionOptions(fit_correlation_mm=0.0)
    with pytest.raises(InputError, match="settle_rival_cost"):
        motion.MotionOptions(settle_rival_cost=-1.0)
    with pytest.raises(InputError, match="biplane_sigma_rotation_deg"):
        motion.MotionOptions(biplane_sigma_rotation_deg=0.0)
    with pytest.raises(InputError, match="biplane_lumen_slack"):
        motion.MotionOptions(biplane_lumen_slack=-0.1)


def test_breathing_truth_renders_the_wire_at_the_frame_pose(tmp_path):
    case = simulate(PhantomOptions(seed=2, n_frames=4, breathing_mm=15.0), make_ct=False)
    assert np.ptp(case.motion_lps_mm[:, 2]) > 0.5  # it moves, mostly cranio-caudally
    for t in range(case.options.n_frames):
        np.testing.assert_allclose(case.carm.project(case.wire_lps_mm[t], case.frame_pose(t)), case.wire_uv_px[t],
                                   atol=1e-9)
    truth = load_truth(write_case(case, tmp_path / "c"))
    for t in range(case.options.n_frames):
        assert truth.frame_pose(t).allclose(case.frame_pose(t), atol_mm=1e-4, atol_rad=1e-7)


def test_tracking_follows_breathing_in_the_live_path():
    case = simulate(PhantomOptions(seed=5, n_frames=16, breathing_mm=15.0, cardiac_mm=2.0), make_ct=False)
    out = {}
    for track in (False, True):
        s = live.Session(case.tree, case.carm, case.pose, track_motion=track)
        err, pose_err = [], []
        for t, frame in enumerate(case.frames):
            fr = s.process(frame)
            pose_err.append(mtre_mm(fr.pose, case.frame_pose(t), case.tree.points_lps_mm))
            if fr:
                err.append(cKDTree(case.wire_lps_mm[t]).query(fr.wire3d.points_lps_mm)[0].mean())
            if track and fr.wire2d:  # a frame whose 2D wire was found updated the pose
                assert fr.motion is not None and fr.to_dict()["motion"]["pose"] is not None
        out[track] = (np.mean(err) if err else np.inf, np.mean(pose_err), len(err))
    # with the roadmap pose the wire misses the moved tree in most frames; tracked, every frame is
    # reconstructed, within 1 mm of the true wire on average
    assert out[True][2] == len(case.frames) and out[True][2] > out[False][2], out
    assert out[True][0] < 1.0, out
    assert out[True][1] < out[False][1], out


def test_real_liver_catheter_is_followed_through_breathing():
    sys.path.insert(0, str(SCRIPTS))
    from ambrosini_data import dataset1_root, load_dataset1

    if not (dataset1_root() / "dataset1_lps.npz").exists():
        pytest.skip(f"shared real data not found at {dataset1_root()}")
    d = load_dataset1()
    frames = d.curves_uv_px[::3]
    res = motion.track_poses(d.tree, frames, d.carm, Pose.identity())
    fusion = np.mean([motion.curve_to_tree_distance_px(c, d.tree, d.carm, Pose.identity()).mean() for c in frames])
    tracked = np.mean([motion.curve_to_tree_distance_px(c, d.tree, d.carm, r.pose).mean() for c, r in zip(frames, res)])
    assert tracked < 0.75 * fusion, (tracked, fusion)
    c0 = d.tree.points_lps_mm.mean(axis=0)
    depth = [abs((d.carm.axes @ (r.pose.apply(c0[None])[0] - c0))[2]) for r in res]
    assert max(depth) < 5.0
    assert all(r.verdict in (Verdict.OK, Verdict.UNCERTAIN, Verdict.FAILED) for r in res)
    assert sum(r.verdict is Verdict.OK for r in res) >= 0.9 * len(res)


def test_a_tracked_frames_overlay_draws_its_wire_where_the_frame_shows_it():
    """``overlay_NNNN.png`` of a tracked frame projects the tree and the 3D wire in the frame's own pose (the one the
    wire was reconstructed in). Until stop 45 it used the registration's, which drew the wire off the frame's wire by
    the breathing (the biplane overlays of plane B were already right)."""
    from types import SimpleNamespace

    from guidewire3d.app import export

    case = simulate(PhantomOptions(seed=5, n_frames=8, breathing_mm=15.0), make_ct=False)
    s = live.Session(case.tree, case.carm, case.pose, track_motion=True)
    frs = [s.process(frame) for frame in case.frames]
    run = SimpleNamespace(registration=SimpleNamespace(pose=case.pose), tree=case.tree, carm=case.carm,
                          frames_carm=case.carm, frame_results=frs, wires3d=[fr.wire3d for fr in frs])
    fixed = SimpleNamespace(**{**vars(run), "frame_results": []})  # the same wires drawn in the registration's pose
    tracked, registered = [], []
    for k, fr in enumerate(frs):
        if fr.motion is None or not fr.wire3d.success:
            continue
        true_uv = cKDTree(case.wire_uv_px[k])
        tracked.append(true_uv.query(export.overlay_uv(run, k)[1])[0].mean())
        registered.append(true_uv.query(export.overlay_uv(fixed, k)[1])[0].mean())
    assert len(tracked) >= 4
    assert np.median(tracked) < 2.0 and np.median(registered) > 2 * np.median(tracked), (tracked, registered)


def test_reconstruct_track_motion_writes_each_frames_pose(small_case_dir, tmp_path):
    import json

    from guidewire3d.app.cli import main

    d, out = small_case_dir, tmp_path / "out"
    rc = main(["reconstruct", "--cta", str(d / "ct"), "--roadmap", str(d / "roadmap.dcm"), "--frames",
               str(d / "frames.dcm"), "--out", str(out), "--track-motion", "--no-images", "--force"])
    assert rc == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["inputs"]["track_motion"] is True
    tracked = [f for f in rep["frames"] if f.get("motion")]
    assert tracked, [f["verdict_message"] for f in rep["frames"]]
    truth = load_truth(d)
    for f in tracked:
        # the case does not move: the tracked pose stays at the registered one
        pose = Pose.from_matrix(f["motion"]["pose"])
        assert mtre_mm(pose, Pose.from_matrix(rep["pose"]), truth.tree.points_lps_mm) < 1.0
    # the viewer shows each tracked frame in its own pose, and applies a correction the same way
    from guidewire3d.viewer.controller import ViewerController
    from guidewire3d.app.outdir import load_outdir

    ctrl = ViewerController(load_outdir(out), persist=False)
    k = next(i for i, w in enumerate(ctrl._case.wires) if w.pose is not None)
    ctrl.set_frame(k)
    rec = next(f for f in tracked if f["index"] == ctrl._case.wires[k].index)
    assert ctrl.shown_pose.allclose(Pose.from_matrix(rec["motion"]["pose"]), atol_mm=1e-6)
    ctrl.toggle_roadmap()  # the roadmap is shown in the registration's pose
    assert ctrl.shown_pose is ctrl.pose
    ctrl.toggle_roadmap()
    assert ctrl.apply(force=True) == len(ctrl._case.wires)
    assert any(w.pose is not None for w in ctrl._case.wires)


def test_a_pose_perturbation_maps_to_the_trackers_delta(still_case):
    # the tangent map used for the covariances: a small left perturbation of the pose (room axes,
    # about the iso origin) is the tracker's delta (camera axes, left-handed, about the centroid)
    case = still_case
    tracker = motion.MotionTracker(case.tree, case.carm, case.pose)
    A = tracker._tangent_to_delta
    rng = np.random.default_rng(0)
    pts = case.tree.points_lps_mm
    for _ in range(5):
        xi = rng.normal(size=6) * np.r_[0.5, 0.5, 0.5, 2e-3, 2e-3, 2e-3]
        # first order in xi: the tree moved by the perturbation and by the mapped delta agree to well below 1 um
        moved = Pose.exp(xi) @ case.pose
        assert mtre_mm(tracker.pose_of(A @ xi), moved, pts) < 1e-2 * mtre_mm(case.pose, moved, pts)
    # the registration covariance enters the prior through the same map: a covariance that is
    # pure rotation about the iso origin becomes rotation plus the centroid's swing in the tracker
    C = np.zeros((6, 6))
    C[3:, 3:] = np.eye(3) * np.radians(1.0) ** 2
    np.testing.assert_allclose(tracker._camera_covariance(C), A @ C @ A.T)


def test_the_reported_pose_covariance_is_calibrated_on_breathing():
    # the true 2D wires of breathing sequences (no segmentation): the tracker's reported 1 sigma
    # (RMS over the tree) is of the size of its real error, not ~5x smaller as its own Hessian's
    err, std = [], []
    for seed in (7, 8, 9):
        case = simulate(PhantomOptions(seed=seed, n_frames=8, breathing_mm=15.0, cardiac_mm=2.0), make_ct=False)
        res = motion.track_poses(case.tree, case.wire_uv_px, case.carm, case.pose)
        err += [mtre_mm(r.pose, case.frame_pose(t), case.tree.points_lps_mm) for t, r in enumerate(res)]
        std += [r.pose_std_mm for r in res]
        for r in res:  # in the registration's convention: symmetric, positive definite
            C = r.covariance_6x6
            assert C.shape == (6, 6) and np.allclose(C, C.T) and np.linalg.eigvalsh(C).min() > 0
    err, std = np.array(err), np.array(std)
    ratio = np.sqrt(np.mean(err**2)) / np.sqrt(np.mean(std**2))
    assert CALIBRATED_RATIO[0] < ratio < CALIBRATED_RATIO[1], (ratio, err.round(2), std.round(2))


def test_the_tracked_pose_covariance_enters_the_wire_uncertainty(still_case):
    case = still_case
    uv = case.carm.project(case.wire_lps_mm[0], case.pose)
    s = live.Session(case.tree, case.carm, case.pose, track_motion=True, segmenter="ridge")
    fr = s.process_wire(uv)
    assert fr.motion is not None and s.tracker.registration_covariance is fr.motion.covariance_6x6
    static = live.Session(case.tree, case.carm, case.pose, segmenter="ridge").process_wire(uv)
    # the same 2D wire at (nearly) the same pose: the pose's uncertainty adds to every point's
    assert np.median(fr.wire3d.uncertainty_mm) > np.median(static.wire3d.uncertainty_mm)


def test_a_tracked_pose_stuck_in_a_wrong_fit_is_not_settled(still_case):
    # the tracker's state knocked along the patient's axis: from some shifts it recovers the true
    # pose, from others the curve also fits the lumen at a wrong pose and the temporal chain stays
    # there. The second opinion (the frame solved alone) tells those apart from the recovered ones.
    case = still_case
    path = case.tree.points_lps_mm[case.wire_path_point_ids]
    uv = case.carm.project(case.wire_lps_mm[0], case.pose)
    opt = motion.MotionOptions(settle_every=1)
    outcomes = []
    for shift_mm in (5.0, -5.0, 8.0, -8.0):
        tracker = motion.MotionTracker(case.tree, case.carm, case.pose, options=opt)
        tracker.update(uv)
        tracker.delta = tracker.delta + np.r_[shift_mm * tracker.cc_cam, 0.0, 0.0, 0.0]
        res = tracker.update(uv)
        err = mtre_mm(res.pose, case.pose, path)
        if err > opt.max_unsettled_mm:
            assert res.verdict is Verdict.UNCERTAIN and "not settled" in res.message, (shift_mm, err, res.message)
        else:
            assert res.verdict is Verdict.OK, (shift_mm, err, res.message)
        outcomes.append(err > opt.max_unsettled_mm)
    assert any(outcomes) and not all(outcomes), outcomes  # both kinds occur here
    # without the second opinion the stuck pose is reported OK: the check is what flags it
    tracker = motion.MotionTracker(case.tree, case.carm, case.pose, options=motion.MotionOptions(settle_every=0))
    tracker.update(uv)
    tracker.delta = tracker.delta + np.r_[8.0 * tracker.cc_cam, 0.0, 0.0, 0.0]
    res = tracker.update(uv)
    assert mtre_mm(res.pose, case.pose, path) > opt.max_unsettled_mm and res.verdict is Verdict.OK


def _rotation_deg(pose_a, pose_b) -> float:
    cos = (np.trace(pose_a.R @ pose_b.R.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def test_the_wires_offset_in_the_lumen_does_not_rotate_the_tree(still_case):
    """No motion: the frame shows the true wire, which rides the outer side of bends and wanders
    inside the lumen, off the centerline. Counted as independent points, that offset tilts and spins
    the fitted tree; counted as one point per ``fit_correlation_mm`` of the curve, the rotation
    stays within the roadmap prior's scale (the truth: no rotation at all)."""
    case = still_case
    vis = np.asarray(case.wire_visible[0], bool)
    uv = case.carm.project(case.wire_lps_mm[0][vis], case.pose)
    rot = {}
    for name, opt in (("default", None), ("every point", motion.MotionOptions(fit_correlation_mm=1e-3))):
        tracker = motion.MotionTracker(case.tree, case.carm, case.pose, options=opt)
        for _ in range(3):
            res = tracker.update(uv)
        assert res.verdict is Verdict.OK, res.message
        rot[name] = _rotation_deg(res.pose, case.pose)
    assert rot["default"] < 1.0  # deg; the priors: 0.5 deg tilt, 1 deg spin (1 sigma)
    assert rot["default"] < rot["every point"]


# --- the compiled solve and search (kernels.motion_solve, motion_acquire_costs) against the numpy code they replaced


def _residuals_numpy(tr, c, delta, sel, point_weight, pairs=None):
    """The numpy residuals the tracker used before ``kernels.motion_solve``: signed point-to-projected-
    tangent distances (px), their Jacobian, IRLS weights and the tree sample paired with each point."""
    opt = tr.options
    if pairs is None:
        uv_sel = tr._project(tr._moved_subset(delta, sel))
        j = sel[cKDTree(uv_sel).query(c)[1]]
    else:
        j = pairs
    Y = tr._moved_subset(delta, np.concatenate([j, tr._nbr[j]]))
    uv2 = tr._project(Y)
    Y, uv, uvn = Y[: len(j)], uv2[: len(j)], uv2[len(j):]
    tan = uvn - uv
    nrm = np.linalg.norm(tan, axis=1, keepdims=True)
    tan = np.where(nrm > 1e-9, tan / np.maximum(nrm, 1e-12), 0.0)
    d = c - uv
    n = np.stack([-tan[:, 1], tan[:, 0]], axis=1)
    n = np.where(nrm > 1e-9, n, d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12))
    r = -np.einsum("ij,ij->i", n, d)
    a = np.abs(r)
    w = (np.where(a <= opt.gate_px, 1.0 / np.sqrt(1.0 + (a / opt.huber_px) ** 2), 0.0)
         * (point_weight / opt.sigma_px**2))
    z = Y[:, 2]
    g = np.empty((len(r), 3))
    g[:, 0] = n[:, 0] * (tr._f / z)
    g[:, 1] = n[:, 1] * (tr._f / z)
    g[:, 2] = -(g[:, 0] * Y[:, 0] + g[:, 1] * Y[:, 1]) / z
    J = np.hstack([g, np.cross(Y - tr._c, g)])
    return r, J, w, j


def _solve_numpy(tr, c, start, prev, Lt, iterations):
    """The numpy Gauss-Newton the tracker used before ``kernels.motion_solve``."""
    opt = tr.options
    delta = np.array(start, float)
    uv = tr._project(tr._moved(delta))
    m = opt.gate_px + motion.CROP_MARGIN_PX
    lo, hi = c.min(axis=0) - m, c.max(axis=0) + m
    sel = np.flatnonzero((uv[:, 0] >= lo[0]) & (uv[:, 0] <= hi[0]) & (uv[:, 1] >= lo[1]) & (uv[:, 1] <= hi[1]))
    if len(sel) < 2:
        return None
    length_mm = float(np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1))) * tr._c[2] / tr._f
    pw = min(1.0, max(1.0, length_mm / opt.fit_correlation_mm) / len(c))
    it, j = 0, None
    for it in range(1, iterations + 1):
        r, J, w, j = _residuals_numpy(tr, c, delta, sel, pw, pairs=None if it % 2 else j)
        H = J.T @ (J * w[:, None]) + tr._Lambda0 + Lt
        g = J.T @ (w * r) + tr._Lambda0 @ delta + Lt @ (delta - prev)
        step = -np.linalg.solve(H, g)
        delta = delta + step
        if np.abs(step[:3]).max() < motion.STEP_TOL_MM and np.abs(step[3:]).max() < motion.STEP_TOL_RAD:
            break
    r, J, w, j = _residuals_numpy(tr, c, delta, sel, pw)
    lumen_px = tr._f * tr._radius_mm[j] / tr._moved_subset(delta, j)[:, 2]
    outside = np.maximum(np.abs(r) - lumen_px, 0.0)
    inl = outside <= opt.inlier_px
    a = np.minimum(np.abs(r), opt.gate_px) / opt.sigma_px
    h = opt.huber_px / opt.sigma_px
    cost = float(pw * np.sum(2.0 * h * h * (np.sqrt(1.0 + (a / h) ** 2) - 1.0))
                 + delta @ tr._Lambda0 @ delta + (delta - prev) @ Lt @ (delta - prev))
    return (cost, delta, it, float(inl.mean()), float(outside[inl].mean()) if inl.any() else np.inf,
            J, w, j, lumen_px)


#: the compiled code sums in another order than numpy: relative agreement required
KERNEL_RTOL = 1e-8


def test_the_compiled_solve_is_the_numpy_solve():
    case = simulate(PhantomOptions(seed=4, n_frames=6, breathing_mm=15.0, cardiac_mm=2.0), make_ct=False)
    tracker = motion.MotionTracker(case.tree, case.carm, case.pose)
    rng = np.random.default_rng(1)
    z6, n_cmp = np.zeros((6, 6)), 0
    for t in range(case.options.n_frames):
        vis = np.asarray(case.wire_visible[t], bool)
        c = case.wire_uv_px[t][vis][::3] + rng.normal(scale=0.5, size=(len(case.wire_uv_px[t][vis][::3]), 2))
        prev = np.r_[rng.normal(scale=2.0, size=3) * [1, 1, 0.1], rng.normal(scale=3e-3, size=3)]
        for start, Lt, iters in ((np.zeros(6), z6, 4), (prev, tracker._Lambda_t, 4), (prev, tracker._Lambda_t, 3),
                                 (np.r_[6.0 * tracker.cc_cam, 0, 0, 0], z6, 2)):
            ref = _solve_numpy(tracker, c, start, prev, Lt, iters)
            got = tracker._solve(c, start, prev, Lt, iterations=iters)
            assert ref is not None and got is not None
            cost, delta, _, it, frac, mean_res = got
            _, J, w, lumen_px, j = tracker._last_fit
            assert it == ref[2] and frac == ref[3] and np.array_equal(j, ref[7])
            np.testing.assert_allclose(cost, ref[0], rtol=KERNEL_RTOL)
            np.testing.assert_allclose(delta, ref[1], rtol=KERNEL_RTOL, atol=1e-10)
            np.testing.assert_allclose(mean_res, ref[4], rtol=KERNEL_RTOL, atol=1e-10)
            for a, b in ((J, ref[5]), (w, ref[6]), (lumen_px, ref[8])):
                np.testing.assert_allclose(a, b, rtol=KERNEL_RTOL, atol=1e-12)
            n_cmp += 1
    assert n_cmp == 4 * case.options.n_frames
    # a curve that no tree sample projects near: no solve, in both
    far = c + 5000.0
    assert _solve_numpy(tracker, far, np.zeros(6), np.zeros(6), z6, 4) is None
    assert tracker._solve(far, np.zeros(6), np.zeros(6), z6) is None


@pytest.mark.parametrize("seed, n_points", [(0, 60), (1, 60), (2, 60), (3, 2000), (4, 2000)])
def test_the_compiled_acquisition_search_is_the_kd_tree_one(seed, n_points):
    from guidewire3d import kernels

    rng = np.random.default_rng(seed)
    # sparse (some curve points lie beyond the gate) or dense (the nearest lies in the query's cell)
    pts = rng.uniform(0, 300, size=(n_points, 2))
    c = np.cumsum(rng.normal(scale=3.0, size=(60, 2)), axis=0) + 150.0
    step = rng.normal(size=2) * 4.0
    shifts = np.arange(-25.0, 25.5, 1.0)
    gate = 40.0
    kd = cKDTree(pts)
    ref = np.array([np.sum(np.minimum(kd.query(c - s * step, distance_upper_bound=gate)[0], gate) ** 2)
                    for s in shifts])
    got = kernels.motion_acquire_costs(pts, c, step, shifts, gate_px=gate)
    beyond = [np.isinf(kd.query(c - s * step, distance_upper_bound=gate)[0]).any() for s in shifts]
    if n_points < 100:  # some shifts put curve points beyond the gate, some not
        assert any(beyond) and not all(beyond)
    np.testing.assert_allclose(got, ref, rtol=1e-9)


def test_the_tracker_compiles_nothing_after_its_construction(still_case):
    """The tracker's constructor warms its kernels (``kernels.warm_up_motion``): each has the one compiled
    specialisation, and tracking frames (first frame, tracked ones, the second opinion) adds none."""
    from guidewire3d import kernels

    case = still_case
    tracker = motion.MotionTracker(case.tree, case.carm, case.pose, options=motion.MotionOptions(settle_every=1))
    compiled = kernels._compile_motion()
    before = {name: len(f.signatures) for name, f in compiled.items()}
    assert set(before.values()) == {1}
    uv = case.carm.project(case.wire_lps_mm[0], case.pose)
    res = [tracker.update(uv) for _ in range(3)]
    assert all(r.verdict is Verdict.OK for r in res), [r.message for r in res]
    assert {name: len(f.signatures) for name, f in compiled.items()} == before


# --- biplane: both views in one solve (motion.BiplaneMotionTracker) ------------------------------------------------
def _moved_along_beam(case, depth_mm, cc_mm):
    """The roadmap pose with the anatomy moved ``depth_mm`` along plane A's beam (room) and ``cc_mm`` along the
    patient's axis (LPS +z)."""
    return Pose(np.eye(3), depth_mm * case.carm.beam_direction) @ case.pose @ Pose(np.eye(3), [0.0, 0.0, cc_mm])


def test_biplane_tracking_sees_the_depth_one_view_cannot(still_case):
    """A rigid shift with 6 mm along plane A's beam (breathing's antero-posterior part): one view holds the depth
    at the roadmap's (its prior; the shift is invisible in the image), both views recover it."""
    case = still_case
    path = case.tree.points_lps_mm[case.wire_path_point_ids]
    moved = _moved_along_beam(case, 6.0, 5.0)
    ca = [case.carm.project(path, moved)] * 3
    cb = [case.heldout_carm.project(path, moved)] * 3
    mono = motion.track_poses(case.tree, ca, case.carm, case.pose)
    bi = motion.track_poses_biplane(case.tree, ca, cb, case.carm, case.heldout_carm, case.pose)
    assert len(bi) == 3 and all(isinstance(r, RegistrationResult) for r in bi)
    assert all(r.verdict is Verdict.OK and "both planes" in r.message for r in bi), [r.message for r in bi]
    pts = case.tree.points_lps_mm
    err_bi = [mtre_mm(r.pose, moved, pts) for r in bi]
    err_mono = [mtre_mm(r.pose, moved, pts) for r in mono]
    assert max(err_bi) < 0.5, err_bi
    assert min(err_mono) > 3.0, err_mono  # the depth is not seen in one view
    # the depth itself: the tree's centroid along plane A's beam
    c = pts.mean(axis=0)
    def depth(pose):
        return float(case.carm.beam_direction @ (pose.apply(c[None])[0] - case.pose.apply(c[None])[0]))

    assert abs(depth(bi[-1].pose) - depth(moved)) < 0.3, (depth(bi[-1].pose), depth(moved))
    assert abs(depth(mono[-1].pose) - depth(moved)) > 3.0
    # the lumen-slack objective (a curve anywhere within 0.3 radii of the centerline fits, so the pose is
    # determined only to that slack) sees it too
    slack = motion.track_poses_biplane(case.tree, ca, cb, case.carm, case.heldout_carm, case.pose,
                                       options=motion.MotionOptions(biplane_lumen_slack=0.3))
    assert all(r.verdict is Verdict.OK for r in slack)
    assert mtre_mm(slack[-1].pose, moved, pts) < 0.5 * min(err_mono)


def test_biplane_tracking_is_closer_to_breathing_than_one_view():
    """The simulator's breathing (15 mm, with its antero-posterior part and rotation) plus the cardiac
    contraction, true 2D wires in both planes: both views track the pose closer than plane A alone."""
    case = simulate(PhantomOptions(seed=3, n_frames=30, breathing_mm=15.0, cardiac_mm=2.0, biplane=True),
                    make_ct=False)
    pts = case.tree.points_lps_mm
    mono = motion.track_poses(case.tree, case.wire_uv_px, case.carm, case.pose)
    bi = motion.track_poses_biplane(case.tree, case.wire_uv_px, case.heldout_wire_uv_px, case.carm,
                                    case.heldout_carm, case.pose)
    err_mono = np.mean([mtre_mm(r.pose, case.frame_pose(t), pts) for t, r in enumerate(mono)])
    err_bi = np.mean([mtre_mm(r.pose, case.frame_pose(t), pts) for t, r in enumerate(bi)])
    assert all(r.verdict is Verdict.OK for r in bi), [r.message for r in bi]
    assert err_bi < 1.2 and err_bi < 0.75 * err_mono, (err_bi, err_mono)


def test_a_pair_without_a_plane_b_curve_falls_back_to_plane_a(still_case):
    case = still_case
    path = case.tree.points_lps_mm[case.wire_path_point_ids]
    moved = _moved_along_beam(case, 0.0, 6.0)
    ua, ub = case.carm.project(path, moved), case.heldout_carm.project(path, moved)
    bi = motion.track_poses_biplane(case.tree, [ua, ua, ua, None], [ub, None, np.zeros((0, 2)), None], case.carm,
                                    case.heldout_carm, case.pose)
    assert "both planes" in bi[0].message
    for r in bi[1:3]:  # plane A's one-view update, its verdict and priors
        assert r.verdict is Verdict.OK and "plane B shows no curve: plane A alone" in r.message, r.message
        assert mtre_mm(r.pose, moved, path) < SHIFT_TOL_MM
    assert bi[3].verdict is Verdict.FAILED and "no curve in either plane" in bi[3].message
    assert bi[3].pose.allclose(bi[2].pose, atol_mm=1e-9)
    # and plane A missing: plane B alone
    only_b = motion.track_poses_biplane(case.tree, [None], [ub], case.carm, case.heldout_carm, case.pose)
    assert "plane A shows no curve: plane B alone" in only_b[0].message
    assert mtre_mm(only_b[0].pose, moved, path) < 1.0


def test_a_plane_whose_curve_does_not_fit_makes_the_pair_uncertain(still_case):
    case = still_case
    path = case.tree.points_lps_mm[case.wire_path_point_ids]
    ua, ub = case.carm.project(path, case.pose), case.heldout_carm.project(path, case.pose)
    # plane B's curve is a straight stroke across the image that follows no vessel
    stroke = np.linspace(ub[0], ub[0] + np.array([0.0, 150.0]), 60) + np.array([25.0, 0.0])
    bi = motion.track_poses_biplane(case.tree, [ua, ua], [ub, stroke], case.carm, case.heldout_carm, case.pose)
    assert bi[0].verdict is Verdict.OK
    assert bi[1].verdict is Verdict.UNCERTAIN, bi[1].message
    assert "plane B's curve does not fit" in bi[1].message and "plane A alone" in bi[1].message
    assert mtre_mm(bi[1].pose, case.pose, path) < SHIFT_TOL_MM


def test_the_two_view_solve_with_one_view_is_the_compiled_one_view_solve(still_case):
    """``BiplaneMotionTracker._solve`` (per-view ``kernels.motion_linearize``, normal equations summed in numpy)
    restricted to plane A, with plane A's priors, is ``kernels.motion_solve``."""
    case = still_case
    bt = motion.BiplaneMotionTracker(case.tree, case.carm, case.heldout_carm, case.pose)
    A = bt.planes[0]
    bt._Lambda0 = A._Lambda0
    c = motion._prepare_curve(case.carm.project(case.wire_lps_mm[-1], case.pose @ Pose(np.eye(3), [0, 0, 4.0])))
    start = np.array([0.5, -1.0, 0.2, 0.002, -0.001, 0.003])
    prev = np.zeros(6)
    for Lt in (A._no_Lt, A._Lambda_t):
        one = A._solve(c, start, prev, Lt)
        two = bt._solve([c, None], start, prev, Lt, views=(0,))
        assert abs(one[0] - two[0]) < 1e-8 * max(1.0, abs(one[0]))
        np.testing.assert_allclose(two[1], one[1], atol=1e-10)
        assert one[3] == two[3]
        assert (one[4], one[5]) == pytest.approx(two[4][0], abs=1e-9)


def test_plane_b_delta_is_the_same_rigid_motion(still_case):
    case = still_case
    bt = motion.BiplaneMotionTracker(case.tree, case.carm, case.heldout_carm, case.pose)
    d = np.array([1.0, -2.0, 3.0, 0.01, -0.02, 0.015])
    assert bt.planes[0].pose_of(d).allclose(bt.planes[1].pose_of(bt._to_view[1] @ d), atol_mm=1e-9, atol_rad=1e-12)


def test_track_poses_biplane_refuses_unpaired_sequences(still_case):
    case = still_case
    with pytest.raises(InputError, match="plane-B"):
        motion.track_poses_biplane(case.tree, [np.zeros((0, 2))] * 2, [None], case.carm, case.heldout_carm, case.pose)


def test_biplane_session_tracks_motion_and_reconstructs_each_pair_in_its_pose():
    from guidewire3d.app.biplane import BiplaneSession

    case = simulate(PhantomOptions(seed=3, n_frames=8, breathing_mm=15.0, biplane=True), make_ct=False)
    pts = case.tree.points_lps_mm
    out = {}
    for track in (False, True):
        bs = BiplaneSession(case.tree, (case.carm, case.heldout_carm), case.pose, segmenter="ridge", threads=1,
                            track_motion=track)
        frs = [bs.process_wires(case.wire_uv_px[t], case.heldout_wire_uv_px[t]) for t in range(8)]
        bs.close()
        assert all((f.result.motion is not None) == track for f in frs)
        out[track] = [mtre_mm(f.result.pose, case.frame_pose(t), pts) for t, f in enumerate(frs)]
        if track:
            assert all(f.result.motion.pose.allclose(f.result.pose, atol_mm=1e-6) for f in frs)
            # the two-view context moved to the tracked pose is the one made there
            from guidewire3d.reconstruction.triangulation import TwoViewContext

            fresh = TwoViewContext(case.tree, bs.carms, bs.pose)
            for a, b in zip(bs.context.P, fresh.P):
                np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-9)
            np.testing.assert_allclose(bs.context.F / np.linalg.norm(bs.context.F), fresh.F / np.linalg.norm(fresh.F),
                                       atol=1e-12)
            for ca, cb in zip(bs.context.cams, fresh.cams):
                for x, y in zip(ca, cb):
                    np.testing.assert_allclose(x, y, atol=1e-9)
            w = [cKDTree(case.wire_lps_mm[t]).query(f.result.wire3d.points_lps_mm)[0].mean()
                 for t, f in enumerate(frs) if f]
            assert len(w) == 8 and np.mean(w) < 1.0, w
    assert np.mean(out[True]) < 1.0 < np.mean(out[False]), out


def test_a_first_frame_whose_wire_fits_another_vessel_is_not_acquired_confidently():
    """bench_stress --draws wide, seed 5213 (--breathing 15 --cardiac 4 --no-background): the roadmap's
    breathing phase is 14 mm from frame 0's and the contraction moves the wire's vessel across the patient's
    axis too. The acquisition's search along the axis kept a pose 11.8 mm off, where the short wire lies
    wholly in the projected lumen of another vessel 12 mm from its own, and every frame was ``ok`` (tips
    12-15 mm off). The fixture holds the tracker's inputs as the live session gave them (its tree, view,
    roadmap pose and covariance, the four frames' curves) and the true poses; it was recorded from the
    kept case with a patched ``MotionTracker.update``."""
    import json

    from guidewire3d.geometry import CArm
    from guidewire3d.vesseltree import VesselTree

    d = np.load(Path(__file__).parent / "data" / "tracking_seed5213.npz")
    tree = VesselTree(d["tree_points_lps_mm"].astype(float), d["tree_radius_mm"].astype(float), d["tree_parent"])
    trk = motion.MotionTracker(tree, CArm.from_dict(json.loads(str(d["carm_json"]))),
                               Pose.from_matrix(d["roadmap_pose"]), covariance=d["registration_covariance"])
    P = tree.points_lps_mm
    errors = []
    for k in range(int(d["n_frames"])):
        res = trk.update(d[f"curve_uv_px_{k}"].astype(float))
        T = d[f"true_pose_{k}"]
        mtre = float(np.linalg.norm(res.pose.apply(P) - (P @ T[:3, :3].T + T[:3, 3]), axis=1).mean())
        errors.append((k, res.success, round(mtre, 1), res.message))
    assert errors[0][2] > 5.0, errors  # the case: the pose found is still the wrong one ...
    for k, ok, mtre, msg in errors:  # ... but no frame says ok with its pose more than 3 mm off
        assert not ok or mtre <= 3.0, errors
    assert "not settled" in errors[0][3] and "elsewhere" in errors[0][3]
