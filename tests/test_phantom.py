"""The simulator checked against its own ground truth (issue 3)."""
import json
import os

import numpy as np
import pydicom
import pytest
from scipy import ndimage

from guidewire3d import io
from guidewire3d import phantom
from guidewire3d.app.cli import build_parser, main
from guidewire3d.errors import InputError
from guidewire3d.geometry import CArm, Pose, nominal_pose
from guidewire3d.phantom import (
    WIRE_MARGIN_MM,
    PhantomOptions,
    VolumeSize,
    load_truth,
    lumen_depth_mm,
    render_tube_line_integral,
    simulate,
    write_case,
)
from guidewire3d.phantom.anatomy import _make_tree, _sample_grid
from guidewire3d.phantom.case import _rngs
from guidewire3d.vesseltree import VesselTree

TOL_UV_PX = 0.5  # truth wire vs rendered wire
TOL_DEPTH_MM = 1e-6
TOL_JSON_MM = 1e-4  # truth.json rounds to 5 decimals


def _depth_margin(case):
    return case.wire_diameter_mm / 2 + WIRE_MARGIN_MM


# --------------------------------------------------------------------------------------
# tree, CT and lumen
# --------------------------------------------------------------------------------------
def test_tree_structure_radii_and_angles(small_case):
    tree = small_case.tree
    assert tree.root == 0
    assert 2.5 <= tree.radius_mm.max() <= 3.2
    assert tree.radius_mm.min() >= 0.8 - 1e-9
    # a trunk plus at least 2 levels of branches: some root-to-leaf path passes >= 2 bifurcations
    bif = set(tree.bifurcations.tolist())
    n_bif = [sum(int(i) in bif for i in tree.path_to_root(int(leaf))) for leaf in tree.leaves]
    assert len(tree.leaves) >= 4 and max(n_bif) >= 2
    # radii taper along every branch
    for b in tree.branches:
        r = tree.radius_mm[b.point_ids[1:]]
        assert np.all(np.diff(r) <= 1e-9)
    # bifurcation angles: at each bifurcation one child continues the parent, the other leaves it
    # at 30-75 degrees (measured over the first 3 mm; tortuosity adds a little)
    P = tree.points_lps_mm
    for node in tree.bifurcations:
        up = tree.path_to_root(int(node))[-5:]
        t_in = P[up[-1]] - P[up[0]]
        angles = []
        for ch in tree.children[node]:
            k = ch
            for _ in range(5):
                k = tree.children[k][0] if tree.children[k] else k
            t = P[k] - P[node]
            angles.append(np.degrees(np.arccos(t_in @ t / np.linalg.norm(t_in) / np.linalg.norm(t))))
        angles.sort()
        assert len(angles) == 2 and angles[0] < 20 and 22 <= angles[1] <= 83, angles


def test_tree_inside_ct_and_lumen_mask_matches_tubes(small_case):
    vol, tree = small_case.volume, small_case.tree
    lo, hi = vol.bounds_lps_mm
    assert np.all(tree.points_lps_mm >= lo) and np.all(tree.points_lps_mm <= hi)
    assert np.any(np.abs(vol.origin_lps_mm) > 1.0)  # non-zero origin
    sx, sy, sz = vol.spacing_mm
    assert 0.5 <= sx == sy <= 0.8 and 0.6 <= sz <= 1.25
    assert vol.shape_zyx[1:] == (160, 160) and 100 <= vol.shape_zyx[0] <= 140
    # the CT lumen mask is the union of tubes of the truth tree
    rng = np.random.default_rng(0)
    mask = small_case.lumen_mask_zyx
    inside = np.argwhere(mask)
    near = np.argwhere(ndimage.binary_dilation(mask, iterations=3) & ~mask)
    idx = np.vstack([inside[rng.choice(len(inside), 1500)], near[rng.choice(len(near), 1500)]])
    d = lumen_depth_mm(tree, vol.index_zyx_to_lps(idx))
    clear = np.abs(d) > 0.02
    assert np.array_equal(mask[tuple(idx.T)][clear], d[clear] >= 0)


def test_ct_intensities(small_case):
    hu, mask = small_case.volume.array_zyx, small_case.lumen_mask_zyx
    deep = ndimage.binary_erosion(mask, iterations=2)
    far = ~ndimage.binary_dilation(mask, iterations=4)
    assert 220 <= np.median(hu[deep]) <= 520
    assert 25 <= np.median(hu[far]) <= 55
    assert 5 <= np.std(hu[far]) <= 40  # noise present


