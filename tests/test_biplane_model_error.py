"""The biplane verdict's model error (``app.biplane.MODEL_ERROR_INFLATION``, ``_model_error_std_mm``) against ground truth.

Each roadmap's 2D centerline disagrees with the projected 3D tree by a smooth field (an automatic CTA tree's centerline
errors, its extra branches); the joint pose's model-error 1-sigma propagates each plane's field, measured at the pose
(``ViewFit.misfit_px``), through both planes' information. Checked here: the measured field against a field imposed on
a simulated roadmap, the model-error 1-sigma of a tree displaced by a smooth 3D field against the clean tree's, and the
verdict's use of it."""
import sys
from pathlib import Path

import numpy as np
import pytest
from guidewire3d import metrics
from guidewire3d.app import biplane
from guidewire3d.phantom import PhantomOptions, simulate
from guidewire3d.registration import Verdict, verdict
from guidewire3d.vesseltree import VesselTree
from test_biplane import _projected_centerline

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from diagnose_real_anatomy import smooth_offsets_px  # noqa: E402

FIELD_TOL = 0.3  # the measured field (RMS over N_FIELDS draws) within this fraction of the imposed one
N_FIELDS = 6
CLEAN_FIELD_PX = 0.1  # exact (projected true) centerlines: a field far below verdict.MODEL_ERROR_PX
DISPLACED_MM = 0.5  # the 3D tree displaced by a smooth field of this rms per component ...
DISPLACED_LENGTH_MM = 30.0  # ... correlated over this length
SUCCESS_MM = 2.0


@pytest.fixture(scope="module")
def case():
    """A biplane case without CT: seed 1, plane B 90 deg from plane A, and both planes' exact centerlines."""
    c = simulate(PhantomOptions(seed=1, n_frames=1, biplane=True), make_ct=False)
    carms = (c.carm, c.heldout_carm)
    return c, carms, [_projected_centerline(c.tree, cm, c.pose) for cm in carms]


def _displaced(tree: VesselTree, rms_mm: float, length_mm: float, rng, n_waves: int = 8) -> VesselTree:
    """``tree`` with its points moved by a smooth random 3D field (plane waves, ``rms_mm`` per component)."""
    p = tree.points_lps_mm
    k = rng.normal(0.0, 1.0 / length_mm, (n_waves, 3))
    ph = rng.uniform(0.0, 2.0 * np.pi, (n_waves, 3))
    f = np.stack([np.sin(p @ k.T + ph[:, d]).sum(axis=1) for d in range(3)], axis=1) / np.sqrt(0.5 * n_waves)
    return VesselTree(p + rms_mm * f, tree.radius_mm, tree.parent)


def test_the_measured_field_is_the_imposed_one(case):
    """Plane B's centerline moved by smooth random fields of a known 1-sigma (correlated over
    ``verdict.MODEL_ERROR_LENGTH_PX``): plane B's measured field, RMS over the draws, is that 1-sigma within
    ``FIELD_TOL`` (each draw's own realisation varies: 0.5-1.2x; the pose absorbs part of each field), plane A's (exact)
    stays below half of it, and the model-error 1-sigma grows with the field."""
    c, carms, cls = case
    clean = biplane.register_biplane(c.tree, cls, carms, init_pose=c.pose, global_search=False)
    assert clean.success and all(v.misfit_px < CLEAN_FIELD_PX for v in clean.views)
    rng = np.random.default_rng(0)
    for rms_px in (0.5, 1.0):
        measured = []
        for _ in range(N_FIELDS):
            moved = cls[1] + smooth_offsets_px(cls[1], rms_px, verdict.MODEL_ERROR_LENGTH_PX, rng)
            r = biplane.register_biplane(c.tree, [cls[0], moved], carms, init_pose=c.pose, global_search=False)
            a, b = r.views
            measured.append(b.misfit_px)
            assert a.misfit_px < 0.5 * rms_px
            assert r.result.model_std_mm > clean.result.model_std_mm
            assert b.to_dict()["misfit_px"] == pytest.approx(b.misfit_px, abs=1e-4)
        assert abs(np.sqrt(np.mean(np.square(measured))) - rms_px) <= FIELD_TOL * rms_px, (rms_px, measured)


def test_a_tree_displaced_by_a_smooth_field_has_a_larger_model_error(case):
    """The roadmaps from the true tree, the registration to a tree displaced by a smooth 3D field (an extracted
    centerline's error): the measured fields and the model-error 1-sigma are several times the clean tree's, which stays
    ``ok`` and right; the displaced tree's pose is off by at least its model-error 1-sigma (first order, it does not
    overstate the error)."""
    c, carms, cls = case
    clean = biplane.register_biplane(c.tree, cls, carms)
    assert clean.success and clean.result.verdict is Verdict.OK
    assert metrics.mtre_mm(clean.pose, c.pose, c.tree.points_lps_mm) < 0.1
    assert np.isfinite(clean.result.model_std_mm) and "model-error 1-sigma" in clean.result.message
    rng = np.random.default_rng(1)
    for _ in range(2):
        r = biplane.register_biplane(_displaced(c.tree, DISPLACED_MM, DISPLACED_LENGTH_MM, rng), cls, carms)
        assert r.result.fits_2d
        assert max(v.misfit_px for v in r.views) > verdict.MODEL_ERROR_PX > CLEAN_FIELD_PX
        assert r.result.model_std_mm > 3.0 * clean.result.model_std_mm
        err = metrics.mtre_mm(r.pose, c.pose, c.tree.points_lps_mm)
        assert r.result.model_std_mm <= err < SUCCESS_MM


def test_the_model_error_gates_the_verdict(case, monkeypatch):
    """``success`` needs hypot(pose 1-sigma, ``MODEL_ERROR_INFLATION`` x model-error 1-sigma) within the limit: with
    the factor set just over what a registration tolerates it is ``uncertain`` and the message names the plane whose
    roadmap disagrees; 0 turns the gate off."""
    c, carms, cls = case
    moved = cls[1] + smooth_offsets_px(cls[1], 1.0, verdict.MODEL_ERROR_LENGTH_PX, np.random.default_rng(2))
    args = (c.tree, [cls[0], moved], carms)
    r = biplane.register_biplane(*args, init_pose=c.pose, global_search=False).result
    assert r.success and r.verdict is Verdict.OK
    assert np.hypot(r.pose_std_mm, biplane.MODEL_ERROR_INFLATION * r.model_std_mm) <= r.max_pose_std_mm
    f = 1.05 * np.sqrt(r.max_pose_std_mm**2 - r.pose_std_mm**2) / r.model_std_mm
    monkeypatch.setattr(biplane, "MODEL_ERROR_INFLATION", f)
    big = biplane.register_biplane(*args, init_pose=c.pose, global_search=False)
    assert big.result.model_std_mm == pytest.approx(r.model_std_mm, rel=1e-9)
    assert not big.success and big.result.fits_2d and big.result.verdict is Verdict.UNCERTAIN
    assert "model error: plane B's 2D centerline" in big.result.message
    monkeypatch.setattr(biplane, "MODEL_ERROR_INFLATION", 0.0)
    assert biplane.register_biplane(*args, init_pose=c.pose, global_search=False).success
