"""The Slicer module's logic with two planes and Track motion: ``process(..., roadmap_b=..., track_motion=True)``
runs ``biplane.run(track_motion=True)`` (it used to refuse), each pair's pose follows the breathing, and both
planes' C-arms follow the tracked pose with the frame browser (slicer-core, no Qt)."""
from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import slicer  # noqa: F401,E402  (slicer-core: a test dependency, never skipped)

from guidewire3d import metrics  # noqa: E402
from guidewire3d.phantom import PhantomOptions, load_truth, simulate, write_case  # noqa: E402

PLUGIN_DIR = Path(__file__).resolve().parents[1] / "plugin" / "GuidewireReconstruction"
sys.path.insert(0, str(PLUGIN_DIR))

from GuidewireReconstructionLib import logic as L  # noqa: E402

SEED, N_FRAMES, BREATHING_MM = 3, 5, 15.0  # the case of tests/test_biplane_track_motion.py
TRACKED_POSE_TOL_MM = 1.5  # each pair's tracked pose against its true breathing pose (measured 0.7-0.8 mm)
STATIC_OFF_MM = 3.0  # the joint roadmap pose against the frames' poses, on average (measured 4.6-8.5 mm)
TRACKED_OVER_STATIC = 0.3  # tracked against static, mean over the pairs (measured 0.11)
MATRIX_ATOL = 1e-6


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    root = tmp_path_factory.mktemp("plugin-biplane-motion")
    d = write_case(simulate(PhantomOptions(seed=SEED, n_frames=N_FRAMES, breathing_mm=BREATHING_MM, biplane=True)),
                   root / "case")
    h = L.create_headless_scene(home_directory=root / "home")
    cta = h.logics["Volumes"].AddArchetypeVolume(str(sorted((d / "ct").iterdir())[0]), "CTA", 0)
    p = SimpleNamespace(ctaVolume=cta, roadmapPath=d / "roadmap.dcm", framesPath=d / "frames.dcm",
                        roadmapSequence=None, framesSequence=None, roadmapBPath=d / "roadmap_b.dcm",
                        framesBPath=d / "frames_b.dcm", roadmapBSequence=None, framesBSequence=None, seeds=None,
                        roadmapFrame=-1, method="vessel", segmenter="ridge", force=False, trackMotion=True,
                        registrationTransform=None, metricsTable=None, vesselModel=None)
    core = L.GuidewireReconstructionCoreLogic(h.scene, app_logic=h.app_logic)
    core.process_parameters(p)
    yield SimpleNamespace(h=h, core=core, out=core.outputs, truth=load_truth(d), p=p)
    h.scene.Clear(1)


def test_two_planes_with_track_motion_track_each_pair(tracked):
    core, truth = tracked.core, tracked.truth
    assert core.biplane is not None and core.track_motion
    assert len(core.frame_results) == N_FRAMES
    P = truth.tree.points_lps_mm
    static = [metrics.mtre_mm(core.registration.pose, truth.frame_pose(t), P) for t in range(N_FRAMES)]
    errs = []
    for fr in core.frame_results:
        assert fr.motion is not None, fr.message
        errs.append(metrics.mtre_mm(fr.pose, truth.frame_pose(fr.index), P))
    assert np.mean(static) > STATIC_OFF_MM, static
    assert max(errs) < TRACKED_POSE_TOL_MM, errs
    assert np.mean(errs) < TRACKED_OVER_STATIC * np.mean(static), (errs, static)


def test_both_carms_follow_the_tracked_pose_with_the_frame_browser(tracked):
    core, out = tracked.core, tracked.out
    assert out.motion_sequence is not None and out.motion_sequence.GetNumberOfDataNodes() == N_FRAMES
    browser = core._browser_for(tracked.p.framesSequence)
    proxy = browser.GetProxyNode(out.motion_sequence)
    for node in (out.carm_model, out.roadmap_points_model, out.carm_b_model, out.roadmap_b_points_model):
        assert node.GetParentTransformNode() is proxy, node.GetName()
    for t in range(N_FRAMES):
        browser.SetSelectedItemNumber(t)
        core.update_proxies(browser)
        fr = next(f for f in core.frame_results if f.index == t)
        np.testing.assert_allclose(L.pose_from_transform_node(proxy).matrix, fr.pose.matrix, atol=MATRIX_ATOL)


def test_refine_keeps_tracking_the_pairs(tracked):
    """Refine makes the wires again through ``BiplaneSession(track_motion=True)``: every pair keeps a tracked pose."""
    core, truth = tracked.core, tracked.truth
    core.refine_parameters(tracked.p)
    P = truth.tree.points_lps_mm
    assert all(fr.motion is not None for fr in core.frame_results)
    assert max(metrics.mtre_mm(fr.pose, truth.frame_pose(fr.index), P) for fr in core.frame_results) \
        < TRACKED_POSE_TOL_MM
