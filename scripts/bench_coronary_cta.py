"""The automatic vessel stage on a coronary CTA: a synthetic heart crop with the coronary arteries as truth.

Usage::

    nice .venv/bin/python scripts/bench_coronary_cta.py [--runs auto,aorta,lm,lm+rca] [--spacing-mm 0.4] [--slice-mm 0.6]
        [--fov-mm 180,180,130] [--lumen-hu 400] [--right-hu 180] [--pa-hu 250] [--distal-fall 0.2] [--plaques 4]
        [--noise-hu 20] [--blur-mm 0.4] [--noise-seed 0] [--write-nifti /tmp/coronary.nii.gz]

A coronary CTA is the input an interventional cardiologist brings: a tight crop around the heart (about 180 x 180 mm
in-plane, 130 mm in z, 0.4 x 0.4 x 0.6 mm voxels) whose brightest tubes are not the arteries of interest but the
left heart's blood pools, the aortic root (15 mm radius) and the descending aorta, and whose coronary arteries
(0.7-2.0 mm radius) run in epicardial fat 1-3 mm off the myocardium. The phantom (``coronary_phantom``; every number
below is a named constant of this module), in LPS mm, the left ventricle's centre at ``LV_CENTRE`` and its long axis
``LONG_AXIS`` (base to apex: left, anterior, inferior):

* the chest (``BODY``: an elliptic cylinder, skin fat 8 mm at -100 HU, chest wall 40 HU), lungs (-850 HU), a
  mediastinal fat column (-100 HU) and a layer of epicardial fat (-100 HU, ``EPICARDIAL_FAT_MM`` = 7 mm) around the
  heart and its great vessels;
* the heart: left ventricle cavity (44 x 44 x 76 mm, ``--lumen-hu`` = 400) in a myocardium ~10-12 mm thick (110 HU),
  a right ventricle (4 mm wall) and right atrium with SVC and IVC (contrast washed out by a saline chaser:
  ``--right-hu`` = 180), the left atrium with four pulmonary veins (400), the LV outflow tract into the aortic root
  (radius 16) and ascending aorta (radius 15; leaves the crop at the top), the descending aorta (radius 12, 400) in
  front of the spine, the right ventricular outflow tract, pulmonary trunk (radius 13) and its branches (10)
  (``--pa-hu`` = 250);
* bone: vertebral bodies (cortex 1000, marrow 250 HU), the sternum (cortex 900, marrow 200), six rib sections
  (radius 5 mm, cortex 900, marrow 200);
* the coronary arteries, the truth (``coronary_tree``; paths placed on the heart's surface ``CORONARY_GAP_MM`` =
  1.5-2.5 mm outside the myocardium, chambers and great vessels, in the epicardial fat): the left main (radius 2.0,
  16 mm from inside the root, 15 mm of it outside) from the left aortic sinus splitting into the LAD (anterior
  interventricular groove to and round the apex, 1.8 -> 0.7 mm, 110 mm) with two diagonals (1.2 -> 0.6, 40-45 mm)
  and the LCx (left AV groove, 1.6 -> 0.8, 91 mm) with two marginals (1.0-1.1 -> 0.6, 47-52 mm); the RCA from the
  right sinus round the right AV groove (2.0 -> 0.8, 122 mm with its ostial 13 mm) with a PDA (1.1 -> 0.7, 41 mm) in
  the inferior interventricular groove (the lengths are printed with each run). Their contrast is the aorta's, falling by ``--distal-fall`` (0.2: 400 -> 320 HU)
  over ``DISTAL_FALL_MM`` = 150 mm of path from the ostium;
* ``--plaques`` (4) calcified plaques (1200 HU, radius 1.0-1.3 mm) at the walls of the proximal LAD and RCA;
* partial volume at every edge (the fraction of a voxel-sized rim inside), Gaussian blur (``--blur-mm`` = 0.4 mm
  sigma, 0.94 mm FWHM), Gaussian noise (``--noise-hu`` = 20 HU; ``--noise-seed``).

Runs (``--runs``): ``auto`` (``vesselplan.plan_vessels`` without seeds, as ``guidewire3d vessels --cta`` runs it),
``aorta`` (a seed in the ascending aorta), ``lm`` (a seed in the left main), ``lm+rca`` (seeds in the left main and
the proximal RCA). Each prints whether it was refused (and why) or the tree's numbers: seconds, the lumen and
background levels estimated, the coronaries' truth centerline covered within ``COVER_MM`` = 1.5 mm (all segments;
then the LAD, LCx and RCA main vessels), the fraction of the estimated centerline inside the coronaries (within 1 mm of
their lumen) / the aortas / the heart chambers (LV, LA, RV, RA, SVC, IVC) / the pulmonary arteries and veins / bone /
elsewhere (myocardium, fat, lung, chest wall), the total length and the branches.
A tree mostly in heart chambers, veins or bone with exit 0 is the defect this benchmark is for.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from guidewire3d import io
from guidewire3d.app import bench, vesselplan
from guidewire3d.cta import vesselmodel
from guidewire3d.errors import InputError, SegmentationError

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_head_cta import dense_polyline  # noqa: E402  (the same sampling of a polyline with radii)

# ----------------------------------------------------------------------------------------------------------------
# the grid and the levels
# ----------------------------------------------------------------------------------------------------------------
SPACING_MM = 0.4  # in-plane
SLICE_MM = 0.6
FOV_MM = (180.0, 180.0, 130.0)  # x, y, z
FOV_CENTRE_LPS_MM = (0.0, -10.0, -10.0)
LUMEN_HU = 400.0  # the left heart, the aortas, the pulmonary veins, the coronary ostia
RIGHT_HU = 180.0  # the right heart, SVC and IVC: contrast washed out by a saline chaser
PA_HU = 250.0  # the pulmonary trunk and arteries
DISTAL_FALL = 0.2  # of the coronaries' level, over DISTAL_FALL_MM of path from the ostium
DISTAL_FALL_MM = 150.0
NOISE_HU = 20.0
BLUR_SIGMA_MM = 0.4
N_PLAQUES = 4
PLAQUE_HU = 1200.0
LEVELS = dict(air=-1000.0, tissue=40.0, fat=-100.0, lung=-850.0, myocardium=110.0, cortex=1000.0, marrow=250.0,
              sternum_cortex=900.0, sternum_marrow=200.0)
EPICARDIAL_FAT_MM = 7.0
CORONARY_GAP_MM = (1.5, 2.5)  # the coronaries' wall to the heart's surface: min, max
COVER_MM = 1.5

#: labels of the phantom's classes (``label_zyx``)
LABELS = dict(air=0, tissue=1, fat=2, lung=3, myocardium=4, lv=5, la=6, rv=7, ra=8, aorta=9, pa=10, pv=11, bone=12,
              coronary=13, plaque=14)
CHAMBERS = ("lv", "la", "rv", "ra")
HEART_SURFACE = ("myocardium", "lv", "la", "rv", "ra", "aorta", "pa", "pv")

# ----------------------------------------------------------------------------------------------------------------
# the anatomy (LPS mm: x to the patient's left, y posterior, z superior)
# ----------------------------------------------------------------------------------------------------------------
BODY = dict(centre_xy=(0.0, 5.0), semi_xy=(160.0, 100.0), skin_fat_mm=8.0)
LUNGS = (((75.0, 15.0, 0.0), (70.0, 80.0, 120.0)), ((-75.0, 15.0, 0.0), (70.0, 80.0, 120.0)))
MEDIASTINUM = dict(centre_xy=(0.0, -5.0), semi_xy=(32.0, 72.0))
LV_CENTRE = np.array([20.0, -10.0, -20.0])
LONG_AXIS = np.array([0.5, -0.5, -0.7])  # base -> apex (normalised in _heart_frame)
RV_TOWARD = np.array([-0.6, -0.8, 0.0])  # right and anterior (orthogonalised to the long axis)
#: the ventricles are ellipsoids cut by the base plane (``BASE_PLANE_MM`` from LV_CENTRE toward the base): open
#: there to the atria and the outflow tracts
LV_CAVITY_SEMI = (53.0, 22.0, 22.0)  # along the long axis, toward the RV, the third axis
LV_CAVITY_SHIFT_MM = -15.0  # along the long axis from LV_CENTRE: the cavity from -38 (base) to +38 mm (apex)
LV_CAVITY_BASE_MM = 38.0
LV_MYO_SEMI = (64.0, 32.0, 32.0)
LV_MYO_SHIFT_MM = -12.0  # the apex wall 14 mm, the free wall 10 mm
BASE_PLANE_MM = 42.0
RV_CENTRE_HF = (-10.0, 30.0, -2.0)  # heart frame (long axis, toward RV, third)
RV_CAVITY_SEMI = (46.0, 16.0, 30.0)
RV_WALL_MM = 4.0
LA = ((0.0, 32.0, 5.0), (27.0, 17.0, 20.0))  # centre, semi axes (x, y, z)
RA = ((-36.0, 0.0, 0.0), (22.0, 22.0, 25.0))
#: tubes: (x, y, z, radius) polylines
AORTA_ROOT = ((-2.0, -4.0, 19.0), 16.0)  # the sinuses: a ball
LVOT = ((8.0, 0.0, -6.0, 11.0), (-4.0, -2.0, 8.0, 12.0))
ASCENDING_AORTA = ((-4.0, -2.0, 8.0, 15.0), (-6.0, -4.0, 22.0, 15.0), (-11.0, -8.0, 45.0, 15.0), (-10.0, -6.0, 70.0, 15.0))
DESCENDING_AORTA = ((34.0, 54.0, 70.0, 12.0), (35.0, 52.0, 0.0, 12.0), (30.0, 50.0, -90.0, 12.0))
RVOT = ((0.0, -36.0, -12.0, 12.0), (12.0, -30.0, 18.0, 13.0))
PULMONARY_TRUNK = ((12.0, -30.0, 18.0, 13.0), (20.0, -16.0, 35.0, 13.0), (18.0, 2.0, 46.0, 12.0))
PULMONARY_BRANCHES = (((18.0, 2.0, 46.0, 10.0), (-8.0, 24.0, 48.0, 10.0), (-45.0, 26.0, 44.0, 9.0)),
                      ((18.0, 2.0, 46.0, 10.0), (42.0, 18.0, 48.0, 10.0), (60.0, 28.0, 42.0, 9.0)))
PULMONARY_VEINS = (((20.0, 38.0, 14.0, 7.0), (62.0, 46.0, 28.0, 6.0)), ((20.0, 40.0, -2.0, 7.0), (64.0, 50.0, -12.0, 6.0)),
                   ((-20.0, 38.0, 14.0, 7.0), (-62.0, 46.0, 28.0, 6.0)), ((-20.0, 40.0, -2.0, 7.0), (-64.0, 50.0, -12.0, 6.0)))
SVC = ((-36.0, 2.0, 70.0, 10.0), (-36.0, 1.0, 18.0, 10.0))
IVC = ((-30.0, 14.0, -90.0, 12.0), (-34.0, 6.0, -22.0, 12.0))
VERTEBRAE = dict(centre_xy=(0.0, 74.0), semi=(21.0, 16.0, 11.0), pitch_mm=27.0, z0=-85.0, marrow_fraction=0.8)
STERNUM = dict(centre_xy=(0.0, -76.0), semi_xy=(16.0, 7.0), marrow_fraction=0.65)
RIBS = dict(z_mm=(-50.0, -15.0, 20.0), radius_mm=5.0, cortex_mm=1.3, slope=0.35, wall_inset_mm=16.0)

#: the coronaries: (name, parent, control points, radius at the start, radius at the end). A control point is a guess
#: snapped onto the heart's surface: either (x, y, z) LPS mm, or (t, azimuth deg) about the LV: t along its long axis
#: (0 at the base of its cavity, 1 at its apex; above 1 the path turns round the apex), the azimuth about that axis
#: (0 toward the RV, -90 anterior-superior-left, +90 inferior-posterior-right). A branch starts at its parent's point
#: nearest its first control point; the LAD and RCA start at the end of the left main / ostial RCA, which leave the
#: aortic root (``AORTA_ROOT``) toward their first points.
CORONARY_PATHS = (
    ("LAD", "LM", ((20.0, -6.0, 18.0), (0.12, -68.0), (0.5, -60.0), (0.85, -58.0), (1.0, -50.0), (1.15, -20.0)),
     1.8, 0.7),
    ("D1", "LAD", ((0.2, -64.0), (0.45, -90.0), (0.75, -105.0)), 1.2, 0.6),
    ("D2", "LAD", ((0.45, -60.0), (0.65, -82.0), (0.9, -95.0)), 1.1, 0.6),
    ("LCX", "LM", ((20.0, -6.0, 18.0), (-0.03, -120.0), (-0.04, -160.0), (-0.05, -195.0), (-0.05, -215.0)), 1.6, 0.8),
    ("OM1", "LCX", ((-0.03, -140.0), (0.25, -145.0), (0.6, -150.0)), 1.1, 0.6),
    ("OM2", "LCX", ((-0.05, -185.0), (0.25, -185.0), (0.55, -180.0)), 1.0, 0.6),
    ("RCA", "RCAO", ((-22.0, -22.0, 17.0), (-28.0, -25.0, 5.0), (-31.0, -22.0, -8.0), (-30.0, -14.0, -20.0),
                     (-24.0, -2.0, -29.0), (-12.0, 8.0, -34.0), (0.0, 15.0, -34.0)), 2.0, 0.8),
    ("PDA", "RCA", ((-24.0, -2.0, -29.0), (0.3, 60.0), (0.75, 60.0)), 1.1, 0.7),
)
OSTIAL_RADIUS_MM = {"LM": 2.0, "RCAO": 2.0}  # the left main and the RCA's ostial segment
MAIN_ARTERIES = {"LAD": ("LM", "LAD"), "LCx": ("LCX",), "RCA": ("RCAO", "RCA")}


def _p(*pts):
    return np.array(pts, float)


def _heart_frame():
    """(u, w, v): the long axis (base -> apex), toward the RV, and their cross product (inferior-posterior)."""
    u = LONG_AXIS / np.linalg.norm(LONG_AXIS)
    w = RV_TOWARD - (RV_TOWARD @ u) * u
    w /= np.linalg.norm(w)
    return u, w, np.cross(u, w)


class _Grid:
    """A regular LPS grid (x, y, z spacing ``sp``, origin ``org``, ``n`` voxels per axis) painted by primitives."""

    def __init__(self, sp_xyz, org_xyz, n_xyz):
        self.sp = np.asarray(sp_xyz, float)
        self.org = np.asarray(org_xyz, float)
        self.n = np.asarray(n_xyz, int)
        self.h = float(np.prod(self.sp) ** (1.0 / 3.0))  # the partial-volume rim's width
        self.v = np.full(tuple(self.n[::-1]), LEVELS["air"], np.float32)
        self.label = np.zeros(self.v.shape, np.uint8)

    def box(self, lo_xyz, hi_xyz):
        """Index slices (z, y, x) and sparse coordinate grids of the box (clipped), or None when empty."""
        i0 = np.maximum(np.floor((np.asarray(lo_xyz) - self.org) / self.sp).astype(int), 0)
        i1 = np.minimum(np.ceil((np.asarray(hi_xyz) - self.org) / self.sp).astype(int) + 1, self.n)
        if np.any(i1 <= i0):
            return None
        sl = (slice(i0[2], i1[2]), slice(i0[1], i1[1]), slice(i0[0], i1[0]))
        x = (self.org[0] + self.sp[0] * np.arange(i0[0], i1[0]))[None, None, :]
        y = (self.org[1] + self.sp[1] * np.arange(i0[1], i1[1]))[None, :, None]
        z = (self.org[2] + self.sp[2] * np.arange(i0[2], i1[2]))[:, None, None]
        return sl, x, y, z

    def paint(self, sl, sd, level, label, where=None):
        """Blend ``level`` in by the fraction of the rim inside (``sd``: signed distance, mm, negative inside)."""
        frac = np.clip(0.5 - sd / self.h, 0.0, 1.0).astype(np.float32)
        if where is not None:
            frac *= where
        v = self.v[sl]
        v += (np.asarray(level, np.float32) - v) * frac
        lab = self.label[sl]
        lab[frac >= 0.5] = LABELS[label]

    def chunks(self, lo_xyz, hi_xyz, nz: int = 24):
        """The box in slabs of ``nz`` slices (bounded memory on the full grid)."""
        b = self.box(lo_xyz, hi_xyz)
        if b is None:
            return
        sl, x, y, z = b
        for k in range(0, z.shape[0], nz):
            s = (slice(sl[0].start + k, min(sl[0].start + k + nz, sl[0].stop)), sl[1], sl[2])
            yield s, x, y, z[k:k + nz]


def _ellipsoid_sd(x, y, z, centre, semi, axes=np.eye(3)):
    """Approximate signed distance (mm) to an ellipsoid (one Newton step of its quadric: exact on the surface)."""
    d = [x - centre[0], y - centre[1], z - centre[2]]
    q = [axes[0, k] * d[0] + axes[1, k] * d[1] + axes[2, k] * d[2] for k in range(3)]
    g = sum((q[k] / semi[k]) ** 2 for k in range(3))
    grad = np.sqrt(sum((2 * q[k] / semi[k] ** 2) ** 2 for k in range(3))) + 1e-6
    return (g - 1.0) / grad


def paint_ellipsoid(G: _Grid, centre, semi, level, label, axes=np.eye(3), inside_of=None, outside_of=None,
                    beyond=None):
    """An ellipsoid (``axes``: columns are its axes in LPS); optionally only inside / outside other ellipsoids
    (``(centre, semi, axes)``) and ``beyond`` a plane (``(point, normal)``: on the normal's side)."""
    r = max(semi) + 2.0
    for sl, x, y, z in G.chunks(np.asarray(centre) - r, np.asarray(centre) + r):
        sd = _ellipsoid_sd(x, y, z, centre, semi, axes)
        if np.all(sd > G.h):
            continue
        where = None
        if outside_of is not None:
            where = np.clip(0.5 + _ellipsoid_sd(x, y, z, *outside_of) / G.h, 0, 1)
        if inside_of is not None:
            w2 = np.clip(0.5 - _ellipsoid_sd(x, y, z, *inside_of) / G.h, 0, 1)
            where = w2 if where is None else where * w2
        if beyond is not None:
            (px, py, pz), n = beyond
            w3 = np.clip(0.5 + ((x - px) * n[0] + (y - py) * n[1] + (z - pz) * n[2]) / G.h, 0, 1)
            where = w3 if where is None else where * w3
        G.paint(sl, sd, level, label, where)


def tube_sd(G: _Grid, polys, margin_mm: float = 2.0, levels=None):
    """Signed distance (mm) to the union of tubes (``(K, 4)`` polylines of x, y, z, radius) over their bounding box:
    ``(slices, sd)`` (and the level of the nearest tube point when ``levels`` gives one per polyline point, as
    ``(K,)`` arrays)."""
    pts = [dense_polyline(np.asarray(p, float), 0.1) for p in polys]
    lvs = None if levels is None else [np.interp(np.linspace(0, 1, len(d)), np.linspace(0, 1, len(l)), l)
                                       for d, l in zip(pts, levels)]
    allp = np.vstack(pts)
    rmax = allp[:, 3].max() + margin_mm
    b = G.box(allp[:, :3].min(0) - rmax, allp[:, :3].max(0) + rmax)
    if b is None:
        return None
    sl, *_ = b
    i0 = np.array([sl[2].start, sl[1].start, sl[0].start])
    shape = (sl[0].stop - sl[0].start, sl[1].stop - sl[1].start, sl[2].stop - sl[2].start)
    sd = np.full(shape, 99.0, np.float32)
    lev = None if levels is None else np.zeros(shape, np.float32)
    for k, d in enumerate(pts):
        # thin the dense polyline where the tube is wide (the union of balls sags by step^2 / 8r)
        keep, last = [0], 0.0
        s = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(d[:, :3], axis=0), axis=1))])
        for i in range(1, len(d)):
            if s[i] - s[keep[-1]] >= max(0.1, min(d[i, 3] / 4.0, 2.0)) or i == len(d) - 1:
                keep.append(i)
        for i in keep:
            px, py, pz, r = d[i]
            lo = np.maximum(np.floor((np.array([px, py, pz]) - r - margin_mm - G.org) / G.sp).astype(int) - i0, 0)
            hi = np.minimum(np.ceil((np.array([px, py, pz]) + r + margin_mm - G.org) / G.sp).astype(int) + 1 - i0,
                            np.array(shape[::-1]))
            if np.any(hi <= lo):
                continue
            gx = (G.org[0] + G.sp[0] * (i0[0] + np.arange(lo[0], hi[0])))[None, None, :]
            gy = (G.org[1] + G.sp[1] * (i0[1] + np.arange(lo[1], hi[1])))[None, :, None]
            gz = (G.org[2] + G.sp[2] * (i0[2] + np.arange(lo[2], hi[2])))[:, None, None]
            dd = (np.sqrt((gx - px) ** 2 + (gy - py) ** 2 + (gz - pz) ** 2) - r).astype(np.float32)
            box = (slice(lo[2], hi[2]), slice(lo[1], hi[1]), slice(lo[0], hi[0]))
            cur = sd[box]
            closer = dd < cur
            cur[closer] = dd[closer]
            if lev is not None:
                lev[box][closer] = lvs[k][i]
    return sl, sd, lev


