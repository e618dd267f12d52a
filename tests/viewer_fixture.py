"""A synthetic OUT_DIR that follows the OUT_DIR contract, for the viewer tests and benchmark.

The case is exact by construction: the 2D roadmap centerline, the live frames' dark vessels and
the 2D wire are projections of the 3D tree / wire with the true pose, so a correct viewer lines
them up to within a pixel.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from guidewire3d import io
from guidewire3d.geometry import CArm, Pose, nominal_pose
from guidewire3d.metrics import resample_polyline
from guidewire3d.vesseltree import VesselTree

BACKGROUND = 3000.0
VESSEL_CONTRAST = 800.0
WIRE_CONTRAST = 1300.0


@dataclass(frozen=True, eq=False)
class SyntheticCase:
    out_dir: Path
    frames_path: Path
    carm: CArm
    pose: Pose
    tree: VesselTree
    centerline_uv_px: np.ndarray
    wires_lps_mm: tuple
    uncertainty_mm: tuple
    images: np.ndarray
    roadmap: np.ndarray
    carm_b: CArm | None = None  # plane B of a biplane case (plane_b_deg given)
    images_b: np.ndarray | None = None  # plane B's live frames: frame k + 1 pairs with plane A's frame k
    wires_uv_b: tuple = ()  # plane B's 2D wire per pair


#: plane B's recorded projection errors (px) in the synthetic biplane report: (plane A, plane B)
PLANE_B_PROJECTION_ERRORS_PX = (0.31, 0.47)


def make_tree(*, centre_lps_mm=(12.0, -160.0, 1040.0)) -> VesselTree:
    """A non-planar three-branch tree (~120 mm of vessel) centred near ``centre_lps_mm``."""
    c = np.asarray(centre_lps_mm, float)
    s = np.linspace(0.0, 1.0, 60)
    trunk = np.column_stack([-5 + 8 * np.sin(2 * s), -4 * s, 28 - 46 * s]) + c
    s1 = np.linspace(0.0, 1.0, 40)
    left = trunk[-1] + np.column_stack([30 * s1, 6 * np.sin(3 * s1), -18 * s1**1.3])
    right = trunk[-1] + np.column_stack([-28 * s1, 10 * s1, -22 * s1 + 4 * np.sin(4 * s1)])
    s2 = np.linspace(0.0, 1.0, 25)
    side = trunk[25] + np.column_stack([18 * s2, -8 * s2, 6 * s2])
    radii = [np.linspace(4.0, 3.0, 60), np.linspace(2.6, 1.6, 40), np.linspace(2.6, 1.5, 40), np.linspace(1.8, 1.2, 25)]
    return VesselTree.from_polylines([trunk, left, right, side], radii, [None, (0, 59), (0, 59), (0, 25)])


CTA_VESSEL_HU = 450.0
CTA_TISSUE_HU = 40.0


def make_cta(tree: VesselTree, *, spacing_mm=(1.0, 1.0, 1.5), margin_mm: float = 12.0) -> io.Volume:
    """A small CTA around the tree: tissue at 40 HU, lumen (within the tree radius) at 450 HU."""
    lo = tree.points_lps_mm.min(0) - margin_mm
    hi = tree.points_lps_mm.max(0) + margin_mm
    sp = np.asarray(spacing_mm, float)
    n = np.ceil((hi - lo) / sp).astype(int) + 1
    zz, yy, xx = np.mgrid[0:n[2], 0:n[1], 0:n[0]]
    pts = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()]) * sp + lo
    dense, rad = _dense_centerline(tree, 0.5)
    d, i = cKDTree(dense).query(pts)
    hu = np.where(d <= rad[i], CTA_VESSEL_HU, CTA_TISSUE_HU).astype(np.float32).reshape(n[2], n[1], n[0])
    return io.Volume(hu, tuple(sp), tuple(lo))


def tree_polylines(tree: VesselTree):
    return [tree.points_lps_mm[b.point_ids] for b in tree.branches], [tree.radius_mm[b.point_ids] for b in tree.branches]


def vessel_surface(tree: VesselTree):
    """Tube surfaces of every branch with the tree's radius (a pyvista PolyData, LPS mm)."""
    import pyvista as pv

    meshes = []
    for pl, rr in zip(*tree_polylines(tree)):
        line = pv.lines_from_points(pl)
        line.point_data["radius_mm"] = rr
        meshes.append(line.tube(scalars="radius_mm", absolute=True, n_sides=16, capping=True))
    return pv.merge(meshes).triangulate().clean()


