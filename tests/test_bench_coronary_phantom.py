"""The coronary CTA phantom of ``scripts/bench_coronary_cta.py``: its grid, its levels, and its coronaries (the truth)
in bright lumen surrounded by epicardial fat."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage as ndi

SPACING_MM, SLICE_MM = 0.6, 0.6  # coarser than the benchmark's 0.4 x 0.6 mm: a few seconds
LEVEL_TOL_HU = 15.0  # a class's median against its level (no noise; blur and partial volume at the edges)
MIN_LUMEN_HU = 120.0  # the coronaries' centerline (no noise): 320-400 HU blurred to ~140 at 0.6 mm radius
MIN_PROXIMAL_HU = 300.0  # where the radius is at least PROXIMAL_RADIUS_MM
PROXIMAL_RADIUS_MM = 1.2
TIP_POINTS = 8  # the last 1.6 mm of each artery: its end's half ball, blurred
MIN_IN_FAT = 0.85  # of the truth's wall points 1 mm outside it (ostia and branch points aside)

_spec = importlib.util.spec_from_file_location(
    "bench_coronary_cta", Path(__file__).resolve().parents[1] / "scripts" / "bench_coronary_cta.py")
B = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(B)


@pytest.fixture(scope="module")
def phantom():
    return B.coronary_phantom(spacing_mm=SPACING_MM, slice_mm=SLICE_MM, noise_hu=0.0, seed=0)


def test_grid(phantom):
    vol, _, label = phantom
    want = tuple(int(round(e / s)) for e, s in zip(B.FOV_MM[::-1], (SLICE_MM, SPACING_MM, SPACING_MM)))
    assert vol.shape_zyx == want == label.shape
    assert vol.spacing_mm == (SPACING_MM, SPACING_MM, SLICE_MM)
    centre = vol.bounds_lps_mm.mean(axis=0)
    assert np.allclose(centre, B.FOV_CENTRE_LPS_MM, atol=1e-6)


@pytest.mark.parametrize("cls, level", [("lung", B.LEVELS["lung"]), ("fat", B.LEVELS["fat"]),
                                        ("myocardium", B.LEVELS["myocardium"]), ("lv", B.LUMEN_HU),
                                        ("la", B.LUMEN_HU), ("aorta", B.LUMEN_HU), ("rv", B.RIGHT_HU),
                                        ("ra", B.RIGHT_HU), ("pa", B.PA_HU), ("pv", B.LUMEN_HU)])
def test_levels(phantom, cls, level):
    vol, _, label = phantom
    assert np.median(vol.array_zyx[label == B.LABELS[cls]]) == pytest.approx(level, abs=LEVEL_TOL_HU)


def test_bone_is_bright(phantom):
    vol, _, label = phantom
    bone = vol.array_zyx[label == B.LABELS["bone"]]
    assert np.percentile(bone, 90) > 800.0 and np.median(bone) > 150.0


def test_truth_in_bright_lumen(phantom):
    vol, tree, label = phantom
    pts = np.vstack([B.dense_polyline(p, 0.2)[:-TIP_POINTS] for p, _, _ in tree.values()])  # the tips aside
    idx = vol.lps_to_index_zyx(pts[:, :3])
    v = ndi.map_coordinates(vol.array_zyx, idx.T, order=1)
    assert v.min() > MIN_LUMEN_HU
    assert v[pts[:, 3] >= PROXIMAL_RADIUS_MM].min() > MIN_PROXIMAL_HU
    lab = label[tuple(np.rint(idx).astype(int).T)]
    assert np.all(np.isin(lab, [B.LABELS[k] for k in ("coronary", "plaque", "aorta")]))


def test_truth_runs_in_epicardial_fat(phantom):
    """1 mm outside the lumen, about the truth's tangent, lies fat (the coronaries sit 1.5-2.5 mm off the heart)."""
    vol, tree, label = phantom
    rng = np.random.default_rng(0)
    outside = []
    for name, (poly, _, _) in tree.items():
        if name in ("LM", "RCAO"):  # leave the aortic root
            continue
        d = B.dense_polyline(poly, 0.5)[4:-1]  # off the branch point and the tip
        t = np.gradient(d[:, :3], axis=0)
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        n = np.cross(t, rng.normal(size=t.shape))
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        outside.append(d[:, :3] + (d[:, 3:] + 1.0) * n)
    p = np.vstack(outside)
    lab = label[tuple(np.clip(np.rint(vol.lps_to_index_zyx(p)).astype(int), 0, np.array(label.shape) - 1).T)]
    assert np.mean(np.isin(lab, [B.LABELS[k] for k in ("fat", "coronary", "plaque")])) >= MIN_IN_FAT


def test_truth_lengths():
    """The main arteries' lengths are clinical ones (LAD ~120 mm with the left main, LCx ~80-90, RCA ~120-130)."""
    tree = B.coronary_tree(B._surface_distance(B.FOV_MM, B.LUMEN_HU, B.RIGHT_HU, B.PA_HU))
    length = {k: float(np.sum(np.linalg.norm(np.diff(p[:, :3], axis=0), axis=1))) for k, (p, _, _) in tree.items()}
    assert 100.0 <= length["LM"] + length["LAD"] <= 150.0
    assert 70.0 <= length["LCX"] <= 110.0
    assert 100.0 <= length["RCAO"] + length["RCA"] <= 150.0