def paint_tubes(G: _Grid, polys, level, label, where_label_not=None):
    res = tube_sd(G, polys)
    if res is None:
        return
    sl, sd, _ = res
    where = None
    if where_label_not is not None:
        where = (~np.isin(G.label[sl], [LABELS[k] for k in where_label_not])).astype(np.float32)
    G.paint(sl, sd, level, label, where)


def paint_anatomy(G: _Grid, *, lumen_hu: float, right_hu: float, pa_hu: float, fat_distance=None) -> None:
    """Everything but the coronaries, in painting order (later over earlier). ``fat_distance(x, y, z)``: the distance
    (mm) to the heart's surface, for the epicardial fat layer (none without it)."""
    u, w, v = _heart_frame()
    HF = np.column_stack([u, w, v])
    lo, hi = G.org - 1.0, G.org + G.sp * (G.n - 1) + 1.0
    zmid = 0.5 * (lo[2] + hi[2])
    big = 1e4
    # the chest: an elliptic cylinder (an ellipsoid very long in z), skin fat, chest wall
    bx, by = BODY["centre_xy"]
    sa, sb = BODY["semi_xy"]
    paint_ellipsoid(G, (bx, by, zmid), (sa, sb, big), LEVELS["fat"], "fat")
    f = BODY["skin_fat_mm"]
    paint_ellipsoid(G, (bx, by, zmid), (sa - f, sb - f, big), LEVELS["tissue"], "tissue")
    for c, s in LUNGS:
        paint_ellipsoid(G, c, s, LEVELS["lung"], "lung",
                        inside_of=((bx, by, zmid), (sa - 2 * f, sb - 2 * f, big), np.eye(3)))
    mx, my = MEDIASTINUM["centre_xy"]
    paint_ellipsoid(G, (mx, my, zmid), (*MEDIASTINUM["semi_xy"], big), LEVELS["fat"], "fat")
    if fat_distance is not None:
        for sl, x, y, z in G.chunks(lo, hi):
            G.paint(sl, fat_distance(x, y, z) - EPICARDIAL_FAT_MM, LEVELS["fat"], "fat")
    # bone
    sx, sy = STERNUM["centre_xy"]
    paint_ellipsoid(G, (sx, sy, zmid), (*STERNUM["semi_xy"], big), LEVELS["sternum_cortex"], "bone")
    m = STERNUM["marrow_fraction"]
    paint_ellipsoid(G, (sx, sy, zmid), (STERNUM["semi_xy"][0] * m, STERNUM["semi_xy"][1] * m, big),
                    LEVELS["sternum_marrow"], "bone")
    vx, vy = VERTEBRAE["centre_xy"]
    for zc in np.arange(VERTEBRAE["z0"], hi[2] + 20, VERTEBRAE["pitch_mm"]):
        paint_ellipsoid(G, (vx, vy, zc), VERTEBRAE["semi"], LEVELS["cortex"], "bone")
        paint_ellipsoid(G, (vx, vy, zc), tuple(s * VERTEBRAE["marrow_fraction"] for s in VERTEBRAE["semi"]),
                        LEVELS["marrow"], "bone")
    for poly in rib_polylines():
        paint_tubes(G, [poly], LEVELS["sternum_cortex"], "bone")
        inner = poly.copy()
        inner[:, 3] -= RIBS["cortex_mm"]
        paint_tubes(G, [inner], LEVELS["sternum_marrow"], "bone")
    # the great vessels behind and above, then the heart
    paint_tubes(G, [_p(*DESCENDING_AORTA)], lumen_hu, "aorta")
    paint_tubes(G, [_p(*SVC), _p(*IVC)], right_hu, "ra")
    lv_myo = (LV_CENTRE + LV_MYO_SHIFT_MM * u, LV_MYO_SEMI, HF)
    rv_c = LV_CENTRE + HF @ np.asarray(RV_CENTRE_HF)
    rv_semi = np.asarray(RV_CAVITY_SEMI)
    base = (LV_CENTRE - BASE_PLANE_MM * u, u)
    paint_ellipsoid(G, rv_c, rv_semi + RV_WALL_MM, LEVELS["myocardium"], "myocardium", HF, beyond=base)
    paint_ellipsoid(G, lv_myo[0], lv_myo[1], LEVELS["myocardium"], "myocardium", lv_myo[2], beyond=base)
    paint_ellipsoid(G, rv_c, rv_semi, right_hu, "rv", HF, outside_of=lv_myo, beyond=base)
    paint_ellipsoid(G, *RA, right_hu, "ra")
    paint_ellipsoid(G, *LA, lumen_hu, "la")
    paint_tubes(G, [_p(*q) for q in PULMONARY_VEINS], lumen_hu, "pv")
    paint_ellipsoid(G, LV_CENTRE + LV_CAVITY_SHIFT_MM * u, LV_CAVITY_SEMI, lumen_hu, "lv", HF, beyond=base)
    paint_tubes(G, [_p(*LVOT)], lumen_hu, "lv")
    paint_tubes(G, [_p(*RVOT)], right_hu, "rv")
    paint_tubes(G, [_p(*PULMONARY_TRUNK), *[_p(*q) for q in PULMONARY_BRANCHES]], pa_hu, "pa")
    c, r = AORTA_ROOT
    paint_tubes(G, [_p((*c, r), (*c, r)), _p(*ASCENDING_AORTA)], lumen_hu, "aorta")