def _dense_centerline(tree: VesselTree, step_mm: float = 0.25):
    pts, rad = [], []
    for pl, rr in zip(*tree_polylines(tree)):
        d = resample_polyline(pl, step_mm)
        s_old = np.r_[0, np.cumsum(np.linalg.norm(np.diff(pl, axis=0), axis=1))]
        s_new = np.r_[0, np.cumsum(np.linalg.norm(np.diff(d, axis=0), axis=1))]
        pts.append(d)
        rad.append(np.interp(s_new, s_old, rr))
    return np.vstack(pts), np.concatenate(rad)


def render_frames(tree, carm, pose, wires_lps_mm, *, seed: int = 0) -> np.ndarray:
    """Live frames: dark vessels (roadmap) plus a darker thin wire, with mild noise."""
    rng = np.random.default_rng(seed)
    pts, rad = _dense_centerline(tree)
    uv, z = carm.project(pts, pose, return_depth=True)
    rad_px = rad * carm.focal_px / z
    rows, cols = carm.shape
    vv, uu = np.mgrid[0:rows, 0:cols]
    grid = np.column_stack([uu.ravel(), vv.ravel()]).astype(float)
    dist, idx = cKDTree(uv).query(grid)
    depth = np.clip(1.0 - (dist / rad_px[idx]) ** 2, 0.0, None)
    vessel = VESSEL_CONTRAST * np.sqrt(depth)
    frames = []
    for w in wires_lps_mm:
        if w is None:  # the contrast roadmap: vessels only, fully opacified
            frames.append((BACKGROUND - 1.6 * vessel + rng.normal(0.0, 15.0, size=len(grid))).reshape(rows, cols))
            continue
        wuv = carm.project(resample_polyline(w, 0.2), pose)
        dw, _ = cKDTree(wuv).query(grid)
        wire = WIRE_CONTRAST * np.clip(1.5 - dw, 0.0, 1.0)
        img = BACKGROUND - vessel - wire + rng.normal(0.0, 15.0, size=len(grid))
        frames.append(img.reshape(rows, cols))
    return np.stack(frames)


def make_wires(tree: VesselTree, n_frames: int):
    """A wire advancing along root -> left leaf; frame k reaches further. Uncertainty grows distally."""
    leaf = int(tree.branches[1].point_ids[-1])
    path = tree.points_lps_mm[tree.path(tree.root, leaf)]
    path = resample_polyline(path, 1.0)
    wires, uncs = [], []
    for k in range(n_frames):
        frac = 0.55 + 0.45 * k / max(n_frames - 1, 1)
        n = max(int(len(path) * frac), 5)
        w = path[:n] + np.array([0.6, -0.4, 0.3])  # inside the lumen, off the centreline
        s = np.linspace(0.0, 1.0, n)
        uncs.append(0.2 + 1.6 * s**2)
        wires.append(w)
    return wires, uncs


