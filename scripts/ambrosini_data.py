"""Loader for the real liver catheterisation data of Ambrosini et al. (``shared/data/ambrosini-dataset1``).

Benchmarks and tests only (not in the package's run-time path). The data: a 3DRA vessel tree,
74 fluoroscopy frames of 2D catheter centerlines (no images), the C-arm parameters and a manual
fusion made on frame 0; see the data folder's README. ``dataset1_lps.npz`` already maps it to
guidewire3d's convention, so the manual fusion is ``Pose.identity()``.

    from ambrosini_data import load_dataset1
    d = load_dataset1()
    d.tree, d.carm, d.curves_uv_px[k]          # proximal -> distal, tip last
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from guidewire3d.geometry import CArm
from guidewire3d.vesseltree import VesselTree

#: where the shared data sits relative to a checkout (``../shared`` beside it), unless
#: ``GUIDEWIRE3D_SHARED`` names the shared folder
DEFAULT_ROOT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ambrosini-dataset1"
#: the source marks the radius of its first nodes with this placeholder value (mm)
PLACEHOLDER_RADIUS_MM = 10.0


def dataset1_root() -> Path:
    env = os.environ.get("GUIDEWIRE3D_SHARED")
    return Path(env) / "data" / "ambrosini-dataset1" if env else DEFAULT_ROOT


@dataclass(frozen=True, eq=False)
class Dataset1:
    tree: VesselTree            # LPS mm, frame-0 manual fusion applied (pose = identity)
    carm: CArm                  # the fluoroscopy view
    curves_uv_px: list          # per frame (N_k, 2) catheter centerline, proximal -> distal (tip last)
    baseline_mean_px: np.ndarray  # (74,) per-frame catheter-to-projected-tree distance under the fusion


def _radii_mm(root: Path, n: int) -> np.ndarray:
    files = sorted((root / "3dra").glob("*_vesselsStructCenterline.txt"))
    if not files:
        return np.full(n, 2.0)
    lines = [ln.strip() for ln in files[0].read_text().splitlines() if ln.strip()]
    count = int(lines[0])
    # line 1: the root; then one line of node values and one of neighbour indices per node
    node_lines = lines[2: 2 + 2 * count: 2]
    r = np.array([float(ln.split(";")[6]) for ln in node_lines[:n]])
    bad = r >= PLACEHOLDER_RADIUS_MM - 1e-9
    if bad.any() and (~bad).any():
        r[bad] = r[np.flatnonzero(~bad)[0]]
    return r


def load_dataset1(root: Path | None = None) -> Dataset1:
    root = Path(root) if root else dataset1_root()
    d = np.load(root / "dataset1_lps.npz")
    pts = np.asarray(d["tree_points_mm"], float)
    T = np.asarray(d["T_ours_from_theirs"], float)
    pts = pts @ T[:3, :3].T + T[:3, 3]
    n = len(pts)
    parent = np.full(n, -1, np.int64)
    adj: list[list[int]] = [[] for _ in range(n)]
    for a, b in np.asarray(d["tree_edges"], int):
        adj[a].append(b)
        adj[b].append(a)
    r0 = int(d["tree_root"])
    seen = np.zeros(n, bool)
    seen[r0] = True
    stack = [r0]
    while stack:
        i = stack.pop()
        for j in adj[i]:
            if not seen[j]:
                seen[j] = True
                parent[j] = i
                stack.append(j)
    tree = VesselTree(pts, _radii_mm(root, n), parent)
    ps = np.asarray(d["pixel_spacing"], float)
    carm = CArm(float(d["primary_deg"]), float(d["secondary_deg"]), float(d["sid"]), float(d["sod"]),
                float(ps[0]), (int(d["rows"]), int(d["cols"])))
    curves = []
    for k in range(len(d["catheter_len"])):
        c = np.asarray(d["catheter_uv"][k, : int(d["catheter_len"][k])], float)
        curves.append(c[::-1].copy())  # the source lists the tip first
    return Dataset1(tree, carm, curves, np.asarray(d["baseline_mean_px"], float))