def rib_polylines() -> list[np.ndarray]:
    """Rib sections: arcs just inside the chest wall, falling anteriorly (``RIBS``), on both sides."""
    bx, by = BODY["centre_xy"]
    sa, sb = (s - RIBS["wall_inset_mm"] for s in BODY["semi_xy"])
    out = []
    for z0 in RIBS["z_mm"]:
        for side in (-1, 1):
            th = np.radians(np.linspace(-75, 40, 24))  # from anterior-lateral to posterior-lateral
            x = bx + side * sa * np.cos(th)
            y = by + sb * np.sin(th)
            z = z0 + RIBS["slope"] * (y - by)
            out.append(np.column_stack([x, y, z, np.full_like(x, RIBS["radius_mm"])]))
    return out


def _grid_for(spacing_mm, slice_mm, fov_mm) -> _Grid:
    sp = np.array([spacing_mm, spacing_mm, slice_mm])
    n = np.round(np.asarray(fov_mm, float) / sp).astype(int)
    org = np.asarray(FOV_CENTRE_LPS_MM) - 0.5 * sp * (n - 1)
    return _Grid(sp, org, n)


def _surface_distance(fov_mm, lumen_hu, right_hu, pa_hu):
    """The signed distance (mm, negative inside) to the heart's surface (myocardium, chambers, great vessels) on a
    1 mm grid, as a function of LPS coordinates (trilinear), and its gradient's."""
    C = _grid_for(1.0, 1.0, np.asarray(fov_mm) + 40.0)
    paint_anatomy(C, lumen_hu=lumen_hu, right_hu=right_hu, pa_hu=pa_hu)
    heart = np.isin(C.label, [LABELS[k] for k in HEART_SURFACE])
    dist = (ndi.distance_transform_edt(~heart) - ndi.distance_transform_edt(heart)).astype(np.float32)
    grads = np.gradient(dist)  # z, y, x per mm (1 mm grid)

    def sample(arr, x, y, z):
        x, y, z = np.broadcast_arrays(x, y, z)
        idx = np.stack([(z - C.org[2]) / C.sp[2], (y - C.org[1]) / C.sp[1], (x - C.org[0]) / C.sp[0]])
        return ndi.map_coordinates(arr, idx.reshape(3, -1), order=1, mode="nearest").reshape(x.shape)

    def at(x, y, z):
        return sample(dist, x, y, z)

    def grad(p):
        return np.stack([sample(grads[2], *p.T), sample(grads[1], *p.T), sample(grads[0], *p.T)], axis=-1)

    at.grad = grad
    return at


