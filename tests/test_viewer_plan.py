"""The vessel plan in the viewer (``guidewire3d view DIR`` on a folder written by ``guidewire3d vessels``).

Before stop 44 the viewer refused such a folder ("no report.json") and ``vessels`` wrote no picture. The plan is seen
from the front, so the patient's left (+L) is on the screen's right: two tubes 20 mm apart along L, each its own tree,
must show the first tree's colour on the left half and the second's on the right.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from guidewire3d import io
from guidewire3d.app import cli
from guidewire3d.viewer import plan_scene

from test_vessels3d_seeds_apart import _two_tubes

pytest.importorskip("pyvista")
SIZE = "400x300"


@pytest.fixture(scope="module")
def plan_dir(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("plan")
    f = io.write_volume(_two_tubes(), tmp / "tubes.nii.gz")
    out = tmp / "plan"
    assert cli.main(["vessels", "--cta", str(f), "--out", str(out), "--seed-lps=10,20,15", "--seed-lps=30,20,15"]) == 0
    return out


def _read_png(path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, path
    return img[..., ::-1].astype(float)  # RGB


def _colour_centre_x(img: np.ndarray, rgb) -> float:
    """Mean column of the pixels nearest in hue to ``rgb`` (the tubes are the only lit pixels besides text)."""
    lit = img.sum(axis=2) > 60
    c = np.asarray(rgb, float) / np.linalg.norm(rgb)
    unit = img / np.maximum(np.linalg.norm(img, axis=2, keepdims=True), 1e-9)
    near = lit & (np.einsum("hwc,c->hw", unit, c) > 0.97)
    near[: img.shape[0] // 8] = False  # the caption
    near[-img.shape[0] // 5:] = False  # the keys and the scalar bar
    assert near.sum() > 50, "colour not found"
    return float(np.argwhere(near)[:, 1].mean())


def test_vessels_writes_a_screenshot_of_the_plan(plan_dir):
    img = _read_png(plan_dir / "screenshot.png")
    assert img.shape[:2] == (800, 1200)
    assert (img.sum(axis=2) > 60).mean() > 0.01  # something drawn


def test_view_shows_the_plan_from_the_front_each_tree_its_colour(plan_dir, tmp_path):
    png = tmp_path / "view.png"
    assert cli.main(["view", str(plan_dir), "--screenshot", str(png), "--size", SIZE]) == 0
    img = _read_png(png)
    assert img.shape[:2] == (300, 400)
    x_first = _colour_centre_x(img, plan_scene.TREE_COLORS[0])  # tree 1: the tube at L = 10 mm
    x_second = _colour_centre_x(img, plan_scene.TREE_COLORS[1])  # tree 2: L = 30 mm, the patient's left of it
    assert x_first < 0.5 * img.shape[1] < x_second


def test_caption_names_each_tree_and_its_levels(plan_dir):
    text = plan_scene.plan_caption(json.loads((plan_dir / "vessels.json").read_text()))
    lines = text.splitlines()
    assert lines[0] == "2 separate vessel trees"
    assert lines[1].startswith("tree 1 (seeds 1): 1 branch, ") and "(HU)" in lines[1]
    assert lines[2].startswith("tree 2 (seeds 2): 1 branch, ")


def test_a_plan_folder_missing_a_file_is_refused_naming_it(plan_dir, tmp_path, capsys):
    broken = tmp_path / "broken"
    broken.mkdir()
    for n in ("vessels.json", "centerline.vtp"):
        (broken / n).write_bytes((plan_dir / n).read_bytes())
    (broken / "vessels.vtp").write_text("not a vtp")
    assert plan_scene.is_plan_folder(broken)
    rc = cli.main(["view", str(broken), "--screenshot", str(tmp_path / "x.png"), "--size", SIZE])
    err = capsys.readouterr().err
    assert rc == 2 and "vessels.vtp" in err and not (tmp_path / "x.png").exists()


def test_access_point_on_a_finished_plan_is_refused(plan_dir, tmp_path, capsys):
    rc = cli.main(["view", str(plan_dir), "--access-lps=10,20,0", "--screenshot", str(tmp_path / "x.png")])
    assert rc == 2 and "give --access-lps to `guidewire3d vessels`" in capsys.readouterr().err
