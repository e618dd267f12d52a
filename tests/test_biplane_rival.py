"""The biplane second opinion (app.biplane._closest_rival): which LM end counts as a rival, and that it is reported."""
from types import SimpleNamespace

import numpy as np
import pytest

from guidewire3d import metrics
from guidewire3d.app import biplane
from guidewire3d.geometry import Pose
from guidewire3d.phantom import PhantomOptions, simulate
from guidewire3d.registration import model, problem

POSE_TOL_MM = 0.5  # joint registration mTRE on exact (projected true) centerlines
DIST_TOL_MM = 1e-9  # the RMS distance of a pure translation is its length


@pytest.fixture(scope="module")
def bcase():
    """A biplane case without CT (fast): seed 1, plane B 90 deg from plane A."""
    return simulate(PhantomOptions(seed=1, n_frames=1, biplane=True), make_ct=False)


def _projected_centerline(tree, carm, pose):
    polys = [tree.points_lps_mm[b.point_ids] for b in tree.branches]
    uv = np.vstack([metrics.resample_polyline(carm.project(metrics.resample_polyline(p, 0.1), pose), 1.0)
                    for p in polys])
    return uv[carm.in_image(uv)]


def _end(pose, energy):
    return SimpleNamespace(pose=pose, ev=SimpleNamespace(energy=energy))


def _moved(pose, mm):
    return Pose(np.eye(3), np.array([float(mm), 0.0, 0.0])) @ pose


def test_the_rival_is_the_lowest_end_far_enough_and_low_enough():
    """Ground truth by construction: the ends are the result translated by known distances (RMS over any points = the
    translation), with known energies."""
    rng = np.random.default_rng(0)
    pts = rng.normal(scale=30.0, size=(200, 3))
    out = _end(Pose(np.eye(3), np.zeros(3)), 1000.0)
    near_low = _end(_moved(out.pose, 0.5), 1001.0)  # the same answer: closer than min_mm
    far_high = _end(_moved(out.pose, 6.0), 1000.0 * (biplane.AMBIGUITY_ENERGY_RATIO + 0.01))  # clearly worse
    far_low = _end(_moved(out.pose, 3.0), 1020.0)
    farther_lower = _end(_moved(out.pose, 4.0), 1010.0)
    assert biplane._closest_rival(out, [near_low, far_high], pts, min_mm=1.0) is None
    pose, d, ratio = biplane._closest_rival(out, [near_low, far_high, far_low, farther_lower], pts, min_mm=1.0)
    assert pose is farther_lower.pose  # the lowest energy among those far enough, not the nearest
    assert abs(d - 4.0) < DIST_TOL_MM and ratio == pytest.approx(1.01)
    # the limit on the distance is the caller's (the pose 1-sigma limit when larger than AMBIGUITY_MM)
    assert biplane._closest_rival(out, [far_low, farther_lower], pts, min_mm=4.5) is None


def test_the_rival_that_makes_it_uncertain_is_reported(bcase):
    """The registration reports the rival it was refused for (its pose, distance and energy ratio), and none when the
    other end is clearly worse; the pose itself is right either way."""
    carms = (bcase.carm, bcase.heldout_carm)
    cls = [_projected_centerline(bcase.tree, c, bcase.pose) for c in carms]
    finish, ratio = biplane._finish, [1.02]
    injected = []

    def with_rival(prob, out, qs, cs, iterations, t0, *, rivals=()):
        injected.append(_moved(out.pose, 3.0))
        return finish(prob, out, qs, cs, iterations, t0, rivals=[_end(injected[-1], out.ev.energy * ratio[0])])

    biplane._finish = with_rival
    try:
        amb = biplane.register_biplane(bcase.tree, cls, carms)
        ratio[0] = 1.5
        clear = biplane.register_biplane(bcase.tree, cls, carms)
    finally:
        biplane._finish = finish
    for r in (amb, clear):
        assert metrics.mtre_mm(r.pose, bcase.pose, bcase.tree.points_lps_mm) < POSE_TOL_MM
    assert amb.result.verdict.value == "uncertain" and amb.rival_pose is injected[0]
    assert amb.rival_mm == pytest.approx(3.0) and amb.rival_energy_ratio == pytest.approx(1.02)
    assert "another pose 3.0 mm away" in amb.result.message and "2.0% higher" in amb.result.message
    assert clear.success and clear.rival_pose is None
    assert np.isnan(clear.rival_mm) and np.isnan(clear.rival_energy_ratio)


def test_starts_in_one_basin_end_in_one_minimum_and_no_rival(bcase):
    """Exact centerlines (one minimum, at the truth): LM from the truth and from starts millimetres and degrees away
    ends at the truth from every start (one end, the others merged with it), so the second opinion has no rival to
    weigh and the registration is ok."""
    carms = (bcase.carm, bcase.heldout_carm)
    qs = [_projected_centerline(bcase.tree, c, bcase.pose) for c in carms]
    m3 = model._model_from_input(bcase.tree, carms[0])
    prob = biplane._JointProblem([problem._Problem(m3, model._model_2d(q, None, c), c, lam=problem.LAMBDA,
                                                   delta=problem.DELTA) for q, c in zip(qs, carms)])
    d = carms[0].beam_direction
    turn = Pose.from_rotvec_about(np.radians([0.0, 0.0, 2.0]), bcase.pose.apply(m3.centroid))
    starts = [bcase.pose, Pose(np.eye(3), 3.0 * d) @ bcase.pose, turn @ Pose(np.eye(3), [-2.0, 1.0, 0.0]) @ bcase.pose]
    ends, iterations = biplane._multi_start_lm(prob, starts, gate_wide_px=problem.GATE_WIDE_PX,
                                               delta_wide=problem.DELTA_WIDE, max_iterations=100)
    assert len(ends) == 1  # every start's wide stage ended within SAME_POSE_MM of the first one's: one minimum
    out, visible = ends[0]
    assert metrics.mtre_mm(out.pose, bcase.pose, bcase.tree.points_lps_mm) < POSE_TOL_MM
    for p, v in zip(prob.probs, visible):
        p.visible3 = v
    res = biplane._finish(prob, out, qs, carms, iterations, 0.0, rivals=[o for o, _ in ends[1:]])
    assert res.success and res.rival_pose is None