def test_lumen_depth_of_a_straight_tube():
    tree = VesselTree(np.array([[0, 0, 0], [0, 0, 10.0], [0, 0, 20.0]]), np.array([2.0, 2.0, 2.0]), np.array([-1, 0, 1]))
    pts = np.array([[0, 0, 5.0], [1.5, 0, 12.0], [0, 3.0, 8.0], [0, 0, 21.0]])
    assert np.allclose(lumen_depth_mm(tree, pts), [2.0, 0.5, -1.0, 1.0], atol=TOL_DEPTH_MM)


def test_distractors_away_from_lumen(distractor_case, small_case):
    case = distractor_case
    dm = case.distractor_mask_zyx
    assert dm.sum() > 1000
    assert not np.any(dm & case.lumen_mask_zyx)
    rng = np.random.default_rng(1)
    idx = np.argwhere(dm)
    idx = idx[rng.choice(len(idx), 2000)]
    d = lumen_depth_mm(case.tree, case.volume.index_zyx_to_lps(idx))
    assert d.max() <= -3.0 + 0.05
    hu = case.volume.array_zyx[dm]
    assert np.median(hu) >= 240  # bone (700-1200) or contrast blobs (250-450), before noise
    assert hu.max() >= 700 or np.median(hu) <= 480
    assert not small_case.distractor_mask_zyx.any()


# --------------------------------------------------------------------------------------
# guidewire
# --------------------------------------------------------------------------------------
def test_wire_inside_lumen_everywhere(small_case, distractor_case):
    for case in (small_case, distractor_case):
        margin = _depth_margin(case)
        for w in case.wire_lps_mm:
            assert lumen_depth_mm(case.tree, w).min() >= margin - TOL_DEPTH_MM
        # and the CT shows contrast along the wire
        idx = case.volume.lps_to_index_zyx(case.wire_lps_mm[-1])
        hu = ndimage.map_coordinates(case.volume.array_zyx, idx.T, order=1)
        assert np.median(hu) > 200


def test_wire_order_steps_and_advance(small_case):
    case = small_case
    tree = case.tree
    wires = case.wire_lps_mm
    for w in wires:
        steps = np.linalg.norm(np.diff(w, axis=0), axis=1)
        assert 0.15 <= steps.min() and steps.max() <= 0.5
    # proximal end at the trunk's start, frames are prefixes of the longest, the tip advances
    assert np.linalg.norm(wires[0][0] - tree.points_lps_mm[tree.root]) <= tree.radius_mm[tree.root]
    for a, b in zip(wires[:-1], wires[1:]):
        assert len(b) > len(a) and np.array_equal(a, b[: len(a)])
    path = case.wire_path_point_ids
    assert path[0] == tree.root and len(tree.children[path[-1]]) == 0
    assert np.array_equal(tree.path_to_root(int(path[-1])), path)
    # the tip is near the path's leaf in the last frame
    s_tip = tree.arclength_from_root_mm[path]
    _, j = tree.kdtree.query(wires[-1][-1])
    assert tree.arclength_from_root_mm[j] >= 0.7 * s_tip[-1]


def test_wire_is_off_centre_and_on_outer_side_of_bends(small_case, distractor_case):
    from scipy.spatial import cKDTree

    for case in (small_case, distractor_case):
        tree = case.tree
        path = case.wire_path_point_ids
        c = tree.points_lps_mm[path]
        w = case.wire_lps_mm[-1]
        d, j = cKDTree(c).query(w)
        assert np.mean(d) > 0.15  # not on the centreline
        # curvature of the smoothed centreline (normal toward the centre of curvature)
        cs = ndimage.gaussian_filter1d(c, 6, axis=0, mode="nearest")
        T = np.gradient(cs, axis=0)
        T /= np.linalg.norm(T, axis=1, keepdims=True)
        k = np.gradient(T, axis=0) / 0.5
        kappa = np.linalg.norm(k, axis=1)
        # away from bifurcations (where the wire cuts the corner), bends are ridden on the outer side
        s = tree.arclength_from_root_mm[path]
        s_bif = np.array([s[i] for i in range(1, len(path) - 1) if len(tree.children[path[i]]) >= 2])
        far = np.min(np.abs(s[j][:, None] - s_bif[None, :]), axis=1) > 7.0
        bend = far & (kappa[j] > 1 / 30.0)
        assert bend.sum() > 20
        room = tree.radius_mm[path][j] - _depth_margin(case)
        inward = np.sum((w - c[j]) * k[j] / kappa[j, None], axis=1) / room
        assert np.mean(inward[bend]) < -0.15