def _snap(surface_distance, pts: np.ndarray, target: np.ndarray, iterations: int = 12) -> np.ndarray:
    """Points moved along the distance's gradient onto its level ``target`` (mm outside the heart's surface)."""
    p = np.array(pts, float)
    for _ in range(iterations):
        d = surface_distance(*p.T)
        g = surface_distance.grad(p)
        g /= np.linalg.norm(g, axis=1, keepdims=True) + 1e-6
        p -= np.clip(d - target, -4.0, 4.0)[:, None] * g
    return p


def coronary_tree(surface_distance) -> dict:
    """name -> ``(poly, parent, s0_mm)``: the ``(K, 4)`` polyline (x, y, z, radius) of each coronary, placed on the
    heart's surface (``CORONARY_PATHS``, then snapped to ``CORONARY_GAP_MM`` outside it), its parent and its path
    distance from the ostium at its first point."""
    u, w, v = _heart_frame()

    def guess(t, az_deg):
        """A point off the LV's myocardium at (t, azimuth), to be snapped onto the heart's surface."""
        a = -LV_CAVITY_BASE_MM + (LV_CAVITY_SHIFT_MM + LV_CAVITY_SEMI[0] + LV_CAVITY_BASE_MM) * min(t, 1.0)
        tilt = np.radians(np.clip((t - 0.85) / 0.3, 0, 1) * 80.0)  # round the apex
        phi = np.radians(az_deg)
        d = np.cos(tilt) * (np.cos(phi) * w + np.sin(phi) * v) + np.sin(tilt) * u
        am = a - LV_MYO_SHIFT_MM
        rr = LV_MYO_SEMI[1] * np.sqrt(max(1.0 - (am / LV_MYO_SEMI[0]) ** 2, 0.05))
        return LV_CENTRE + a * u + (rr + 6.0) * d

    out = {}
    root_c, root_r = np.asarray(AORTA_ROOT[0]), AORTA_ROOT[1]
    for name, parent, ctrl, r0, r1 in CORONARY_PATHS:
        xyz = []  # dense guesses: along (t, azimuth) between two such points, else straight
        for c0, c1 in zip(ctrl[:-1], ctrl[1:]):
            k = 16
            f = np.linspace(0, 1, k, endpoint=False)
            if len(c0) == 2 and len(c1) == 2:
                xyz += [guess(c0[0] + (c1[0] - c0[0]) * g, c0[1] + (c1[1] - c0[1]) * g) for g in f]
            else:
                g0 = np.asarray(c0, float) if len(c0) == 3 else guess(*c0)
                g1 = np.asarray(c1, float) if len(c1) == 3 else guess(*c1)
                xyz += [g0 + (g1 - g0) * g for g in f]
        xyz.append(np.asarray(ctrl[-1], float) if len(ctrl[-1]) == 3 else guess(*ctrl[-1]))
        xyz = np.array(xyz)
        q = np.linspace(0, 1, len(xyz))
        gap = np.mean(CORONARY_GAP_MM) + 0.5 * np.diff(CORONARY_GAP_MM)[0] * np.sin(np.arange(len(q)) / 6.0)
        rad = r0 + (r1 - r0) * q
        xyz = _snap(surface_distance, xyz, rad + gap)
        xyz = ndi.uniform_filter1d(xyz, 5, axis=0, mode="nearest")  # a smooth path, then on the level again
        xyz = _snap(surface_distance, xyz, rad + gap)
        if parent in out:  # start exactly on the parent, at its point nearest the branch's first point
            pp = out[parent][0]
            j = int(np.argmin(np.linalg.norm(pp[:, :3] - xyz[0], axis=1)))
            xyz[0] = pp[j, :3]
            s0 = out[parent][2] + float(np.sum(np.linalg.norm(np.diff(pp[:j + 1, :3], axis=0), axis=1)))
        else:
            s0 = 0.0
        L = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))])
        rad = r0 + (r1 - r0) * L / L[-1]
        out[name] = (np.column_stack([xyz, rad]), parent, s0)
        if name in ("LAD", "RCA"):  # the left main, the ostial RCA: from the sinus (inside the root) to the first point
            b = xyz[0]
            o = root_c + (root_r - 1.0) * (b - root_c) / np.linalg.norm(b - root_c)
            ost = "LM" if name == "LAD" else "RCAO"
            out[ost] = (_p((*o, OSTIAL_RADIUS_MM[ost]), (*b, OSTIAL_RADIUS_MM[ost])), None, 0.0)
            out[name] = (out[name][0], ost, float(np.linalg.norm(b - o)))
    if "LCX" in out:  # the LCx starts at the left main's end, as the LAD does
        p, _, _ = out["LCX"]
        p[0, :3] = out["LM"][0][-1, :3]
        out["LCX"] = (p, "LM", out["LAD"][2])
    return out


