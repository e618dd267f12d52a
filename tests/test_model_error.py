"""The registration verdict's model-error opinion (``verdict.MODEL_ERROR_PX``) against ground truth.

A single view fixes the depth through perspective alone, so a smooth disagreement of the 2D and the projected 3D
centerline (not independent per point: the Gauss-Newton covariance does not see it) moves the pose along the beam.
The verdict propagates a Gaussian random field of that disagreement to the pose to first order. Checked here
against the truth, the pose actually re-fitted after moving the 2D points by such fields, and its use in
``success`` (off by default)."""
import sys
from pathlib import Path

import numpy as np
import pytest
from guidewire3d import registration as reg
from guidewire3d.registration import verdict
from test_registration import _case, _centerline

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from diagnose_real_anatomy import smooth_offsets_px  # noqa: E402

N_FIELDS = 12


def _rms_displacement_mm(pose_a, pose_b, points_lps_mm) -> float:
    d = pose_a.apply(points_lps_mm) - pose_b.apply(points_lps_mm)
    return float(np.sqrt((d**2).sum(axis=1).mean()))


@pytest.mark.parametrize("seed", [0, 3])
def test_model_error_predicts_the_refit_pose_spread(seed):
    """The pose re-fitted from the 2D centerline moved by smooth random fields (``MODEL_ERROR_PX`` rms per
    component, correlated over ``MODEL_ERROR_LENGTH_PX``) spreads as ``model_std_mm`` says, within a factor 2
    (the re-fit re-matches points and is robust; the prediction is first order)."""
    tree, carm, true = _case(seed)
    uv = _centerline(tree, carm, true)
    r0 = reg.refine(tree, uv, carm, true)
    assert r0.fits_2d and np.isfinite(r0.model_std_mm) and r0.model_std_mm > 0
    rng = np.random.default_rng(seed)
    moved = []
    for _ in range(N_FIELDS):
        dq = smooth_offsets_px(uv, verdict.MODEL_ERROR_PX, verdict.MODEL_ERROR_LENGTH_PX, rng)
        r = reg.refine(tree, uv + dq, carm, r0.pose)
        moved.append(_rms_displacement_mm(r.pose, r0.pose, tree.points_lps_mm))
    actual = float(np.sqrt(np.mean(np.square(moved))))
    assert 0.5 * r0.model_std_mm <= actual <= 2.0 * r0.model_std_mm, (actual, r0.model_std_mm)
    # a correlated error, not the independent points' covariance again: several times its uninflated 1-sigma
    assert r0.model_std_mm > 3 * r0.pose_std_mm / verdict.COVARIANCE_INFLATION


def test_model_error_is_reported_and_gates_only_when_asked(monkeypatch):
    """Reported on a pose that passes the screen (message, record); by default it does not change ``success``.
    With ``MODEL_ERROR_GATE`` ``success`` needs hypot(pose 1-sigma, model-error 1-sigma) within the screen: a model
    error that takes the combined 1-sigma just over the limit refuses the same registration with a named reason."""
    tree, carm, true = _case(0)
    uv = _centerline(tree, carm, true)
    r = reg.refine(tree, uv, carm, true)
    assert r.success and np.isfinite(r.model_std_mm) and "model-error 1-sigma" in r.message
    assert r.to_dict()["model_std_mm"] == pytest.approx(r.model_std_mm)
    monkeypatch.setattr(verdict, "MODEL_ERROR_GATE", True)
    assert reg.refine(tree, uv, carm, true).success == bool(np.hypot(r.pose_std_mm, r.model_std_mm)
                                                           <= r.max_pose_std_mm)
    # the opinion is linear in MODEL_ERROR_PX: set it so that the combined 1-sigma is just over the limit
    px0 = verdict.MODEL_ERROR_PX
    px = 1.05 * np.sqrt(r.max_pose_std_mm**2 - r.pose_std_mm**2) / r.model_std_mm * px0
    monkeypatch.setattr(verdict, "MODEL_ERROR_PX", px)
    big = reg.refine(tree, uv, carm, true)
    assert big.model_std_mm == pytest.approx(r.model_std_mm * px / px0, rel=1e-6)
    assert not big.success and big.fits_2d and big.verdict is reg.Verdict.UNCERTAIN
    assert "(model error)" in big.message
    monkeypatch.setattr(verdict, "MODEL_ERROR_GATE", False)
    assert reg.refine(tree, uv, carm, true).success                          # reported only, by default
    monkeypatch.setattr(verdict, "MODEL_ERROR_PX", 0.0)
    assert np.isnan(reg.refine(tree, uv, carm, true).model_std_mm)           # 0: not computed