def write_synthetic_outdir(root, *, n_frames: int = 4, shape=(240, 320), primary_deg: float = 20.0,
                           secondary_deg: float = 10.0, seed: int = 0, plane_b_deg=None) -> SyntheticCase:
    """Write ``root/frames.dcm`` and the OUT_DIR ``root/out`` for a synthetic case.

    ``plane_b_deg=(primary, secondary)``: a biplane case as ``reconstruct`` with two planes writes
    it: also ``root/frames_b.dcm`` / ``roadmap_b.dcm`` (plane B's live frame ``k + 1`` shows plane A's
    frame ``k``'s wire, its frame 0 the first wire again) and ``report.json`` ``biplane`` records.
    """
    import pyvista as pv

    root = Path(root)
    out = root / "out"
    out.mkdir(parents=True, exist_ok=True)
    tree = make_tree()
    carm = CArm(primary_deg, secondary_deg, 1100.0, 760.0, 0.6, tuple(shape))
    pose = Pose.from_rotvec_about(np.radians([2.0, -3.0, 4.0]), np.zeros(3)) @ nominal_pose(tree.centroid_lps_mm)
    pose = Pose(pose.R, pose.t + np.array([1.5, -2.0, 3.0]))
    wires, uncs = make_wires(tree, n_frames)
    images = render_frames(tree, carm, pose, wires, seed=seed)
    cta_path = root / "cta.mha"
    io.write_volume(make_cta(tree), cta_path)
    frames_path = root / "frames.dcm"
    io.write_xa(frames_path, images, carm)
    roadmap = render_frames(tree, carm, pose, [None], seed=seed + 1)
    roadmap_path = root / "roadmap.dcm"
    io.write_xa(roadmap_path, roadmap, carm)

    pts, rad = _dense_centerline(tree, 0.5)
    cl_uv, z = carm.project(pts, pose, return_depth=True)
    cl_rad_px = rad * carm.focal_px / z
    np.savez(out / "registration_inputs.npz", tree_points_lps_mm=tree.points_lps_mm, tree_radius_mm=tree.radius_mm,
             tree_parent=tree.parent, centerline_uv_px=cl_uv, centerline_radius_px=cl_rad_px)

    surf = vessel_surface(tree)
    surf.save(out / "vessels.vtp")
    surf.save(out / "vessels.stl")
    cl = pv.wrap(tree.to_polydata())
    cl.save(out / "centerline.vtp")

    frames = []
    for k, (w, u) in enumerate(zip(wires, uncs)):
        uv = carm.project(w, pose)
        line = pv.lines_from_points(w)
        line.point_data["uncertainty_mm"] = u
        line.point_data["arclength_mm"] = np.r_[0, np.cumsum(np.linalg.norm(np.diff(w, axis=0), axis=1))]
        line.save(out / f"guidewire_{k:04d}.vtp")
        line.tube(radius=0.45, n_sides=12).triangulate().save(out / f"guidewire_{k:04d}.stl")
        frames.append({
            "index": k, "success": True, "message": "ok", "points_lps_mm": w.tolist(), "uncertainty_mm": u.tolist(),
            "length_mm": float(np.linalg.norm(np.diff(w, axis=0), axis=1).sum()), "projection_error_px": 0.0,
            "seconds": 0.01, "wire_uv_px": uv.tolist(),
        })
    reg = {"success": True, "message": "synthetic", "mean_residual_px": 0.0, "inlier_fraction": 1.0,
           "iterations": 0, "seconds": 0.0, "source": "automatic"}
    P = carm.projection_matrix(pose)
    report = {
        "version": 1,
        "inputs": {"cta": str(cta_path), "roadmap": str(roadmap_path), "frames": str(frames_path),
                   "roadmap_frame": 0, "series_uid": ""},
        "carm": carm.to_dict(), "frames_carm": carm.to_dict(), "pose": pose.matrix.tolist(),
        "projection_matrix": P.tolist(), "registration": reg, "frames": frames, "timing": {"total": 0.0},
    }
    carm_b = images_b = None
    uv_b = ()
    if plane_b_deg is not None:
        carm_b = CArm(float(plane_b_deg[0]), float(plane_b_deg[1]), 1150.0, 780.0, 0.6, tuple(shape))
        images_b = render_frames(tree, carm_b, pose, [wires[0], *wires], seed=seed + 2)
        frames_b_path = root / "frames_b.dcm"
        io.write_xa(frames_b_path, images_b, carm_b)
        roadmap_b_path = root / "roadmap_b.dcm"
        io.write_xa(roadmap_b_path, render_frames(tree, carm_b, pose, [None], seed=seed + 3), carm_b)
        report["inputs"].update(frames_b=str(frames_b_path), roadmap_b=str(roadmap_b_path), biplane=True)
        report["biplane"] = {"planes": [
            {"plane": p, "carm": c.to_dict(), "frames_carm": c.to_dict(), "mean_residual_px": 0.0, "fits_2d": True}
            for p, c in (("A", carm), ("B", carm_b))], "n_pairs": n_frames, "two_view_pairs": n_frames,
            "fallback_pairs": 0}
        uv_b = tuple(carm_b.project(w, pose) for w in wires)
        # plane B's roadmap centerline beside plane A's (what a biplane reconstruct keeps for refine)
        cl_b_uv, z_b = carm_b.project(pts, pose, return_depth=True)
        with np.load(out / "registration_inputs.npz") as zf:
            arrays = dict(zf)
        np.savez(out / "registration_inputs.npz", **arrays, centerline_b_uv_px=cl_b_uv,
                 centerline_b_radius_px=rad * carm_b.focal_px / z_b)
        ea, eb = PLANE_B_PROJECTION_ERRORS_PX
        for k, fr in enumerate(report["frames"]):
            fr["biplane"] = {"views": "AB", "fallback": "", "index_b": k + 1, "projection_error_px_a": ea,
                             "projection_error_px_b": eb, "wire_uv_px_b": uv_b[k].tolist()}
    (out / "report.json").write_text(json.dumps(report))
    (out / "registration.json").write_text(json.dumps({
        "pose": pose.matrix.tolist(), "automatic_pose": pose.matrix.tolist(), "projection_matrix": P.tolist(),
        "carm": carm.to_dict(), "source": "automatic", "registration": reg}))
    return SyntheticCase(out, frames_path, carm, pose, tree, cl_uv, tuple(wires), tuple(uncs), images, roadmap[0],
                         carm_b, images_b, uv_b)


if __name__ == "__main__":
    import sys

    c = write_synthetic_outdir(sys.argv[1] if len(sys.argv) > 1 else "/tmp/viewer-synth")
    print(c.out_dir)