def plaque_centres(tree: dict, n: int, rng) -> list[tuple[np.ndarray, float]]:
    """``n`` calcified plaques (centre, radius) at the walls of the proximal LAD and RCA, alternately."""
    out = []
    for k in range(n):
        poly = tree["LAD" if k % 2 == 0 else "RCA"][0]
        d = dense_polyline(poly, 0.5)
        i = min(int((8 + 12 * (k // 2)) / 0.5), len(d) - 2)  # 8, 20, 32 mm along the artery
        c, r = d[i, :3], d[i, 3]
        t = d[i + 1, :3] - d[i, :3]
        t /= np.linalg.norm(t)
        n_ = np.cross(t, rng.normal(size=3))
        n_ /= np.linalg.norm(n_)
        out.append((c + 0.9 * r * n_, float(rng.uniform(1.0, 1.3))))
    return out


def coronary_phantom(*, spacing_mm: float = SPACING_MM, slice_mm: float = SLICE_MM, fov_mm=FOV_MM,
                     lumen_hu: float = LUMEN_HU, right_hu: float = RIGHT_HU, pa_hu: float = PA_HU,
                     distal_fall: float = DISTAL_FALL, plaques: int = N_PLAQUES, noise_hu: float = NOISE_HU,
                     blur_mm: float = BLUR_SIGMA_MM, seed: int = 0):
    """``(volume, tree, label_zyx)``: the synthetic coronary CTA (see the module), its coronaries (``coronary_tree``)
    and each voxel's class (``LABELS``; the class covering most of the voxel, before blur)."""
    rng = np.random.default_rng(seed)
    dist = _surface_distance(fov_mm, lumen_hu, right_hu, pa_hu)
    tree = coronary_tree(dist)
    G = _grid_for(spacing_mm, slice_mm, fov_mm)
    paint_anatomy(G, lumen_hu=lumen_hu, right_hu=right_hu, pa_hu=pa_hu, fat_distance=dist)
    names = list(tree)
    polys = [tree[k][0] for k in names]
    levels = []
    for k in names:
        p, _, s0 = tree[k]
        s = s0 + np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(p[:, :3], axis=0), axis=1))])
        levels.append(lumen_hu * (1.0 - distal_fall * np.clip(s / DISTAL_FALL_MM, 0, 1)))
    sl, sd, lev = tube_sd(G, polys, margin_mm=1.5, levels=levels)
    G.paint(sl, sd, lev, "coronary", where=(G.label[sl] != LABELS["aorta"]).astype(np.float32))
    for c, r in plaque_centres(tree, plaques, rng):
        sd_p = tube_sd(G, [_p((*c, r), (*c, r))], margin_mm=1.5)
        G.paint(sd_p[0], sd_p[1], PLAQUE_HU, "plaque")
    sig = blur_mm / G.sp[::-1]
    v = ndi.gaussian_filter(G.v, sig, output=np.float32) if blur_mm > 0 else G.v
    for k in range(0, v.shape[0], 32):  # noise slab by slab (bounded memory)
        v[k:k + 32] += rng.normal(0.0, noise_hu, v[k:k + 32].shape).astype(np.float32)
    vol = io.Volume(v, tuple(G.sp), tuple(G.org), np.eye(3), source="coronary CTA phantom")
    return vol, tree, G.label


