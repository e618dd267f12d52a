"""Viewer tests: data loading, scene geometry and pixels (offscreen EGL), controller, CLI, real window."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from guidewire3d.app import cli
from guidewire3d.errors import InputError
from guidewire3d.geometry import Pose
from guidewire3d.metrics import mtre_mm

sys.path.insert(0, str(Path(__file__).parent))
from viewer_fixture import write_synthetic_outdir  # noqa: E402

pv = pytest.importorskip("pyvista")

from guidewire3d.viewer import scene as sc  # noqa: E402
from guidewire3d.viewer.app import open_viewer, parse_size  # noqa: E402
from guidewire3d.viewer.controller import STEP_DEG, STEP_MM, Axis, ExportKind, Step, ViewerController  # noqa: E402
from guidewire3d.app.outdir import display_images_uint8, load_outdir  # noqa: E402

SIZE = (480, 320)
TOL_POINT_MM = 1e-6
TOL_REFINE_MTRE_MM = 0.5
TOL_CHROMA_COS = 0.97
MIN_HIT_FRACTION = 0.85
DARK_FRACTION = 0.6  # vessel pixels must be darker than this fraction of the background


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    return write_synthetic_outdir(tmp_path_factory.mktemp("viewer_case"), n_frames=4)


@pytest.fixture()
def case_dir(synth, tmp_path):
    """A private copy of the OUT_DIR (controllers write registration.json and exports into it)."""
    dst = tmp_path / "out"
    shutil.copytree(synth.out_dir, dst)
    return dst


@pytest.fixture()
def viewer(case_dir):
    ctl, h = open_viewer(case_dir, size_px=SIZE, off_screen=True)
    yield ctl, h
    h.plotter.close()


def _grab(plotter) -> np.ndarray:
    plotter.render()
    return np.asarray(plotter.screenshot(None, return_img=True))[..., :3].astype(float)


# --------------------------------------------------------------------------------------
# data
# --------------------------------------------------------------------------------------
def test_load_outdir_matches_what_was_written(synth):
    case = load_outdir(synth.out_dir)
    assert case.n_frames == 4
    assert case.pose.allclose(synth.pose, atol_mm=1e-9, atol_rad=1e-12)
    assert case.pose_source == "automatic"
    for w, truth, unc in zip(case.wires, synth.wires_lps_mm, synth.uncertainty_mm):
        np.testing.assert_allclose(w.points_lps_mm, truth, atol=TOL_POINT_MM)
        np.testing.assert_allclose(w.uncertainty_mm, unc, atol=1e-12)
    np.testing.assert_allclose(case.images, synth.images, atol=0.51)  # uint16 rounding in the DICOM
    np.testing.assert_allclose(case.tree.points_lps_mm, synth.tree.points_lps_mm)
    assert case.messages == ()


def test_load_outdir_bad_input(tmp_path, synth):
    with pytest.raises(InputError, match="no such output folder"):
        load_outdir(tmp_path / "absent")
    with pytest.raises(InputError, match="report.json: no such file"):
        load_outdir(tmp_path)
    bad = tmp_path / "bad"
    shutil.copytree(synth.out_dir, bad)
    rep = json.loads((bad / "report.json").read_text())
    rep["frames"][1]["uncertainty_mm"] = [1.0, 2.0]
    (bad / "report.json").write_text(json.dumps(rep))
    with pytest.raises(InputError, match=r"frames\[1\]: uncertainty_mm has 2 values"):
        load_outdir(bad)
    (bad / "registration.json").write_text("{not json")
    with pytest.raises(InputError, match="registration.json: not valid JSON"):
        load_outdir(bad)


def test_display_window_is_shared_and_input_untouched(synth):
    imgs = synth.images.copy()
    u8 = display_images_uint8(imgs)
    assert u8.dtype == np.uint8 and u8.shape == imgs.shape
    np.testing.assert_array_equal(imgs, synth.images)
    # one window for the run: the same raw value maps to the same grey in every frame
    v = float(np.median(imgs))
    g = [u8[k][np.abs(imgs[k] - v) < 1.0] for k in range(len(imgs))]
    assert max(np.ptp(np.concatenate(g)), 0) <= 1


# --------------------------------------------------------------------------------------
# scene: numbers
# --------------------------------------------------------------------------------------
def test_scene_bounds_and_point_counts(viewer, synth):
    ctl, h = viewer
    w0 = synth.wires_lps_mm[0]
    assert h.wire.polyline.n_points == len(w0)
    np.testing.assert_allclose(np.asarray(h.wire.polyline.points), w0, atol=TOL_POINT_MM)
    _grab(h.plotter)
    tube = pv.wrap(h.wire.tube.GetOutput())
    lo, hi = w0.min(0), w0.max(0)
    b = np.asarray(tube.bounds).reshape(3, 2)
    assert np.all(b[:, 0] >= lo - sc.WIRE_RADIUS_MM - 1e-6) and np.all(b[:, 1] <= hi + sc.WIRE_RADIUS_MM + 1e-6)
    assert np.all(b[:, 0] <= lo) and np.all(b[:, 1] >= hi)
    surf = pv.read(synth.out_dir / "vessels.vtp")
    np.testing.assert_allclose(h.vessels_actor.GetBounds(), surf.bounds, atol=1e-6)
    np.testing.assert_allclose(np.asarray(h.carm.detector.points), synth.carm.detector_corners_lps_mm(synth.pose),
                               atol=1e-9)
    np.testing.assert_allclose(h.carm.source.GetCenter(), synth.carm.source_lps_mm(synth.pose), atol=1e-9)
    # the 2D overlay: one point per tree point, at the projected pixel (u, -v)
    uv = synth.carm.project(synth.tree.points_lps_mm, synth.pose)
    np.testing.assert_allclose(np.asarray(h.overlay.centerline.points)[:, :2], np.column_stack([uv[:, 0], -uv[:, 1]]),
                               atol=1e-9)
    assert h.overlay.centerline.n_cells == synth.tree.n_points - 1


def test_update_wire_drops_repeated_points_and_keeps_their_uncertainty():
    pl = sc.new_plotter(size_px=(64, 64), off_screen=True, two_views=False)
    try:
        h = sc.add_wire(pl, np.zeros((0, 3)), np.zeros(0))
        assert not h.actor.GetVisibility()
        pts = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 0], [2, 1, 0], [3, 1, 1.0]])
        unc = np.array([0.1, 0.2, 0.25, 0.3, 0.4])
        pts_in, unc_in = pts.copy(), unc.copy()
        sc.update_wire(h, pts, unc)
        np.testing.assert_array_equal(pts, pts_in)  # inputs untouched
        np.testing.assert_array_equal(unc, unc_in)
        np.testing.assert_allclose(np.asarray(h.polyline.points), pts[[0, 1, 3, 4]])
        np.testing.assert_allclose(h.polyline.point_data["uncertainty_mm"], unc[[0, 1, 3, 4]])
        assert h.actor.GetVisibility() and h.polyline.n_cells == 1
    finally:
        pl.close()


# --------------------------------------------------------------------------------------
# scene: pixels
# --------------------------------------------------------------------------------------
def test_wire_colour_appears_where_the_wire_projects(viewer, synth):
    ctl, h = viewer
    ctl.set_frame(3)
    for a in (h.vessels_actor, h.centerline_actor, h.help_text):
        a.SetVisibility(False)
    w = synth.wires_lps_mm[3]
    unc = synth.uncertainty_mm[3]
    with_wire = _grab(h.plotter)
    h.wire.actor.SetVisibility(False)
    without = _grab(h.plotter)
    h.wire.actor.SetVisibility(True)
    xy = np.rint(sc.world_to_display_px(h.renderer_3d, w)).astype(int)
    lut = h.wire.actor.GetMapper().GetLookupTable()
    expect = np.zeros((len(unc), 3))
    for i, u in enumerate(unc):
        lut.GetColor(float(u), expect[i])
    inside = (xy[:, 0] >= 0) & (xy[:, 0] < SIZE[0] // 2) & (xy[:, 1] >= 0) & (xy[:, 1] < SIZE[1])
    assert inside.mean() > 0.95  # the default camera shows the whole wire in the 3D viewport
    xy, expect = xy[inside], expect[inside]

    def chroma_match(img):
        px = img[xy[:, 1], xy[:, 0]]
        cos = (px * expect).sum(1) / (np.linalg.norm(px, axis=1) * np.linalg.norm(expect, axis=1) + 1e-9)
        return (cos > TOL_CHROMA_COS) & (np.linalg.norm(px - img.mean((0, 1)), axis=1) > 20)

    assert chroma_match(with_wire).mean() >= MIN_HIT_FRACTION
    assert chroma_match(without).mean() < 0.3  # what matched was the wire


def test_detector_texture_lines_up_from_the_source(synth):
    """Seen from the X-ray source, the textured detector shows the vessels where the tree projects."""
    case = load_outdir(synth.out_dir)
    carm, pose = case.frames_carm, case.pose
    rows, cols = carm.shape
    pl = sc.new_plotter(size_px=(cols, rows), off_screen=True, two_views=False)
    try:
        u8 = display_images_uint8(case.images)[0]
        sc.add_carm(pl, carm, pose, u8)
        sc.beams_eye_camera(pl.renderer, carm, pose)
        img = _grab(pl).mean(axis=2)
    finally:
        pl.close()
    assert img.shape == (rows, cols)
    # seen from the source the display convention is mirrored: screen column = cols - 1 - u, row = v
    expected = u8[:, ::-1].astype(float)
    corr = np.corrcoef(img.ravel(), expected.ravel())[0, 1]
    assert corr > 0.95
    assert np.corrcoef(img.ravel(), u8.astype(float).ravel())[0, 1] < 0.5  # unmirrored would be wrong
    uv = synth.centerline_uv_px
    uv = uv[carm.in_image(uv, margin_px=2)]
    c = np.rint(cols - 1 - uv[:, 0]).astype(int)
    r = np.rint(uv[:, 1]).astype(int)
    background = np.median(img)
    assert np.median(img[r, c]) < DARK_FRACTION * background
    assert np.mean(img[r, c] < DARK_FRACTION * background) > 0.9


def test_2d_view_centerline_overlay_lies_on_the_dark_vessels(viewer, synth):
    ctl, h = viewer
    o = h.overlay
    for a in (o.centerline_actor, o.wire2d_actor, o.wire_proj_actor, h.info_text, h.status_text):
        a.SetVisibility(False)
    img = _grab(h.plotter).mean(axis=2)
    pts = np.asarray(o.centerline.points)
    xy = np.rint(sc.world_to_display_px(h.renderer_2d, pts)).astype(int)
    assert np.all(xy[:, 0] >= SIZE[0] // 2)  # drawn in the right-hand viewport
    vals = img[xy[:, 1], xy[:, 0]]
    right = img[:, SIZE[0] // 2:]
    background = np.median(right[right > 0])
    assert np.mean(vals < DARK_FRACTION * background) > 0.9


# --------------------------------------------------------------------------------------
# biplane: plane B's detector and 2D view (issue 23)
# --------------------------------------------------------------------------------------
PLANE_B_DEG = (-70.0, 0.0)
TOL_BIPLANE_WIRE_MM = 0.5  # apply from both planes' exact 2D wires: mean distance to the synthetic wire


@pytest.fixture(scope="module")
def bsynth(tmp_path_factory):
    return write_synthetic_outdir(tmp_path_factory.mktemp("viewer_biplane"), n_frames=4, plane_b_deg=PLANE_B_DEG)


@pytest.fixture()
def bviewer(bsynth, tmp_path):
    dst = tmp_path / "out"
    shutil.copytree(bsynth.out_dir, dst)
    ctl, h = open_viewer(dst, size_px=(600, 400), off_screen=True, persist=False)
    yield ctl, h
    h.plotter.close()


def _texture_b(hb, shape) -> np.ndarray:
    from vtk.util.numpy_support import vtk_to_numpy

    return vtk_to_numpy(hb.carm.texture_image.GetPointData().GetScalars())[:, 0].reshape(shape)


def test_biplane_shows_both_planes_and_follows_the_frames(bviewer, bsynth):
    from viewer_fixture import PLANE_B_PROJECTION_ERRORS_PX

    ctl, h = bviewer
    hb, carm_b, pose, tree = ctl.plane_b_scene, bsynth.carm_b, bsynth.pose, bsynth.tree
    assert len(h.plotter.renderers) == 3 and hb.renderer_2d is not h.renderer_2d
    # 3D view: both detectors, each where its own geometry puts it
    actors = h.renderer_3d.actors
    assert {"detector", "detector_b", "xray_source", "xray_source_b", "frustum", "frustum_b"} <= set(actors)
    np.testing.assert_allclose(np.asarray(h.carm.detector.points), bsynth.carm.detector_corners_lps_mm(pose), atol=1e-9)
    np.testing.assert_allclose(np.asarray(hb.carm.detector.points), carm_b.detector_corners_lps_mm(pose), atol=1e-9)
    lo, hi = np.asarray(actors["detector_b"].GetBounds()).reshape(3, 2).T
    corners = carm_b.detector_corners_lps_mm(pose)
    np.testing.assert_allclose(lo, corners.min(0), atol=1e-6)
    np.testing.assert_allclose(hi, corners.max(0), atol=1e-6)
    # plane B's 2D view: the centerline projected with plane B's C-arm, one point per tree point
    uv = carm_b.project(tree.points_lps_mm, pose)
    np.testing.assert_allclose(np.asarray(hb.overlay.centerline.points)[:, :2], uv * [1, -1], atol=1e-9)
    assert hb.overlay.centerline.n_cells == tree.n_points - 1
    np.testing.assert_allclose(ctl.plane_b.images, bsynth.images_b, atol=0.51)  # as written (integer pixels)
    u8_b = display_images_uint8(ctl.plane_b.images)
    n_actors = (h.renderer_3d.GetActors().GetNumberOfItems(), hb.renderer_2d.GetActors().GetNumberOfItems())
    for k in (2, 0, 3):
        ctl.set_frame(k)
        assert ctl.plane_b_image_index == k + 1  # the pair's plane-B frame, not plane A's index
        np.testing.assert_array_equal(_texture_b(hb, carm_b.shape), u8_b[k + 1])
        np.testing.assert_array_equal(_texture(h), display_images_uint8(ctl.case.images)[k])
        w2 = np.asarray(hb.overlay.wire2d.points)
        assert len(w2) == len(bsynth.wires_uv_b[k])
        np.testing.assert_allclose(w2[:, :2], bsynth.wires_uv_b[k] * [1, -1], atol=1e-9)
        wp = np.asarray(hb.overlay.wire_proj.points)
        np.testing.assert_allclose(wp[:, :2], carm_b.project(bsynth.wires_lps_mm[k], pose) * [1, -1], atol=1e-6)
        assert (h.renderer_3d.GetActors().GetNumberOfItems(), hb.renderer_2d.GetActors().GetNumberOfItems()) == n_actors
    ea, eb = PLANE_B_PROJECTION_ERRORS_PX
    text = ctl.info_text_b()
    assert "PLANE B frame 4" in text and f"A {ea:.2f} px, B {eb:.2f} px" in text and "planes A + B" in text
    assert hb.info_text.GetInput() == text
    assert ctl.next_frame() == 0 and ctl.plane_b_image_index == 1


def test_biplane_wire_colour_where_it_projects_in_plane_b(bviewer, bsynth):
    ctl, h = bviewer
    hb = ctl.plane_b_scene
    ctl.set_frame(3)
    for a in (hb.overlay.centerline_actor, hb.overlay.wire2d_actor, hb.info_text, h.status_text):
        a.SetVisibility(False)
    img = _grab(h.plotter)
    W, H = h.plotter.window_size
    pts = np.asarray(hb.overlay.wire_proj.points)
    xy = np.rint(sc.world_to_display_px(hb.renderer_2d, pts)).astype(int)
    assert np.all(xy[:, 0] >= W // 2) and np.all(xy[:, 1] >= H // 2)  # bottom right: plane B's view
    px = img[xy[:, 1], xy[:, 0]] / 255.0
    green = np.asarray(sc.WIRE_PROJ_COLOR)
    cos = (px * green).sum(1) / (np.linalg.norm(px, axis=1) * np.linalg.norm(green) + 1e-9)
    assert np.mean(cos > TOL_CHROMA_COS) >= MIN_HIT_FRACTION
    hb.overlay.wire_proj_actor.SetVisibility(False)
    px = _grab(h.plotter)[xy[:, 1], xy[:, 0]] / 255.0
    cos = (px * green).sum(1) / (np.linalg.norm(px, axis=1) * np.linalg.norm(green) + 1e-9)
    assert np.mean(cos > TOL_CHROMA_COS) < 0.1  # what matched was the projected wire (the frame is grey)
    # plane B's live frame: dark vessels where plane B's C-arm projects the tree
    grey = _grab(h.plotter).mean(axis=2)
    uv = bsynth.carm_b.project(bsynth.tree.points_lps_mm, bsynth.pose)
    xy = np.rint(sc.world_to_display_px(hb.renderer_2d, np.column_stack([uv[:, 0], -uv[:, 1], np.zeros(len(uv))])))
    xy = xy.astype(int)
    quad = grey[H // 2:, W // 2:]
    background = np.median(quad[quad > 0])
    assert np.mean(grey[xy[:, 1], xy[:, 0]] < DARK_FRACTION * background) > 0.9


def test_biplane_nudge_moves_plane_b_and_apply_uses_both_planes(bviewer, bsynth):
    from guidewire3d.metrics import wire_errors_mm

    ctl, h = bviewer
    hb, carm_b = ctl.plane_b_scene, bsynth.carm_b
    ctl.set_frame(1)
    pose = ctl.nudge(Axis.U, +1)
    np.testing.assert_allclose(np.asarray(hb.carm.detector.points), carm_b.detector_corners_lps_mm(pose), atol=1e-9)
    np.testing.assert_allclose(np.asarray(hb.overlay.centerline.points)[:, :2],
                               carm_b.project(bsynth.tree.points_lps_mm, pose) * [1, -1], atol=1e-9)
    assert "wires stale" in ctl.info_text_b()
    ctl.reset()
    assert ctl.apply(force=True) == 4
    assert "from both planes" in ctl.status
    for k, w in enumerate(bsynth.wires_lps_mm):
        ctl.set_frame(k)
        fb = ctl.plane_b_frame
        assert fb.views == "AB" and fb.index_b == k + 1
        assert fb.projection_error_px_a < 1.0 and fb.projection_error_px_b < 1.0
        assert wire_errors_mm(ctl.wire.points_lps_mm, w)["mean_error_mm"] < TOL_BIPLANE_WIRE_MM
        np.testing.assert_allclose(np.asarray(hb.overlay.wire_proj.points)[:, :2],
                                   carm_b.project(ctl.wire.points_lps_mm, ctl.pose) * [1, -1], atol=1e-6)


def test_biplane_refine_fits_both_roadmaps(bviewer, bsynth, monkeypatch):
    """Dragged 6 mm along plane A's beam (the depth one view barely sees) and turned 1-2 deg, the
    refine fits both planes' roadmap centerlines (the joint problem, from the current pose) and
    comes back to the true pose."""
    from guidewire3d.app import biplane

    calls = []
    joint = biplane.register_biplane
    monkeypatch.setattr(biplane, "register_biplane", lambda *a, **k: (calls.append((a, k)), joint(*a, **k))[1])
    ctl, h = bviewer
    assert ctl.refines_both_planes and len(ctl.plane_b.centerline_uv_px) >= 10
    assert ctl.plane_b.centerline_radius_px is not None
    beam = ctl.view_carm.beam_direction
    moved = Pose(np.eye(3), 6.0 * beam) @ Pose.exp([0, 0, 0, *np.radians([1.0, -1.5, 0.5])]) @ bsynth.pose
    P = bsynth.tree.points_lps_mm
    assert mtre_mm(moved, bsynth.pose, P) > 5.0
    ctl._set_pose(moved, "manual", "dragged")
    res = ctl.refine()
    assert res.success, res.message
    assert mtre_mm(ctl.pose, bsynth.pose, P) < 0.5
    (args, kw), = calls
    assert len(args[1]) == 2 and kw["global_search"] is False and kw["init_pose"] is moved
    from viewer_fixture import _dense_centerline

    np.testing.assert_allclose(args[1][1], bsynth.carm_b.project(_dense_centerline(bsynth.tree, 0.5)[0], bsynth.pose),
                               atol=1e-9)
    assert "refined on both planes" in ctl.status or "from both planes" in ctl.status


def test_biplane_refine_without_plane_b_centerline_says_plane_a_alone(bsynth, tmp_path):
    dst = tmp_path / "out"
    shutil.copytree(bsynth.out_dir, dst)
    with np.load(dst / "registration_inputs.npz") as zf:
        arrays = {k: zf[k] for k in zf.files if not k.startswith("centerline_b")}
    np.savez(dst / "registration_inputs.npz", **arrays)
    ctl, h = open_viewer(dst, size_px=(600, 400), off_screen=True, persist=False)
    try:
        assert not ctl.refines_both_planes and len(ctl.plane_b.centerline_uv_px) == 0
        ctl._set_pose(ctl.pose, "manual", "unchanged")
        texts = []
        orig = ctl._say
        ctl._say = lambda t: (texts.append(t), orig(t))[1]
        ctl.refine()
        assert any("plane A's roadmap alone" in t for t in texts)
    finally:
        h.plotter.close()


def test_single_view_output_keeps_two_viewports(viewer):
    ctl, h = viewer
    assert len(h.plotter.renderers) == 2 and ctl.plane_b is None and ctl.plane_b_scene is None
    assert ctl.info_text_b() == "" and "detector_b" not in h.renderer_3d.actors


# --------------------------------------------------------------------------------------
# controller
# --------------------------------------------------------------------------------------
def _texture(h) -> np.ndarray:
    from vtk.util.numpy_support import vtk_to_numpy

    rows, cols = h.overlay.shape
    return vtk_to_numpy(h.carm.texture_image.GetPointData().GetScalars())[:, 0].reshape(rows, cols)


def test_roadmap_toggle_shows_the_registration_target(viewer, synth):
    ctl, h = viewer
    np.testing.assert_allclose(ctl.case.roadmap_image, synth.roadmap, atol=0.51)
    ctl.set_frame(1)
    assert ctl.toggle_roadmap() is True
    np.testing.assert_array_equal(_texture(h), display_images_uint8(ctl.case.roadmap_image[None])[0])
    assert h.overlay.roadmap_centerline_actor.GetVisibility()
    assert h.overlay.wire2d.n_points == 0 and h.overlay.wire_proj.n_points == 0
    np.testing.assert_allclose(np.asarray(h.overlay.roadmap_centerline.points)[:, :2],
                               synth.centerline_uv_px * [1, -1], atol=1e-9)
    assert "ROADMAP" in ctl.info_text()
    assert ctl.toggle_roadmap() is False
    np.testing.assert_array_equal(_texture(h), display_images_uint8(ctl.case.images)[1])
    assert not h.overlay.roadmap_centerline_actor.GetVisibility()
    assert h.overlay.wire2d.n_points == len(ctl.wire.wire_uv_px)


def test_a_failed_frame_hides_the_tube_and_says_why(case_dir, synth):
    rep = json.loads((case_dir / "report.json").read_text())
    rep["frames"][1].update(success=False, message="wire misses the vessel tree", points_lps_mm=[],
                            uncertainty_mm=[])
    (case_dir / "report.json").write_text(json.dumps(rep))
    ctl, h = open_viewer(case_dir, size_px=SIZE, off_screen=True)
    try:
        assert h.wire.actor.GetVisibility()
        ctl.set_frame(1)
        assert not h.wire.actor.GetVisibility() and h.wire.polyline.n_points == 0
        assert "frame failed: wire misses the vessel tree" in ctl.info_text()
        assert h.overlay.wire2d.n_points == len(synth.wires_lps_mm[1])  # the detected 2D wire is still shown
        ctl.set_frame(2)
        assert h.wire.actor.GetVisibility() and h.wire.polyline.n_points == len(synth.wires_lps_mm[2])
    finally:
        h.plotter.close()


@pytest.mark.parametrize(("verdict", "single_path", "says"), [
    ("uncertain", True, "AUTOMATIC REGISTRATION UNCERTAIN: the overlay fits, the roadmap does not settle the pose "
                        "(one vessel path: depth)"),
    ("failed", False, "AUTOMATIC REGISTRATION FAILED: check the overlay"),
])
def test_a_registration_that_did_not_pass_says_which_check(case_dir, verdict, single_path, says):
    for name in ("report.json", "registration.json"):
        path = case_dir / name
        if path.exists():
            rec = json.loads(path.read_text())
            rec["registration"].update(success=False, verdict=verdict, single_path=single_path)
            path.write_text(json.dumps(rec))
    ctl, h = open_viewer(case_dir, size_px=SIZE, off_screen=True)
    try:
        assert says in ctl.info_text()
        assert ("UNCERTAIN" in ctl.info_text()) == (verdict == "uncertain")
    finally:
        h.plotter.close()


def test_cta_slices_pass_through_the_vessels_in_lps(viewer, synth, tmp_path):
    from viewer_fixture import CTA_TISSUE_HU, CTA_VESSEL_HU

    ctl, h = viewer
    n_before = h.renderer_3d.GetActors().GetNumberOfItems()
    assert ctl.toggle_cta() is True
    slices = ctl.cta_slices
    c = ctl.case.centroid_lps_mm
    b = np.asarray(slices.bounds).reshape(3, 2)
    assert np.all(b[:, 0] < c) and np.all(b[:, 1] > c)
    # tree points lying on a slice plane sample bright lumen there; points 15 mm off the tree do not
    pts = synth.tree.points_lps_mm
    near = np.abs(pts - c) < 0.3  # (N, 3): point i is within 0.3 mm of the slice normal to axis k
    idx, axis = np.nonzero(near)
    assert len(idx) >= 3
    on = pts[idx].copy()
    on[np.arange(len(idx)), axis] = c[axis]  # snap onto the slice plane
    off = on.copy()
    off[np.arange(len(idx)), (axis + 1) % 3] += 15.0  # 15 mm away within the same plane: tissue
    mid = 0.5 * (CTA_VESSEL_HU + CTA_TISSUE_HU)
    p_on = pv.PolyData(on).sample(slices, tolerance=1e-3)
    p_off = pv.PolyData(off).sample(slices, tolerance=1e-3)
    assert np.all(p_on["vtkValidPointMask"] == 1)
    assert np.all(p_on["HU"] > mid)
    assert np.mean(p_off["HU"][p_off["vtkValidPointMask"] == 1] < mid) > 0.8
    assert h.renderer_3d.GetActors().GetNumberOfItems() == n_before + 1
    assert ctl.toggle_cta() is False and not ctl.cta_actor.GetVisibility()
    ctl.case.inputs["cta"] = str(tmp_path / "gone")
    ctl2 = ViewerController(ctl.case, h, persist=False)
    with pytest.raises(InputError, match="not there any more"):
        ctl2.toggle_cta()


def test_case_without_wires_still_steps_through_the_frames(case_dir, synth):
    rep = json.loads((case_dir / "report.json").read_text())
    rep["frames"] = []
    (case_dir / "report.json").write_text(json.dumps(rep))
    ctl, h = open_viewer(case_dir, size_px=SIZE, off_screen=True)
    try:
        assert ctl.n_frames == len(synth.images) and ctl.wire is None
        assert not h.wire.actor.GetVisibility()
        assert ctl.set_frame(2) == 2
        np.testing.assert_array_equal(_texture(h), display_images_uint8(ctl.case.images)[2])
        assert "no reconstructed wires" in ctl.info_text()
        with pytest.raises(InputError, match="no reconstructed wire to export"):
            ctl.export(ExportKind.CURRENT_WIRE)
    finally:
        h.plotter.close()


def test_set_frame_updates_the_tube_in_place(viewer, synth):
    ctl, h = viewer
    actor, tube, line = h.wire.actor, h.wire.tube, h.wire.polyline
    n_actors = h.renderer_3d.GetActors().GetNumberOfItems()
    u8 = display_images_uint8(ctl.case.images)
    from vtk.util.numpy_support import vtk_to_numpy

    for k in (2, 3, 1):
        assert ctl.set_frame(k) == k
        _grab(h.plotter)
        assert h.wire.actor is actor and h.wire.tube is tube and h.wire.polyline is line
        shown = actor.GetMapper().GetInput()  # what the actor draws is the tube of the new points
        assert shown.GetNumberOfPoints() == tube.GetOutput().GetNumberOfPoints()
        np.testing.assert_allclose(shown.GetBounds(), tube.GetOutput().GetBounds())
        np.testing.assert_allclose(np.asarray(line.points), synth.wires_lps_mm[k], atol=TOL_POINT_MM)
        np.testing.assert_allclose(line.point_data["uncertainty_mm"], synth.uncertainty_mm[k])
        assert tube.GetOutput().GetNumberOfPoints() > 10 * len(synth.wires_lps_mm[k])
        tex = vtk_to_numpy(h.carm.texture_image.GetPointData().GetScalars())[:, 0].reshape(synth.carm.shape)
        np.testing.assert_array_equal(tex, u8[k])
        assert h.renderer_3d.GetActors().GetNumberOfItems() == n_actors
    assert ctl.next_frame() == 2 and ctl.previous_frame() == 1
    assert ctl.set_frame(99) == 3 and ctl.next_frame() == 0  # clamps, then wraps


def test_nudge_moves_overlay_and_carm_live_and_saves_the_pose(viewer, case_dir, synth):
    ctl, h = viewer
    carm = synth.carm
    before = np.asarray(h.overlay.centerline.points).copy()
    res0 = ctl.residual_px()
    ctl.set_step(Step.COARSE)
    pose = ctl.nudge(Axis.U, +1)
    after = np.asarray(h.overlay.centerline.points)
    du = after[:, 0] - before[:, 0]
    expected_px = STEP_MM[Step.COARSE] * carm.magnification / carm.pixel_mm
    assert abs(np.median(du) - expected_px) < 0.1 * expected_px
    assert np.abs(after[:, 1] - before[:, 1]).max() < 0.1 * expected_px
    np.testing.assert_allclose(np.asarray(h.carm.detector.points), carm.detector_corners_lps_mm(pose), atol=1e-9)
    assert ctl.residual_px() > res0 + 0.5 * expected_px
    rec = json.loads((case_dir / "registration.json").read_text())
    assert rec["source"] == "manual"
    assert Pose.from_matrix(rec["pose"]).allclose(pose, atol_mm=1e-9, atol_rad=1e-12)
    assert Pose.from_matrix(rec["automatic_pose"]).allclose(synth.pose, atol_mm=1e-9, atol_rad=1e-12)
    np.testing.assert_allclose(rec["projection_matrix"], carm.projection_matrix(pose))
    assert ctl.wires_stale


@pytest.mark.parametrize("axis", list(Axis))
def test_every_axis_moves_the_projection_its_own_way(synth, case_dir, axis):
    ctl = ViewerController(load_outdir(case_dir), persist=False)
    carm, pts = synth.carm, synth.tree.points_lps_mm
    uv0 = carm.project(pts, ctl.pose)
    ctl.set_step(Step.FINE)
    uv1 = carm.project(pts, ctl.nudge(axis, +4))  # 4 fine steps = 2 mm
    shift = np.median(uv1 - uv0, axis=0)
    spread = np.std(uv1, axis=0).sum() / np.std(uv0, axis=0).sum()
    px = 4 * STEP_MM[Step.FINE] * carm.magnification / carm.pixel_mm
    if axis is Axis.U:
        assert abs(shift[0] - px) < 0.1 * px and abs(shift[1]) < 0.1 * px
    elif axis is Axis.V:
        assert abs(shift[1] - px) < 0.1 * px and abs(shift[0]) < 0.1 * px
    else:  # toward the detector: less magnification
        assert spread < 1.0 and np.linalg.norm(shift) < 0.5 * px
    # rotation about the same axis through the centroid keeps the centroid's projection
    prev = ctl.pose
    c_uv0 = carm.project(ctl.case.centroid_lps_mm, prev)
    pose = ctl.rotate(axis, deg=STEP_DEG[Step.COARSE])
    np.testing.assert_allclose(carm.project(ctl.case.centroid_lps_mm, pose), c_uv0, atol=1e-6)
    assert abs((pose @ prev.inverse()).rotation_angle_deg() - STEP_DEG[Step.COARSE]) < 1e-9
    assert ctl.toggle_step() is Step.COARSE


def test_nudge_then_refine_returns_to_the_automatic_pose(viewer, synth):
    ctl, h = viewer
    auto = ctl.case.automatic_pose
    ctl.nudge(Axis.U, +1)
    ctl.nudge(Axis.V, -1)
    ctl.rotate(Axis.BEAM, +1)
    off = mtre_mm(ctl.pose, auto, synth.tree.points_lps_mm)
    assert off > 5.0
    res = ctl.refine()
    assert res.success
    assert mtre_mm(ctl.pose, auto, synth.tree.points_lps_mm) < TOL_REFINE_MTRE_MM
    assert ctl.residual_px() < 1.0
    # refine applied the pose: every frame was reconstructed again, close to the true wire
    assert not ctl.wires_stale
    for w, truth in zip(ctl.case.wires, synth.wires_lps_mm):
        assert w.success
        from scipy.spatial import cKDTree

        d, _ = cKDTree(truth).query(w.points_lps_mm)
        assert np.median(d) < 1.5
    rec = json.loads((ctl.case.out_dir / "registration.json").read_text())
    assert rec["source"] == "manual"


@pytest.mark.parametrize("verdict", ["uncertain", "failed"])
def test_refine_adopts_an_uncertain_pose_and_keeps_the_pose_on_failure(viewer, synth, monkeypatch, verdict):
    """A refinement the overlay fits but the roadmap leaves uncertain (e.g. one vessel path's depth) is
    adopted with a warning; a failed one leaves the pose alone."""
    from guidewire3d.registration import verdict as registration_verdict

    ctl, h = viewer
    auto = ctl.case.automatic_pose
    ctl.nudge(Axis.U, +1)
    ctl.rotate(Axis.BEAM, +1)
    moved = ctl.pose
    # a limit no pose meets: every refinement becomes "uncertain" (pose) or "failed" (2D fit)
    limit = "MAX_POSE_STD_MM" if verdict == "uncertain" else "MAX_MEAN_RESIDUAL_PX"
    monkeypatch.setattr(registration_verdict, limit, 0.0)
    res = ctl.refine()
    assert res.verdict == verdict and not res.success
    if verdict == "uncertain":
        assert mtre_mm(ctl.pose, auto, synth.tree.points_lps_mm) < TOL_REFINE_MTRE_MM
        assert "check it" in ctl.status and not ctl.wires_stale
    else:
        assert ctl.pose.allclose(moved) and "refine failed" in ctl.status


def test_reset_goes_back_to_automatic(viewer, synth, case_dir):
    ctl, h = viewer
    ctl.rotate(Axis.U, +2)
    ctl.nudge(Axis.BEAM, -1)
    assert not ctl.pose.allclose(synth.pose)
    ctl.reset()
    assert ctl.pose.allclose(synth.pose, atol_mm=1e-9, atol_rad=1e-12)
    assert ctl.pose_source == "automatic" and not ctl.wires_stale
    rec = json.loads((case_dir / "registration.json").read_text())
    assert rec["source"] == "automatic"
    np.testing.assert_allclose(np.asarray(h.carm.detector.points), synth.carm.detector_corners_lps_mm(synth.pose),
                               atol=1e-9)


@pytest.mark.parametrize("kind", list(ExportKind))
def test_export_writes_models_that_read_back(viewer, synth, tmp_path, kind):
    from guidewire3d.app import export as ex

    ctl, h = viewer
    ctl.set_frame(2)
    paths = ctl.export(kind, tmp_path / "exp")
    assert str(tmp_path / "exp") in ctl.status
    if kind is ExportKind.VESSELS:
        assert sorted(p.name for p in paths) == ["vessels.stl", "vessels.vtp"]
        src = ex.read_polydata(synth.out_dir / "vessels.vtp")
        src_pts = pv.wrap(src).points
        for p in paths:
            back = ex.read_polydata(p)
            if p.suffix == ".vtp":
                assert back.GetNumberOfPoints() == src.GetNumberOfPoints()
            else:  # STL stores float32 triangles; the reader merges identical vertices
                assert back.GetNumberOfPoints() == len(np.unique(src_pts.astype(np.float32), axis=0))
                assert back.GetNumberOfCells() == pv.wrap(src).triangulate().n_cells
            np.testing.assert_allclose(back.GetBounds(), src.GetBounds(), atol=1e-4)
        return
    frames = [2] if kind is ExportKind.CURRENT_WIRE else [0, 1, 2, 3]
    assert sorted(p.name for p in paths) == sorted(f"guidewire_{k:04d}.{e}" for k in frames for e in ("stl", "vtp"))
    from vtk.util.numpy_support import vtk_to_numpy

    for k in frames:
        line = ex.read_polydata(tmp_path / "exp" / f"guidewire_{k:04d}.vtp")
        assert line.GetNumberOfPoints() == len(synth.wires_lps_mm[k])
        np.testing.assert_allclose(vtk_to_numpy(line.GetPoints().GetData()), synth.wires_lps_mm[k], atol=1e-9)
        np.testing.assert_allclose(vtk_to_numpy(line.GetPointData().GetArray("uncertainty_mm")),
                                   synth.uncertainty_mm[k])
        stl = ex.read_polydata(tmp_path / "exp" / f"guidewire_{k:04d}.stl")
        ref = pv.wrap(ex.tube_polydata(ex.wire_polydata(ctl.case.wires[k]), sc.WIRE_RADIUS_MM)).clean()
        assert stl.GetNumberOfPoints() == ref.n_points
        assert stl.GetNumberOfCells() == ref.n_cells


def test_screenshot_at_a_chosen_size(viewer, tmp_path):
    import cv2

    ctl, h = viewer
    p = ctl.screenshot(tmp_path / "s.png", size_px=(640, 360))
    img = cv2.imread(str(p))
    assert img.shape == (360, 640, 3)
    assert tuple(h.plotter.window_size) == SIZE  # restored
    assert str(p) in ctl.status
    # the left half shows the 3D scene on its dark background, the right half the bright frame
    assert img[:, 320:].mean() > img[:, :320].mean()


def test_cli_screenshot_and_errors(synth, tmp_path, capsys):
    import cv2

    out = tmp_path / "shot.png"
    rc = cli.main(["view", str(synth.out_dir), "--screenshot", str(out), "--frame", "2", "--size", "500x300"])
    assert rc == 0
    img = cv2.imread(str(out))
    assert img.shape == (300, 500, 3) and img.std() > 10
    assert cli.main(["view", str(synth.out_dir), "--screenshot", str(out), "--size", "big"]) == 2
    assert "--size" in capsys.readouterr().err
    assert cli.main(["view", str(synth.out_dir), "--screenshot", str(out), "--frame", "9"]) == 2
    assert "--frame: 9 is out of range" in capsys.readouterr().err
    assert cli.main(["view", str(tmp_path / "nothing")]) == 2
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("DISPLAY", raising=False)
        mp.delenv("WAYLAND_DISPLAY", raising=False)
        assert cli.main(["view", str(synth.out_dir)]) == 2
        assert "no display" in capsys.readouterr().err
    assert cli.main(["view"]) == 2
    assert parse_size("1200x800") == (1200, 800)
    with pytest.raises(InputError, match="--size"):
        parse_size("3x3")


def test_cli_runs_the_pipeline_first_with_inputs(synth, tmp_path, monkeypatch, capsys):
    import cv2

    from guidewire3d.app import pipeline

    calls = []

    def fake_run_to_outdir(cta, roadmap, frames, out_dir, **kw):
        calls.append((cta, roadmap, frames, Path(out_dir)))
        shutil.copytree(synth.out_dir, out_dir)

    monkeypatch.setattr(pipeline, "run_to_outdir", fake_run_to_outdir)
    out_dir, shot = tmp_path / "new_out", tmp_path / "shot.png"
    rc = cli.main(["view", str(out_dir), "--cta", "ct_dir", "--roadmap", "r.dcm", "--frames", "f.dcm",
                   "--screenshot", str(shot), "--size", "400x300"])
    assert rc == 0 and calls == [("ct_dir", "r.dcm", "f.dcm", out_dir)]
    assert cv2.imread(str(shot)).shape == (300, 400, 3)
    assert cli.main(["view", "--cta", "ct_dir", "--screenshot", str(shot)]) == 2
    assert "--roadmap, --frames missing" in capsys.readouterr().err


# --------------------------------------------------------------------------------------
# real window (xvfb-run + xdotool)
# --------------------------------------------------------------------------------------
_HAVE_X_TOOLS = all(shutil.which(t) for t in ("xvfb-run", "xdotool"))

#: the driver's own bounds: up to 3 window searches of 30 s (a cold first start of the viewer in a fresh venv under
#: load can take most of one), then about 20 s of keys, screenshot and quit; a clean-clone CI run timed out at 55 s
_DRIVER_TIMEOUT_S = 120
_DRIVER = r"""
set -u
"$PY" -m guidewire3d.app.cli view "$OUT" --size 800x500 > "$LOG" 2>&1 &
APP=$!
# (a search can hit a window that is destroyed while it looks, an X BadWindow error: search again)
WID=""
for i in 1 2 3; do
  WID=$(timeout 30 xdotool search --sync --name "guidewire3d" 2>/dev/null | head -1)
  [ -n "$WID" ] && break
  sleep 1
done
if [ -z "$WID" ]; then echo "no window" >&2; kill $APP; exit 3; fi
sleep 1.5
xdotool windowfocus --sync "$WID" 2>/dev/null || true
xdotool mousemove --window "$WID" 200 250
xdotool key --delay 150 n
sleep 0.5
xdotool key --delay 150 l l
sleep 0.8
xdotool key c
for i in $(seq 1 60); do
  ls "$OUT"/exports/screenshot_frame0001.png >/dev/null 2>&1 && break
  sleep 0.25
done
sleep 0.5
xdotool key q
for i in $(seq 1 20); do kill -0 $APP 2>/dev/null || break; sleep 0.25; done
kill $APP 2>/dev/null || true
wait $APP 2>/dev/null
exit 0
"""


@pytest.mark.xvfb
@pytest.mark.skipif(not _HAVE_X_TOOLS, reason="needs xvfb-run and xdotool (apt: xvfb xauth xdotool)")
def test_real_window_keys_under_xvfb_biplane(bsynth, tmp_path):
    """The biplane window (three views) under keys: 'n' moves both planes to the next pair, 'l' the pose."""
    import cv2

    out = tmp_path / "out"
    shutil.copytree(bsynth.out_dir, out)
    env = dict(os.environ)
    env.pop("VTK_DEFAULT_OPENGL_WINDOW", None)
    env.update(PY=sys.executable, OUT=str(out), LOG=str(tmp_path / "app.log"))
    proc = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 1024x768x24", "bash", "-c", _DRIVER], env=env,
                          capture_output=True, text=True, timeout=_DRIVER_TIMEOUT_S)
    log = (tmp_path / "app.log").read_text() if (tmp_path / "app.log").exists() else ""
    assert proc.returncode == 0, proc.stderr + log
    shot = out / "exports" / "screenshot_frame0001.png"
    assert shot.exists(), log
    img = cv2.imread(str(shot))[..., ::-1].astype(float)  # RGB
    assert img.shape == (500, 800, 3)
    quad_b = img[250:, 400:]  # plane B's 2D view: its live frame with the projected 3D wire in green
    green = np.asarray(sc.WIRE_PROJ_COLOR) * 255
    is_green = np.linalg.norm(quad_b - green, axis=2) < 60
    assert quad_b.std() > 10 and is_green.sum() > 20
    moved = Pose.from_matrix(json.loads((out / "registration.json").read_text())["pose"])
    expected = Pose(np.eye(3), bsynth.carm.axes.T @ np.array([2 * STEP_MM[Step.COARSE], 0, 0])) @ bsynth.pose
    assert moved.allclose(expected, atol_mm=1e-6, atol_rad=1e-9)


@pytest.mark.xvfb
@pytest.mark.skipif(not _HAVE_X_TOOLS, reason="needs xvfb-run and xdotool (apt: xvfb xauth xdotool)")
def test_real_window_keys_under_xvfb(case_dir, synth, tmp_path):
    import cv2

    env = dict(os.environ)
    env.pop("VTK_DEFAULT_OPENGL_WINDOW", None)  # a real X window, not EGL
    env.update(PY=sys.executable, OUT=str(case_dir), LOG=str(tmp_path / "app.log"))
    t0 = time.monotonic()
    proc = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 1024x768x24", "bash", "-c", _DRIVER], env=env,
                          capture_output=True, text=True, timeout=_DRIVER_TIMEOUT_S)
    log = (tmp_path / "app.log").read_text() if (tmp_path / "app.log").exists() else ""
    assert proc.returncode == 0, proc.stderr + log
    assert time.monotonic() - t0 < 55
    shot = case_dir / "exports" / "screenshot_frame0001.png"  # 'n' moved to frame 1 before 'c'
    assert shot.exists(), log
    img = cv2.imread(str(shot))
    assert img.shape == (500, 800, 3) and img.std() > 10
    rec = json.loads((case_dir / "registration.json").read_text())
    assert rec["source"] == "manual"
    moved = Pose.from_matrix(rec["pose"])
    # two coarse 'l' presses: the vessels moved 2 x 5 mm along e_u
    expected = Pose(np.eye(3), synth.carm.axes.T @ np.array([2 * STEP_MM[Step.COARSE], 0, 0])) @ synth.pose
    assert moved.allclose(expected, atol_mm=1e-6, atol_rad=1e-9)