# --------------------------------------------------------------------------------------
# X-ray views and images
# --------------------------------------------------------------------------------------
def test_pose_and_views_in_range(small_case):
    case = small_case
    d = case.pose @ nominal_pose(case.tree.centroid_lps_mm).inverse()
    assert 0 < np.linalg.norm(d.t) <= 20 and 0 < d.rotation_angle_deg() <= 5
    for c in (case.carm, case.heldout_carm):
        assert abs(c.primary_deg) <= 40 and abs(c.secondary_deg) <= 25
        assert 950 <= c.sid_mm <= 1200 and 650 <= c.sod_mm <= 800
        assert 0.15 <= c.pixel_mm <= 0.4 and c.shape == (512, 512)
    cosang = case.carm.beam_direction @ case.heldout_carm.beam_direction
    assert np.degrees(np.arccos(cosang)) >= 30
    # the tree fills a good part of the image
    uv = case.carm.project(case.tree.points_lps_mm, case.pose)
    assert np.ptp(uv[case.carm.in_image(uv)], axis=0).max() >= 0.5 * 512


def test_truth_uv_is_projection_of_truth_wire(small_case):
    case = small_case
    for t, w in enumerate(case.wire_lps_mm):
        assert np.allclose(case.wire_uv_px[t], case.carm.project(w, case.pose), atol=1e-9)
        assert np.allclose(case.heldout_wire_uv_px[t], case.heldout_carm.project(w, case.pose), atol=1e-9)
        assert np.array_equal(case.wire_visible[t], case.carm.in_image(case.wire_uv_px[t]))
        assert case.wire_visible[t].mean() > 0.3


def test_truth_wire_on_rendered_wire_mask(small_case):
    case = small_case
    H, W = case.carm.shape
    for t in range(len(case.frames)):
        uv = case.wire_uv_px[t][case.wire_visible[t]]
        ij = np.clip(np.rint(uv).astype(int), 0, [W - 1, H - 1])
        assert case.wire_mask[t][ij[:, 1], ij[:, 0]].all()
        # and the mask is no wider than the projected wire plus the pixel footprint
        dist = ndimage.distance_transform_edt(~_polyline_mask(uv, (H, W)))
        width_px = case.wire_diameter_mm * case.carm.magnification / case.carm.pixel_mm
        assert dist[case.wire_mask[t]].max() <= width_px / 2 * 1.4 + 1.5


def _polyline_mask(uv, shape):
    m = np.zeros(shape, bool)
    for a, b in zip(uv[:-1], uv[1:]):
        n = int(np.ceil(np.linalg.norm(b - a) / 0.2)) + 1
        p = np.rint(a + (b - a) * np.linspace(0, 1, n)[:, None]).astype(int)
        ok = (p[:, 0] >= 0) & (p[:, 0] < shape[1]) & (p[:, 1] >= 0) & (p[:, 1] < shape[0])
        m[p[ok, 1], p[ok, 0]] = True
    return m


@pytest.fixture(scope="module")
def clean_case():
    """High dose, no background, no catheter: the wire's intensity profile is measurable."""
    return simulate(PhantomOptions(seed=11, n_frames=2, background=False, catheter=False, dose=40.0), make_ct=False)