def seeds(tree: dict) -> dict:
    """The runs' seeds (LPS mm): the ascending aorta, the left main's middle, the proximal RCA (10 mm along)."""
    lm = tree["LM"][0]
    rca = dense_polyline(np.vstack([tree["RCAO"][0], tree["RCA"][0][1:]]), 0.5)
    s = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(rca[:, :3], axis=0), axis=1))])
    aorta = np.asarray(ASCENDING_AORTA[2][:3])
    return {"aorta": aorta, "lm": 0.5 * (lm[0, :3] + lm[-1, :3]), "rca": rca[int(np.searchsorted(s, 10.0)), :3]}


def _truth_points(tree: dict, names=None) -> np.ndarray:
    return np.vstack([dense_polyline(tree[k][0], 0.2) for k in (names or tree)])


def coronary_wall_distance(tree: dict, pts: np.ndarray, k: int = 16) -> np.ndarray:
    """Distance (mm) from points to the coronaries' lumen (negative inside; nearest of ``k`` truth points)."""
    ref = _truth_points(tree)
    d, i = cKDTree(ref[:, :3]).query(pts, k=k)
    return np.min(d - ref[i, 3], axis=1)


def evaluate(vol, trees, tree: dict, label_zyx) -> dict:
    """A tree's (or a forest's) numbers against the phantom's coronaries and classes (see the module)."""
    est = np.vstack([t.densified(0.2)[0].points_lps_mm for t in trees])  # a point every 0.2 mm at most
    kd = cKDTree(est)
    cover = {"all": float(np.mean(kd.query(_truth_points(tree)[:, :3])[0] <= COVER_MM))}
    for art, names in MAIN_ARTERIES.items():
        cover[art] = float(np.mean(kd.query(_truth_points(tree, names)[:, :3])[0] <= COVER_MM))
    idx = np.clip(np.rint(vol.lps_to_index_zyx(est)).astype(int), 0, np.array(vol.shape_zyx) - 1)
    lab = label_zyx[tuple(idx.T)]
    in_cor = (coronary_wall_distance(tree, est) < 1.0) | (lab == LABELS["plaque"])
    frac = {"coronaries": float(in_cor.mean())}
    for what, keys in (("aorta", ("aorta",)), ("chambers", CHAMBERS), ("pulmonary", ("pa", "pv")), ("bone", ("bone",))):
        frac[what] = float(np.mean(~in_cor & np.isin(lab, [LABELS[k] for k in keys])))
    frac["elsewhere"] = 1.0 - sum(frac.values())
    return {"length_m": sum(t.total_length_mm for t in trees) / 1000.0, "branches": sum(len(t.branches) for t in trees),
            "cover": cover, "frac": frac}


