"""Tests of ``guidewire3d segment`` (guidewire3d.app.batch2d): the simulator's XA DICOM frames against
their true wire, a real angiogram PNG against its manual mask, and bad inputs."""
import json
from pathlib import Path

import numpy as np
import pytest

from guidewire3d.app import cli
from guidewire3d.xray.orderedwire import ordered_wire
from guidewire3d.xray.roadmap import vessel_mask
from guidewire3d.io import read_xa
from guidewire3d.metrics import dice
from guidewire3d.xray.segmentation import guidewire_mask

REAL_DIR = Path("/work/shared/data/coronary-angiograms")
WIRE_DICE_MIN = 0.8         # UNet wire mask vs the simulator's truth (per frame)
TIP_MEDIAN_TOL_PX = 2.0     # issue 5: median distance of the ordered wire's last point to the true tip
REAL_DICE_MIN = 0.6         # vessel mask vs the manual mask on one real angiogram


def _png(path):
    from skimage.io import imread

    return imread(path) > 0


def test_segment_xa_frames_against_the_truth(small_case, small_case_dir, tmp_path, capsys):
    out = tmp_path / "seg"
    assert cli.main(["segment", str(small_case_dir / "frames.dcm"), "--out", str(out), "--what", "wire"]) == 0
    assert "ordered wire found in 4/4" in capsys.readouterr().out
    summary = json.loads((out / "segment.json").read_text())
    assert [r["frame"] for r in summary["images"]] == [0, 1, 2, 3]
    assert not list(out.glob("*_vessels.png"))
    run = read_xa(small_case_dir / "frames.dcm")
    tips = []
    for t, rec in enumerate(summary["images"]):
        mask = _png(out / f"frames_f{t:04d}_wire.png")
        # The same as the API on the DICOM pixels, and close to the simulator's truth.
        frame = run.frames[t]
        assert np.array_equal(mask, guidewire_mask(frame))
        assert dice(mask, small_case.wire_mask[t]) >= WIRE_DICE_MIN
        uv = np.asarray(rec["wire"]["points_uv_px"])
        truth = np.asarray(small_case.wire_uv_px[t])[np.asarray(small_case.wire_visible[t])]
        assert rec["wire"]["success"]
        tips.append(np.linalg.norm(uv[-1] - truth[-1]))
        ow = ordered_wire(mask, image=frame)
        np.testing.assert_allclose(uv, np.asarray(ow), atol=0.01)
        assert (rec["wire"]["beyond_tip"] is None) == (ow.beyond_tip is None)
        assert rec["wire"]["hairpin_px"] == pytest.approx(ow.hairpin_px, abs=0.05)
    assert np.median(tips) <= TIP_MEDIAN_TOL_PX
    # The overlay draws that wire in yellow.
    from scipy.spatial import cKDTree
    from skimage.io import imread

    ov = imread(out / "frames_f0000_overlay.png")
    yellow = (ov[..., 0] > 200) & (ov[..., 1] > 150) & (ov[..., 2] < 100)
    wire_uv = np.asarray(summary["images"][0]["wire"]["points_uv_px"])
    rows, cols = np.nonzero(yellow)
    assert len(rows) >= 0.5 * len(wire_uv)
    assert cKDTree(wire_uv).query(np.column_stack([cols, rows]))[0].max() <= 2.0


def test_segment_wire_model_uses_the_dicom_geometry(small_case, small_case_dir, tmp_path):
    from guidewire3d.xray.wiremask import projected_wire_radius_px

    out = tmp_path / "seg"
    d_mm = small_case.wire_diameter_mm
    assert cli.main(["segment", str(small_case_dir / "frames.dcm"), "--out", str(out), "--what", "wire",
                     "--wire-model", "--wire-diameter-mm", str(d_mm)]) == 0
    run = read_xa(small_case_dir / "frames.dcm")
    radius = projected_wire_radius_px(run.carm, d_mm)
    assert radius == pytest.approx(projected_wire_radius_px(small_case.carm, d_mm), rel=1e-3)
    for t in (0, 2):
        ref = guidewire_mask(run.frames[t], wire_model=True, wire_radius_px=radius)
        assert np.array_equal(_png(out / f"frames_f{t:04d}_wire.png"), ref)


@pytest.mark.skipif(not REAL_DIR.is_dir(), reason="real angiograms not available")
def test_segment_a_real_angiogram_png(tmp_path):
    out = tmp_path / "seg"
    assert cli.main(["segment", str(REAL_DIR / "1.png"), "--out", str(out), "--what", "vessels"]) == 0
    mask = _png(out / "1_vessels.png")
    from skimage.io import imread

    img = imread(REAL_DIR / "1.png")
    assert np.array_equal(mask, vessel_mask(img))
    assert dice(mask, imread(REAL_DIR / "1_gt.png") > 0) >= REAL_DICE_MIN
    rec = json.loads((out / "segment.json").read_text())["images"][0]
    assert rec["frame"] is None and rec["vessel_fraction"] == pytest.approx(mask.mean(), abs=1e-6)
    # The overlay marks the mask's skeleton in green (the name's text may cover a few pixels).
    from skimage.morphology import skeletonize

    ov = imread(out / "1_overlay.png")
    green = (ov[..., 0] == 0) & (ov[..., 1] == 200) & (ov[..., 2] == 0)
    skeleton = skeletonize(mask)
    assert not (green & ~skeleton).any() and green.sum() >= 0.95 * skeleton.sum()


def test_bad_inputs_exit_2_and_write_nothing(small_case_dir, tmp_path, capsys):
    out = tmp_path / "seg"
    text = tmp_path / "notes.txt"
    text.write_text("not an image")
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    ct_slice = next((small_case_dir / "ct").iterdir())
    from skimage.io import imsave

    imsave(tmp_path / "ok.png", np.full((32, 32), 100, np.uint8), check_contrast=False)
    for args, message in (([str(tmp_path / "missing.dcm")], "no such file"),
                          ([str(text)], "not a DICOM file or a PNG/TIFF/JPEG image"),
                          ([str(broken)], "unreadable image"),
                          ([str(ct_slice)], "Modality"),
                          ([str(small_case_dir / "frames.dcm"), str(small_case_dir / "frames.dcm")], "same output name"),
                          ([str(tmp_path / "empty")], "no DICOM or PNG"),
                          ([str(small_case_dir / "frames.dcm"), "--wire-diameter-mm", "0.36"], "only used with --wire-model"),
                          ([str(broken.with_name("ok.png")), "--wire-model", "--wire-diameter-mm", "0.36"],
                           "needs the C-arm geometry")):
        (tmp_path / "empty").mkdir(exist_ok=True)
        assert cli.main(["segment", *args, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1
        assert not out.exists() and not list(tmp_path.glob(".seg.*"))
    (out / "x").mkdir(parents=True)
    assert cli.main(["segment", str(small_case_dir / "frames.dcm"), "--out", str(out)]) == 2
    assert "not empty" in capsys.readouterr().err