def test_rendered_wire_profile_centred_on_truth(clean_case):
    case = clean_case
    frame = case.frames[-1].astype(float)
    bg = ndimage.grey_closing(frame, size=(17, 17))
    dark = np.clip(1.0 - frame / bg, 0, None)
    uv = case.wire_uv_px[-1]
    vis = case.carm.in_image(uv, margin_px=8)
    tang = np.gradient(ndimage.gaussian_filter1d(uv, 4, axis=0), axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    nrm = np.column_stack([-tang[:, 1], tang[:, 0]])
    offs = np.linspace(-6, 6, 49)
    errors = []
    for i in np.flatnonzero(vis)[10:-10:5]:
        # skip points where another part of the wire passes close by (crossings, loops)
        other = np.abs(np.arange(len(uv)) - i) > 60
        if np.min(np.linalg.norm(uv[other] - uv[i], axis=1)) < 12:
            continue
        pts = uv[i] + offs[:, None] * nrm[i]
        prof = ndimage.map_coordinates(dark, [pts[:, 1], pts[:, 0]], order=1)
        prof = np.clip(prof - 0.25 * prof.max(), 0, None)
        errors.append(abs(np.sum(offs * prof) / np.sum(prof)))
    errors = np.array(errors)
    assert len(errors) > 40
    assert np.median(errors) <= 0.2 and np.quantile(errors, 0.95) <= TOL_UV_PX


def test_intensity_convention(small_case):
    case = small_case
    for img in (case.roadmap, *case.frames, *case.heldout_frames):
        assert img.min() >= 0 and img.max() <= 65535 and img.dtype == np.float32
    assert 2000 <= np.median(case.frames) <= 14000
    # vessels and wire darker than the background
    assert case.roadmap[case.vessel_mask_2d].mean() < 0.9 * case.roadmap[~case.vessel_mask_2d].mean()
    f = case.frames[0]
    assert f[case.wire_mask[0]].mean() < 0.95 * f[~case.wire_mask[0]].mean()
    # the roadmap is a line integral: thicker vessels are darker
    uv = case.carm.project(case.tree.points_lps_mm, case.pose)
    ok = case.carm.in_image(uv, margin_px=2)
    ij = np.rint(uv[ok]).astype(int)
    val = ndimage.gaussian_filter(case.roadmap, 1.0)[ij[:, 1], ij[:, 0]]
    r = case.tree.radius_mm[ok]
    assert val[r > 2.2].mean() < val[r < 1.1].mean()


def test_line_integral_of_a_cylinder_is_its_volume():
    carm = CArm(20.0, -10.0, 1100.0, 750.0, 0.2, (256, 256))
    pose = Pose.identity()
    # a cylinder through the isocentre, perpendicular to the beam, with a bend (mitred joint)
    e_u = carm.axes[0]
    e_v = carm.axes[1]
    pts = np.array([-8 * e_u, 0 * e_u, 6 * e_v])
    r = 1.5
    L = render_tube_line_integral(carm, pose, [(pts, np.full(3, r))], supersample=3)
    px_at_iso = carm.pixel_at_iso_mm
    vol = L.sum() * px_at_iso**2
    assert vol == pytest.approx(np.pi * r**2 * 14.0, rel=0.03)
    # the central ray through the straight part crosses the full diameter
    uv = carm.project(-4 * e_u, pose)
    assert L[int(round(uv[1])), int(round(uv[0]))] == pytest.approx(2 * r, rel=0.02)


def test_make_ct_false_gives_the_same_2d_data(small_case):
    fast = simulate(PhantomOptions(seed=3, n_frames=4), make_ct=False)
    assert fast.volume is None and fast.lumen_mask_zyx is None
    assert np.array_equal(fast.tree.points_lps_mm, small_case.tree.points_lps_mm)
    assert fast.pose.allclose(small_case.pose)
    assert np.array_equal(fast.frames, small_case.frames)
    assert np.array_equal(fast.roadmap, small_case.roadmap)
    assert all(np.array_equal(a, b) for a, b in zip(fast.wire_lps_mm, small_case.wire_lps_mm))


def test_detector_1024_and_motion():
    case = simulate(PhantomOptions(seed=4, n_frames=3, detector_px=1024, motion_mm=2.0, catheter=False,
                                   wire_diameter_mm=0.36), make_ct=False)
    assert case.frames.shape == (3, 1024, 1024) and case.carm.shape == (1024, 1024)
    assert case.wire_diameter_mm == 0.36
    m = case.motion_lps_mm
    assert np.linalg.norm(m, axis=1).max() <= 2.0 + 1e-9 and np.ptp(m[:, 2]) > 0
    for t in range(3):
        expect = case.carm.project(case.wire_lps_mm[t], case.pose @ Pose(np.eye(3), m[t]))
        assert np.allclose(case.wire_uv_px[t], expect, atol=1e-9)
        assert case.frame_pose(t).allclose(case.pose @ Pose(np.eye(3), m[t]))


def test_wire_diameter_from_seed_takes_both_values():
    seen = set()
    for seed in range(12):
        rng = _rngs(seed)["wire"]
        seen.add(float(rng.choice(phantom.WIRE_DIAMETERS_MM)))
    assert seen == {0.36, 0.89}


@pytest.mark.parametrize("size", list(VolumeSize))
def test_volume_sizes(size):
    rngs = _rngs(9)
    grid, lo, hi = _sample_grid(rngs["grid"], size)
    if size is VolumeSize.LARGE:
        assert grid.shape_zyx == (300, 512, 512)
    else:
        assert grid.shape_zyx[1:] == (160, 160) and 100 <= grid.shape_zyx[0] <= 140
    assert np.all(lo >= grid.lo) and np.all(hi <= grid.hi)
    tree, _ = _make_tree(rngs["tree"], lo, hi, grid)
    assert np.all(tree.points_lps_mm >= grid.lo) and np.all(tree.points_lps_mm <= grid.hi)


# --------------------------------------------------------------------------------------
# files
# --------------------------------------------------------------------------------------
def test_dicom_round_trip(small_case, small_case_dir):
    case, d = small_case, small_case_dir
    vol = io.read_volume(d / "ct")
    assert np.array_equal(vol.array_zyx, np.rint(case.volume.array_zyx))
    assert np.allclose(vol.origin_lps_mm, case.volume.origin_lps_mm, atol=1e-4)
    assert np.allclose(vol.spacing_mm, case.volume.spacing_mm, atol=1e-5)
    ds = pydicom.dcmread(sorted((d / "ct").glob("*.dcm"))[0])
    assert ds.Modality == "CT" and ds.RescaleType == "HU"
    truth = load_truth(d)
    for name, frames, carm, P in (("frames.dcm", case.frames, case.carm, truth.projection_matrix),
                                  ("heldout.dcm", case.heldout_frames, case.heldout_carm, truth.heldout_projection_matrix),
                                  ("roadmap.dcm", case.roadmap[None], case.carm, truth.projection_matrix)):
        run = io.read_xa(d / name)
        assert np.array_equal(run.frames, np.clip(np.rint(frames), 0, 65535))
        assert run.carm.to_dict() == carm.to_dict()
        # the tags' geometry with the true pose reproduces the truth's projection matrices
        assert np.allclose(run.carm.projection_matrix(truth.pose), P, rtol=1e-12, atol=1e-9)
        ds = pydicom.dcmread(d / name)
        assert ds.Modality == "XA" and ds.PhotometricInterpretation == "MONOCHROME2"
        assert int(ds.NumberOfFrames) == len(frames)


def test_truth_round_trip(small_case, small_case_dir):
    case = small_case
    truth = load_truth(small_case_dir)
    assert truth.seed == 3 and truth.options == case.options.to_dict()
    assert truth.pose.allclose(case.pose, atol_mm=1e-9)
    assert np.allclose(truth.projection_matrix, case.carm.projection_matrix(case.pose))
    assert np.allclose(truth.tree.points_lps_mm, case.tree.points_lps_mm, atol=TOL_JSON_MM)
    assert np.array_equal(truth.tree.parent, case.tree.parent)
    assert truth.wire_diameter_mm == case.wire_diameter_mm
    for t in range(len(case.frames)):
        assert np.allclose(truth.wire_lps_mm[t], case.wire_lps_mm[t], atol=TOL_JSON_MM)
        assert np.allclose(truth.wire_uv_px[t], case.wire_uv_px[t], atol=1e-3)
        assert np.array_equal(truth.wire_visible[t], case.wire_visible[t])
    assert np.array_equal(truth.wire_mask, case.wire_mask)
    assert np.array_equal(truth.vessel_mask_2d, case.vessel_mask_2d)
    with np.load(small_case_dir / "truth_masks.npz") as z:
        assert np.array_equal(z["lumen_mask_zyx"], case.lumen_mask_zyx)
    raw = json.loads((small_case_dir / "truth.json").read_text())
    for key in ("seed", "options", "carm", "pose", "projection_matrix", "heldout", "tree", "wire_diameter_mm",
                "frames", "wire_path_point_ids"):
        assert key in raw
    assert set(raw["frames"][0]) >= {"index", "points_lps_mm", "uv_px", "visible", "heldout_uv_px"}


def test_load_truth_errors(tmp_path):
    with pytest.raises(InputError, match="truth.json"):
        load_truth(tmp_path)
    (tmp_path / "truth.json").write_text("{not json")
    with pytest.raises(InputError, match="truth.json: corrupt"):
        load_truth(tmp_path)
    (tmp_path / "truth.json").write_text(json.dumps({"seed": 1}))
    with pytest.raises(InputError, match="missing field"):
        load_truth(tmp_path)


def test_write_case_refuses_non_empty_folder(small_case, tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="not empty"):
        write_case(small_case, tmp_path / "x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x"]  # no temporary leftovers


@pytest.mark.parametrize("kwargs, match", [
    ({"seed": -1}, "seed"),
    ({"n_frames": 0}, "n_frames"),
    ({"wire_diameter_mm": 3.0}, "wire_diameter_mm"),
    ({"detector_px": 640}, "detector_px"),
    ({"volume": "huge"}, "volume"),
    ({"motion_mm": -1.0}, "motion_mm"),
    ({"dose": 0.0}, "dose"),
])
def test_bad_options(kwargs, match):
    with pytest.raises(InputError, match=match):
        PhantomOptions(**kwargs)


def test_default_case_cached(tmp_path, monkeypatch):
    cfg = tmp_path / "default.json"
    cfg.write_text(json.dumps({"options": {"seed": 8, "n_frames": 1, "catheter": False}}))
    monkeypatch.setattr(phantom.files, "_DEFAULT_JSON", cfg)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    d = phantom.default_case_dir(progress=False)
    assert d.parent == tmp_path / "cache" / "guidewire3d"
    assert f"v{phantom.CACHE_VERSION}" in d.name
    assert load_truth(d).seed == 8
    mtime = os.stat(d / "truth.json").st_mtime_ns
    assert phantom.default_case_dir(progress=False) == d
    assert os.stat(d / "truth.json").st_mtime_ns == mtime  # reused, not regenerated


def test_shipped_default_options_are_valid():
    opts = phantom.default_options()
    assert opts.volume == "small" and opts.detector_px == 512 and 8 <= opts.n_frames <= 10


# --------------------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------------------
def test_cli_help_documents_every_option():
    sub = build_parser()._subparsers._group_actions[0].choices["phantom"]
    text = sub.format_help()
    for opt in ("--out", "--seed", "--frames", "--wire-diameter", "--distractors", "--detector", "--volume",
                "--no-background", "--no-catheter", "--motion", "--dose", "--breathing", "--breathing-period",
                "--cardiac", "--heart-rate", "--fps"):
        assert opt in text
    for action in sub._actions:
        assert action.help, action.option_strings


def test_cli_writes_breathing_and_cardiac_motion_with_per_frame_truth(tmp_path, capsys):
    """``phantom --breathing --cardiac`` (issue 18): the options reach the case, each frame has its own
    true pose (breathing moves it mostly cranio-caudally), and a value out of range names its option."""
    out = tmp_path / "case"
    assert main(["phantom", "--out", str(out), "--seed", "5", "--frames", "4", "--no-ct", "--breathing", "15",
                 "--breathing-period", "3", "--cardiac", "2", "--heart-rate", "90", "--fps", "10"]) == 0
    truth = load_truth(out)
    o = truth.options
    assert (o["breathing_mm"], o["breathing_period_s"], o["cardiac_mm"], o["heart_rate_bpm"], o["frame_rate_fps"]) \
        == (15.0, 3.0, 2.0, 90.0, 10.0)
    shifts = np.asarray(truth.motion_lps_mm)
    assert shifts.shape == (4, 3) and np.ptp(shifts[:, 2]) > 1.0          # S (cranio-caudal) moves
    assert np.abs(shifts[:, 2]).max() <= 15.0
    capsys.readouterr()
    bad = tmp_path / "bad"
    assert main(["phantom", "--out", str(bad), "--breathing", "40", "--no-ct"]) == 2
    err = capsys.readouterr().err
    assert "--breathing" in err and "PhantomOptions" not in err and len(err.strip().splitlines()) == 1
    assert not bad.exists()


def test_cli_writes_a_case_and_refuses_non_empty_out(tmp_path, capsys):
    out = tmp_path / "case"
    assert main(["phantom", "--out", str(out), "--seed", "6", "--frames", "1", "--no-ct", "--no-catheter"]) == 0
    assert "phantom seed 6" in capsys.readouterr().out
    truth = load_truth(out)
    assert truth.seed == 6 and truth.n_frames == 1 and not (out / "ct").exists()
    assert main(["phantom", "--out", str(out), "--seed", "6"]) == 2
    assert "not empty" in capsys.readouterr().err