def _fmt_seed(s) -> str:
    return ",".join(f"{v:.1f}" for v in s)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", default="auto,aorta,lm,lm+rca")
    ap.add_argument("--spacing-mm", type=float, default=SPACING_MM, help="in-plane voxel size")
    ap.add_argument("--slice-mm", type=float, default=SLICE_MM)
    ap.add_argument("--fov-mm", default=",".join(f"{v:g}" for v in FOV_MM), help="x,y,z extent (mm)")
    ap.add_argument("--lumen-hu", type=float, default=LUMEN_HU, help="the left heart, aortas, coronary ostia")
    ap.add_argument("--right-hu", type=float, default=RIGHT_HU, help="the right heart (saline chaser)")
    ap.add_argument("--pa-hu", type=float, default=PA_HU, help="the pulmonary arteries")
    ap.add_argument("--distal-fall", type=float, default=DISTAL_FALL,
                    help=f"the coronaries' fall of level over {DISTAL_FALL_MM:g} mm of path (fraction)")
    ap.add_argument("--plaques", type=int, default=N_PLAQUES, help="calcified plaques (proximal LAD and RCA)")
    ap.add_argument("--noise-hu", type=float, default=NOISE_HU)
    ap.add_argument("--blur-mm", type=float, default=BLUR_SIGMA_MM, help="Gaussian blur sigma")
    ap.add_argument("--noise-seed", type=int, default=0)
    ap.add_argument("--write-nifti", default=None, help="also write the phantom here (guidewire3d.io.write_volume)")
    args = ap.parse_args(argv)
    fov = tuple(float(v) for v in args.fov_mm.split(","))
    t0 = time.perf_counter()
    vol, tree, label = coronary_phantom(spacing_mm=args.spacing_mm, slice_mm=args.slice_mm, fov_mm=fov,
                                        lumen_hu=args.lumen_hu, right_hu=args.right_hu, pa_hu=args.pa_hu,
                                        distal_fall=args.distal_fall, plaques=args.plaques, noise_hu=args.noise_hu,
                                        blur_mm=args.blur_mm, seed=args.noise_seed)
    t_ph = time.perf_counter() - t0
    lens = {k: float(np.sum(np.linalg.norm(np.diff(p[:, :3], axis=0), axis=1))) for k, (p, _, _) in tree.items()}
    print(f"machine: {bench.machine_line()}; load {os.getloadavg()[0]:.1f}")
    print(f"phantom: {vol.shape_zyx[::-1]} voxels (x, y, z) of {args.spacing_mm:g} x {args.spacing_mm:g} x "
          f"{args.slice_mm:g} mm, lumen {args.lumen_hu:g} HU, right heart {args.right_hu:g}, pulmonary arteries "
          f"{args.pa_hu:g}, distal fall {args.distal_fall:g}, {args.plaques} plaques, noise {args.noise_hu:g} HU, blur "
          f"{args.blur_mm:g} mm, seed {args.noise_seed}; built in {t_ph:.0f} s")
    print("coronaries (mm): " + ", ".join(f"{k} {v:.0f}" for k, v in lens.items()))
    if args.write_nifti:
        io.write_volume(vol, args.write_nifti)
        print(f"wrote {args.write_nifti}")
    sd = seeds(tree)
    runs = {"auto": None, "aorta": [sd["aorta"]], "lm": [sd["lm"]], "lm+rca": [sd["lm"], sd["rca"]]}
    print("seeds (LPS mm): " + "; ".join(f"{k} {_fmt_seed(v)}" for k, v in sd.items()))
    print("run | result | s | lumen / background est | covered all (LAD, LCx, RCA) | centerline in coronaries / "
          "aorta / chambers / pulmonary / bone / elsewhere | length m, branches")
    for run in args.runs.split(","):
        t0 = time.perf_counter()
        try:
            plan = vesselplan.plan_vessels(vol, seeds_lps_mm=runs[run])
        except (SegmentationError, InputError) as e:
            print(f"{run} | refused (exit 2): {e} | {time.perf_counter() - t0:.0f} | | | | ", flush=True)
            continue
        dt = time.perf_counter() - t0
        r = plan.trees[0]
        m = evaluate(vol, [a.vessels.tree for a in plan.trees], tree, label)
        what = f"tree ({r.segmentation})" if len(plan.trees) == 1 else \
            f"{len(plan.trees)} trees ({', '.join(a.segmentation for a in plan.trees)})"
        if any(vesselmodel.SEEDED_SHORT in a.pruned for a in plan.trees):   # a seeded tree that says it may stop short
            what += ", said short"
        c, f = m["cover"], m["frac"]
        print(f"{run} | {what} | {dt:.0f} | {r.model.lumen:.0f} / {r.model.background:.0f} | {c['all']:.2f} "
              f"({c['LAD']:.2f}, {c['LCx']:.2f}, {c['RCA']:.2f}) | {f['coronaries']:.2f} / {f['aorta']:.2f} / "
              f"{f['chambers']:.2f} / {f['pulmonary']:.2f} / {f['bone']:.2f} / {f['elsewhere']:.2f} | "
              f"{m['length_m']:.2f}, {m['branches']}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
