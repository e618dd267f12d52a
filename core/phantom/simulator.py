"""Simulator with ground truth: a vessel tree, its CTA, a guidewire in it, and the C-arm X-ray views.

Everything is procedural and reproducible from one integer seed. One call to :func:`simulate`
builds a :class:`PhantomCase`; :func:`write_case` writes it as DICOM (CT series, XA roadmap,
XA live frames, XA held-out view) plus ``truth.json`` and ``truth_masks.npz``;
:func:`load_truth` reads the truth back.

Model, in short
---------------
* **Vessel tree** (LPS mm): a trunk (radius about 3 mm) and 2-3 levels of branches grown as
  smooth tortuous curves (an Ornstein-Uhlenbeck process on the curvature vector), radii tapering
  along each branch down to about 0.8 mm, bifurcation angles 30-75 degrees. Branches that leave
  the CT box are cut there, in the truth tree too.
* **Lumen**: the union of the tubes (capsules with linearly varying radius) around the centerline
  segments; :func:`lumen_depth_mm` is its signed depth (positive inside).
* **CTA**: soft tissue about 40 HU, contrast 250-500 HU with a partial-volume edge, mild blur,
  correlated noise; optional spine/ribs (700-1200 HU) and contrast-filled blobs (a heart chamber).
* **Guidewire**: follows one root-to-leaf path; it rides on the outer side of bends, cuts the
  corner where the path turns into a side branch, wanders smoothly off-centre elsewhere, and keeps
  at least ``wire radius + WIRE_MARGIN_MM`` (or the catheter's outer radius) inside the wall.
  Over the frames its tip advances distally; the proximal end stays at the trunk's start.
* **X-ray**: projection with :class:`guidewire3d.geometry.CArm` and the true patient
  :class:`~guidewire3d.geometry.Pose`. Attenuation line integrals are exact chord lengths of rays
  through mitred cylinder segments (no drawn lines): the roadmap integrates the contrast lumen,
  the live frames the wire (and an optional guiding catheter), blurred by focal spot and detector,
  with Poisson quantum noise at a relative dose, gain flicker and an optional faint anatomy-like
  background. MONOCHROME2: background bright, vessels and wire darker.

The true pose ``T_iso_from_lps`` relates to the registration's start
``nominal_pose(tree.centroid_lps_mm)`` by ``pose @ nominal.inverse() = Pose(R, delta)``: a
rotation about the isocentre of at most 5 degrees and an isocentre offset ``|delta| <= 20 mm``.
With ``motion_mm > 0`` frame ``t`` is seen with ``pose @ Pose(I, motion_lps_mm[t])`` (the anatomy
shifted by ``motion_lps_mm[t]``, stored per frame in ``truth.json``). Physiological motion
(``breathing_mm``, ``cardiac_mm``; ``_physiological_motion``) adds a breathing rotation about the
tree's centroid and a cardiac contraction of the wire and catheter; the true pose of frame ``t`` is
``frame_pose(t)`` (also in ``truth.json``). The 3D truth stays in CTA coordinates. By default there is
no motion and every frame uses ``pose``.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import asdict, dataclass, field, fields
from enum import Enum
from pathlib import Path

import numpy as np
from guidewire3d import io
from guidewire3d.assets import resource_path
from guidewire3d.errors import GeometryError, InputError
from guidewire3d.geometry import CArm, Pose, so3_exp
from guidewire3d.io import Volume
from guidewire3d.vesseltree import VesselTree
from scipy import ndimage

__all__ = [
    "VolumeSize",
    "PhantomOptions",
    "PhantomCase",
    "Truth",
    "simulate",
    "write_case",
    "load_truth",
    "default_case_dir",
    "default_options",
    "lumen_depth_mm",
    "render_tube_line_integral",
    "add_cli_options",
    "cli_main",
    "WIRE_DIAMETERS_MM",
    "WIRE_MARGIN_MM",
    "CACHE_VERSION",
]

#: bump when the simulator's output changes, so cached default cases are regenerated
CACHE_VERSION = 1
#: 0.014" and 0.035" guidewires
WIRE_DIAMETERS_MM = (0.36, 0.89)
#: clearance kept between the wire (or catheter) surface and the lumen wall
WIRE_MARGIN_MM = 0.1
#: spacing of the truth wire points along the wire
WIRE_STEP_MM = 0.25
#: growth step of the centerline (spacing of the truth tree points)
TREE_STEP_MM = 0.5

_DEFAULT_JSON = resource_path("phantom_default.json")


class VolumeSize(str, Enum):
    """CT grid size: ``SMALL`` about 160x160x(100-140) voxels, ``LARGE`` 512x512x300."""

    SMALL = "small"
    LARGE = "large"


@dataclass(frozen=True)
class PhantomOptions:
    """What to simulate. Every field has a default; ``seed`` decides everything random."""

    seed: int = 0
    n_frames: int = 8
    wire_diameter_mm: float | None = None  # None: 0.36 or 0.89 chosen from the seed
    distractors: bool = False
    detector_px: int = 512  # 512 or 1024
    volume: str = "small"  # VolumeSize value
    background: bool = True
    catheter: bool = True
    motion_mm: float = 0.0
    dose: float = 1.0  # relative fluoroscopy dose (lower = noisier)
    # physiological motion (see ``_physiological_motion``): breathing, peak-to-peak mostly
    # cranio-caudal translation (mm) with a small rotation, and a cardiac contraction of the tree
    breathing_mm: float = 0.0
    breathing_period_s: float = 4.0
    cardiac_mm: float = 0.0
    heart_rate_bpm: float = 75.0
    frame_rate_fps: float = 15.0
    # biplane (issue 23): the second view (the held-out one) also gets a roadmap, and its angles
    # (primary LAO+, secondary CRA+) can be set; None with ``biplane``: 90 deg from the main view
    biplane: bool = False
    plane_b_angles_deg: tuple[float, float] | None = None

    def __post_init__(self):
        def bad(name, msg):
            raise InputError(f"PhantomOptions.{name}: {msg}")

        try:
            seed = int(self.seed)
        except (TypeError, ValueError):
            bad("seed", f"expected an integer, got {self.seed!r}")
        if seed < 0 or seed != self.seed:
            bad("seed", f"expected a non-negative integer, got {self.seed!r}")
        if not isinstance(self.n_frames, (int, np.integer)) or not 1 <= int(self.n_frames) <= 500:
            bad("n_frames", f"expected an integer in 1..500, got {self.n_frames!r}")
        if self.wire_diameter_mm is not None:
            try:
                d = float(self.wire_diameter_mm)
            except (TypeError, ValueError):
                bad("wire_diameter_mm", f"expected a number in mm, got {self.wire_diameter_mm!r}")
            if not 0.1 <= d <= 1.2:
                bad("wire_diameter_mm", f"expected 0.1..1.2 mm (0.36 or 0.89 typical), got {d}")
        if int(self.detector_px) not in (512, 1024):
            bad("detector_px", f"expected 512 or 1024, got {self.detector_px!r}")
        try:
            VolumeSize(self.volume)
        except ValueError:
            bad("volume", f"expected one of {[v.value for v in VolumeSize]}, got {self.volume!r}")
        if not (np.isfinite(self.motion_mm) and 0.0 <= float(self.motion_mm) <= 10.0):
            bad("motion_mm", f"expected 0..10 mm, got {self.motion_mm!r}")
        if not (np.isfinite(self.dose) and 0.01 <= float(self.dose) <= 100.0):
            bad("dose", f"expected 0.01..100, got {self.dose!r}")
        for name, lo, hi, unit in (("breathing_mm", 0.0, 25.0, "mm"), ("breathing_period_s", 1.0, 20.0, "s"),
                                   ("cardiac_mm", 0.0, 6.0, "mm"), ("heart_rate_bpm", 30.0, 200.0, "bpm"),
                                   ("frame_rate_fps", 1.0, 60.0, "fps")):
            v = getattr(self, name)
            try:
                ok = np.isfinite(float(v)) and lo <= float(v) <= hi
            except (TypeError, ValueError):
                ok = False
            if not ok:
                bad(name, f"expected {lo:g}..{hi:g} {unit}, got {v!r}")
        if self.plane_b_angles_deg is not None:
            try:
                ang = tuple(float(a) for a in self.plane_b_angles_deg)
            except (TypeError, ValueError):
                ang = ()
            if len(ang) != 2 or not np.all(np.isfinite(ang)) or not (-180 <= ang[0] <= 180 and -90 < ang[1] < 90):
                bad("plane_b_angles_deg", f"expected (primary -180..180, secondary -90..90) deg, got "
                                          f"{self.plane_b_angles_deg!r}")
            object.__setattr__(self, "plane_b_angles_deg", ang)
            if not self.biplane:
                bad("plane_b_angles_deg", "needs biplane=True")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["volume"] = VolumeSize(self.volume).value
        # the biplane fields only when used: monoplane cases keep their former options (and cache keys)
        if not self.biplane:
            d.pop("biplane")
            d.pop("plane_b_angles_deg")
        elif self.plane_b_angles_deg is not None:
            d["plane_b_angles_deg"] = list(self.plane_b_angles_deg)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "PhantomOptions":
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise InputError(f"phantom options: unknown field(s) {sorted(unknown)}")
        return cls(**d)


@dataclass(frozen=True, eq=False)
class PhantomCase:
    """A simulated case with its ground truth (see the module docstring for the model)."""

    options: PhantomOptions
    volume: Volume | None  # HU; None when simulate(make_ct=False)
    lumen_mask_zyx: np.ndarray | None  # bool, true lumen on the CT grid
    distractor_mask_zyx: np.ndarray | None  # bool, bone/blob voxels
    tree: VesselTree  # true centerline (LPS mm) with radii, root = trunk start
    carm: CArm  # main view
    pose: Pose  # true T_iso_from_lps (both views)
    roadmap: np.ndarray  # (H, W) float32 subtracted contrast frame
    vessel_mask_2d: np.ndarray  # (H, W) bool
    frames: np.ndarray  # (T, H, W) float32 live frames
    wire_lps_mm: tuple[np.ndarray, ...]  # per frame (n_t, 3) proximal -> distal
    wire_uv_px: tuple[np.ndarray, ...]  # per frame (n_t, 2)
    wire_visible: tuple[np.ndarray, ...]  # per frame (n_t,) bool
    wire_mask: np.ndarray  # (T, H, W) bool
    wire_diameter_mm: float
    heldout_carm: CArm
    heldout_frames: np.ndarray  # (T, H, W)
    heldout_wire_uv_px: tuple[np.ndarray, ...]
    wire_path_point_ids: np.ndarray  # tree point ids, root -> leaf
    motion_lps_mm: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (T, 3) anatomy shift
    # breathing rotation (T, 3) rotation vectors about ``motion_centre_lps_mm`` (applied before
    # the shift); cardiac contraction (T,): the tree scaled by (1 - cardiac_scale[t]) about the centre
    motion_rotvec_rad: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    motion_centre_lps_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    cardiac_scale: np.ndarray = field(default_factory=lambda: np.zeros(0))
    catheter_lps_mm: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (n, 3) catheter axis
    catheter_radii_mm: tuple[float, float] = (0.0, 0.0)  # (outer, inner); zeros without catheter
    heldout_roadmap: np.ndarray | None = None  # (H, W) float32: plane B's roadmap (biplane cases only)

    @property
    def projection_matrix(self) -> np.ndarray:
        return self.carm.projection_matrix(self.pose)

    @property
    def heldout_projection_matrix(self) -> np.ndarray:
        return self.heldout_carm.projection_matrix(self.pose)

    def frame_pose(self, t: int) -> Pose:
        """Pose used to render frame ``t`` (``pose`` unless there is breathing motion)."""
        return _frame_pose(self.pose, self.motion_lps_mm, self.motion_rotvec_rad, self.motion_centre_lps_mm, t)


def _frame_pose(pose: Pose, shift, rotvec, centre, t: int) -> Pose:
    """``pose @ M_t``: the anatomy rotated about ``centre`` by ``rotvec[t]``, then shifted by ``shift[t]``."""
    if len(shift) == 0:
        return pose
    m = Pose(np.eye(3), shift[t])
    if len(rotvec) and np.any(rotvec[t] != 0):
        m = m @ Pose.from_rotvec_about(rotvec[t], centre)
    return pose @ m


def _physiological_motion(options: "PhantomOptions", rng, tree: "VesselTree", n_frames: int):
    """Per-frame breathing (shift (T, 3) mm, rotation (T, 3) rad about the tree centroid) and
    cardiac contraction (T,) of the simulator.

    Breathing: ``s(t) = (1 - cos(2 pi t / (fps P) + phi)) / 2`` (0 at end-expiration), a shift of
    ``breathing_mm * s(t)`` mostly cranio-caudal (LPS +z is superior; a little antero-posterior and
    left-right) and a rotation of ``0.1 deg per mm`` of it about the left-right axis. Cardiac: the
    tree contracts about its centroid by ``cardiac_mm * h(t)`` at its radius of gyration, ``h`` the
    same raised cosine at the heart rate. Both with a random phase.
    """
    T = n_frames
    t = np.arange(T) / float(options.frame_rate_fps)
    centre = tree.points_lps_mm.mean(axis=0)
    shift, rot, scale = np.zeros((T, 3)), np.zeros((T, 3)), np.zeros(T)
    if options.breathing_mm > 0:
        phase = rng.uniform(0, 2 * np.pi)
        s = 0.5 * (1.0 - np.cos(2 * np.pi * t / float(options.breathing_period_s) + phase))
        dirn = _unit(np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.3, 0.3), 1.0]))
        shift = np.outer(s, dirn) * float(options.breathing_mm)
        rot[:, 0] = np.radians(BREATHING_DEG_PER_MM) * float(options.breathing_mm) * s
    if options.cardiac_mm > 0:
        phase = rng.uniform(0, 2 * np.pi)
        h = 0.5 * (1.0 - np.cos(2 * np.pi * t * float(options.heart_rate_bpm) / 60.0 + phase))
        rg = float(np.sqrt(np.mean(np.sum((tree.points_lps_mm - centre) ** 2, axis=1))))
        scale = float(options.cardiac_mm) / max(rg, 1.0) * h
    return shift, rot, centre, scale


#: rotation of the anatomy per mm of breathing shift (about the left-right axis)
BREATHING_DEG_PER_MM = 0.1


def _contract(points, centre, scale: float) -> np.ndarray:
    """Cardiac contraction of points about ``centre`` (identity at ``scale == 0``)."""
    if scale == 0:
        return points
    return centre + (np.asarray(points) - centre) * (1.0 - scale)


@dataclass(frozen=True, eq=False)
class Truth:
    """The ground truth of a written case (``truth.json`` + ``truth_masks.npz``)."""

    carm: CArm
    pose: Pose
    projection_matrix: np.ndarray  # (3, 4)
    heldout_carm: CArm
    heldout_projection_matrix: np.ndarray  # (3, 4)
    tree: VesselTree
    wire_lps_mm: tuple[np.ndarray, ...]
    wire_uv_px: tuple[np.ndarray, ...]
    wire_visible: tuple[np.ndarray, ...]
    heldout_wire_uv_px: tuple[np.ndarray, ...]
    wire_diameter_mm: float
    seed: int
    options: dict
    wire_mask: np.ndarray | None  # (T, H, W) bool
    vessel_mask_2d: np.ndarray | None  # (H, W) bool
    wire_path_point_ids: np.ndarray | None = None
    motion_lps_mm: np.ndarray | None = None  # (T, 3)
    motion_rotvec_rad: np.ndarray | None = None  # (T, 3)
    motion_centre_lps_mm: np.ndarray | None = None  # (3,)
    cardiac_scale: np.ndarray | None = None  # (T,)

    @property
    def n_frames(self) -> int:
        return len(self.wire_lps_mm)

    def frame_pose(self, t: int) -> Pose:
        """The true pose of frame ``t`` (``pose`` unless the patient moves)."""
        shift = self.motion_lps_mm if self.motion_lps_mm is not None else np.zeros((0, 3))
        rot = self.motion_rotvec_rad if self.motion_rotvec_rad is not None else np.zeros((0, 3))
        centre = self.motion_centre_lps_mm if self.motion_centre_lps_mm is not None else np.zeros(3)
        return _frame_pose(self.pose, shift, rot, centre, t)


# ======================================================================================
# random streams
# ======================================================================================
_STAGES = ("grid", "tree", "pose", "wire", "ct", "distractor", "xa", "background")


def _rngs(seed: int) -> dict[str, np.random.Generator]:
    """Independent generators per stage, so that e.g. ``make_ct=False`` changes nothing else."""
    ss = np.random.SeedSequence([int(seed), 0x6A3D_2024])
    return {name: np.random.default_rng(s) for name, s in zip(_STAGES, ss.spawn(len(_STAGES)))}


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-12)


def _perp_unit(t, rng) -> np.ndarray:
    a = _unit(rng.normal(size=3))
    a = a - (a @ t) * t
    if np.linalg.norm(a) < 1e-3:
        a = np.cross(t, [1.0, 0.0, 0.0]) if abs(t[0]) < 0.9 else np.cross(t, [0.0, 1.0, 0.0])
    return _unit(a)


# ======================================================================================
# CT grid
# ======================================================================================
@dataclass(frozen=True)
class _Grid:
    shape_zyx: tuple[int, int, int]
    spacing_xyz: tuple[float, float, float]
    origin_xyz: tuple[float, float, float]

    @property
    def lo(self) -> np.ndarray:
        return np.asarray(self.origin_xyz, float)

    @property
    def hi(self) -> np.ndarray:
        nz, ny, nx = self.shape_zyx
        return self.lo + (np.array([nx, ny, nz]) - 1) * np.asarray(self.spacing_xyz)


def _sample_grid(rng, volume: VolumeSize) -> tuple[_Grid, np.ndarray, np.ndarray]:
    """CT grid and the box (lo, hi) in which the tree grows."""
    sxy = round(float(rng.uniform(0.5, 0.8)), 4)
    sz = round(float(rng.uniform(0.6, 1.25)), 4)
    origin = (
        round(float(rng.uniform(-140.0, -40.0)), 3),
        round(float(rng.uniform(-160.0, -60.0)), 3),
        round(float(rng.uniform(-450.0, -80.0)), 3),
    )
    if volume is VolumeSize.SMALL:
        nz = int(np.clip(round(rng.uniform(95.0, 140.0) / sz), 100, 140))
        grid = _Grid((nz, 160, 160), (sxy, sxy, sz), origin)
        return grid, grid.lo + 3.0, grid.hi - 3.0
    grid = _Grid((300, 512, 512), (sxy, sxy, sz), origin)
    ext = grid.hi - grid.lo
    size = np.minimum([115.0, 115.0, 130.0], ext - 10.0)
    centre = grid.lo + ext / 2 + rng.uniform(-0.12, 0.12, 3) * (ext - size)
    return grid, centre - size / 2, centre + size / 2


# ======================================================================================
# vessel tree
# ======================================================================================
def _grow(rng, start, direction, length_mm, r0, r1, lo, hi, tortuosity):
    """One tortuous branch from ``start``: (n, 3) points at TREE_STEP_MM and (n,) radii."""
    step = TREE_STEP_MM
    n = max(int(length_mm / step), 4)
    pts = np.empty((n + 1, 3))
    pts[0] = start
    d = _unit(direction)
    k = np.zeros(3)
    corr = rng.uniform(8.0, 20.0)
    a = np.exp(-step / corr)
    margin = 8.0
    gain = 0.08
    noise = rng.normal(size=(n, 3)) * tortuosity * np.sqrt(1 - a * a)
    for i in range(n):
        k = a * k + noise[i]
        p = pts[i]
        steer = np.clip((margin - (p - lo)) / margin, 0, None) - np.clip((margin - (hi - p)) / margin, 0, None)
        kk = k + gain * steer
        kk = kk - (kk @ d) * d
        d = _unit(d + kk * step)
        pts[i + 1] = p + d * step
    s = np.linspace(0.0, 1.0, n + 1)
    radii = r0 + (r1 - r0) * s
    return pts, radii


def _grow_tree(rng, lo, hi):
    """Polylines, radii, parents ((branch, point index) or None) and levels of a random tree."""
    ext = hi - lo
    tort = rng.uniform(0.02, 0.06)
    # the trunk enters through a face of the box (mostly the superior or inferior one)
    axis = int(rng.choice([2, 2, 2, 1, 0]))
    sign = 1.0 if rng.random() < 0.5 else -1.0
    start = lo + ext * rng.uniform(0.3, 0.7, 3)
    start[axis] = lo[axis] + 0.5 if sign > 0 else hi[axis] - 0.5
    d0 = np.zeros(3)
    d0[axis] = sign
    d0 = _unit(d0 + 0.35 * _perp_unit(d0, rng) * rng.uniform(0.2, 1.0))
    trunk_len = rng.uniform(0.75, 0.95) * ext[axis]
    r_trunk = rng.uniform(2.6, 3.2)
    polys, radii, parents, levels = [], [], [], []
    p, r = _grow(rng, start, d0, trunk_len, r_trunk, r_trunk * rng.uniform(0.65, 0.85), lo, hi, 0.6 * tort)
    polys.append(p), radii.append(r), parents.append(None), levels.append(0)
    size = float(np.mean(ext))
    spec = {  # level: (children per parent, length fraction of box, end radius range)
        1: ((2, 4), (0.45, 0.8), (1.0, 1.5)),
        2: ((1, 3), (0.3, 0.5), (0.8, 1.1)),
        3: ((1, 2), (0.15, 0.3), (0.8, 0.85)),
    }
    queue = [0]
    while queue:
        b = queue.pop(0)
        lev = levels[b] + 1
        if lev > 3:
            continue
        if lev == 3 and rng.random() < 0.4:
            continue
        (nmin, nmax), (fl, fh), (re_lo, re_hi) = spec[lev]
        n_child = int(rng.integers(nmin, nmax + 1))
        parent_pts, parent_r = polys[b], radii[b]
        n_par = len(parent_pts)
        fracs = np.sort(rng.uniform(0.2, 0.85, n_child))
        for j in range(1, n_child):  # keep bifurcations apart
            fracs[j] = max(fracs[j], fracs[j - 1] + 12.0 / (n_par * TREE_STEP_MM))
        az0 = rng.uniform(0, 2 * np.pi)
        for j, f in enumerate(fracs):
            idx = int(f * (n_par - 1))
            if idx < 2 or idx > n_par - 6:
                continue
            t = _unit(parent_pts[idx + 1] - parent_pts[idx - 1])
            u = _perp_unit(t, rng)
            w = np.cross(t, u)
            az = az0 + 2 * np.pi * j / max(n_child, 1) + rng.uniform(-0.6, 0.6)
            axis_perp = np.cos(az) * u + np.sin(az) * w
            theta = np.radians(rng.uniform(30.0, 75.0))
            dirn = np.cos(theta) * t + np.sin(theta) * axis_perp
            r0 = max(parent_r[idx] * rng.uniform(0.6, 0.78), 0.95)
            r1 = min(rng.uniform(re_lo, re_hi), r0 - 0.05)
            length = rng.uniform(fl, fh) * size
            pc, rc = _grow(rng, parent_pts[idx], dirn, length, r0, max(r1, 0.8), lo, hi, tort)
            polys.append(pc), radii.append(rc), parents.append((b, idx)), levels.append(lev)
            queue.append(len(polys) - 1)
    return polys, radii, parents, levels


def _cut_tree(polys, radii, parents, levels, lo, hi):
    """Cut branches at the first point outside [lo, hi]; drop what hangs beyond a cut."""
    out_p, out_r, out_par, out_lev, cut = [], [], [], [], []
    new_index: dict[int, int] = {}
    for k, (pl, rr, pa, lev) in enumerate(zip(polys, radii, parents, levels)):
        if pa is not None:
            pb, pi = pa
            if pb not in new_index:
                continue
            nb = new_index[pb]
            if pi >= len(out_p[nb]) - 3:
                continue
            pa = (nb, pi)
        inside = np.all((pl >= lo) & (pl <= hi), axis=1)
        n_in = len(pl) if inside.all() else int(np.argmin(inside))
        if n_in < 8:
            if pa is None:
                return None
            continue
        new_index[k] = len(out_p)
        out_p.append(pl[:n_in]), out_r.append(rr[:n_in]), out_par.append(pa), out_lev.append(lev)
        cut.append(n_in < len(pl))
    offsets, n = [], 0
    for k, pl in enumerate(out_p):
        offsets.append(n)
        n += len(pl) if k == 0 else len(pl) - 1
    tree = VesselTree.from_polylines(out_p, out_r, out_par)
    leaf_ids = [offsets[k] + (len(pl) - 1 if k == 0 else len(pl) - 2) for k, pl in enumerate(out_p)]
    return tree, np.array(leaf_ids), np.array(out_lev), np.array(cut)


def _make_tree(rng, lo, hi, grid: _Grid):
    ct_lo, ct_hi = grid.lo + 0.5, grid.hi - 0.5
    for _ in range(50):
        polys, radii, parents, levels = _grow_tree(rng, lo, hi)
        res = _cut_tree(polys, radii, parents, levels, ct_lo, ct_hi)
        if res is None:
            continue
        tree, end_ids, lev, cut = res
        leaves = set(tree.leaves.tolist())
        if len(tree.branches) >= 5 and tree.total_length_mm > 200:
            return tree, {int(e): (int(lv), bool(c)) for e, lv, c in zip(end_ids, lev, cut) if int(e) in leaves}
    raise GeometryError("phantom: could not grow a vessel tree inside the CT box")  # pragma: no cover


# ======================================================================================
# lumen: signed depth of the union of tubes
# ======================================================================================
def lumen_depth_mm(tree: VesselTree, points_lps_mm, *, k_nearest: int = 64) -> np.ndarray:
    """Signed depth inside the lumen (mm; positive inside, negative outside) of ``(N, 3)`` points.

    The lumen is the union of tapered capsules around the tree's edges (the simulator's model);
    the depth is the largest ``radius(t) - distance to the edge axis`` over the edges near each
    point (the ``k_nearest`` nearest centreline points and their edges). Far from the tree the value
    is a lower bound of the true depth (i.e. it never overstates how deep a point is).
    """
    pts = np.atleast_2d(np.asarray(points_lps_mm, dtype=float))
    k = min(k_nearest, tree.n_points)
    _, idx = tree.kdtree.query(pts, k=k)
    idx = idx.reshape(len(pts), k)
    par = tree.parent[idx]
    best = np.full(len(pts), -np.inf)
    P, R = tree.points_lps_mm, tree.radius_mm
    for j in range(k):
        i = idx[:, j]
        for other in (par[:, j], None):
            if other is None:  # the edges to the children are covered as the children's edges
                d = R[i] - np.linalg.norm(pts - P[i], axis=1)
            else:
                ok = other >= 0
                o = np.where(ok, other, i)
                a, b = P[o], P[i]
                ab = b - a
                L2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
                t = np.clip(np.einsum("ij,ij->i", pts - a, ab) / L2, 0, 1)
                q = a + t[:, None] * ab
                d = R[o] + (R[i] - R[o]) * t - np.linalg.norm(pts - q, axis=1)
            best = np.maximum(best, d)
    return best


def _lumen_depth_grid(tree: VesselTree, grid: _Grid, *, pad_mm: float) -> np.ndarray:
    """Depth of every voxel centre (mm), exact within ``pad_mm`` of the wall, ``-pad_mm`` beyond."""
    nz, ny, nx = grid.shape_zyx
    sx, sy, sz = grid.spacing_xyz
    ox, oy, oz = grid.origin_xyz
    depth = np.full(grid.shape_zyx, -pad_mm, dtype=np.float32)
    xs = ox + sx * np.arange(nx)
    ys = oy + sy * np.arange(ny)
    zs = oz + sz * np.arange(nz)
    # coarser segments (every second edge along each branch) are exact enough for the CT
    for br in tree.branches:
        ids = _every_other(br.point_ids)
        P = tree.points_lps_mm[ids]
        R = tree.radius_mm[ids]
        for a, b, ra, rb in zip(P[:-1], P[1:], R[:-1], R[1:]):
            reach = max(ra, rb) + pad_mm
            blo = np.minimum(a, b) - reach
            bhi = np.maximum(a, b) + reach
            i0, i1 = np.searchsorted(xs, blo[0]), np.searchsorted(xs, bhi[0], side="right")
            j0, j1 = np.searchsorted(ys, blo[1]), np.searchsorted(ys, bhi[1], side="right")
            k0, k1 = np.searchsorted(zs, blo[2]), np.searchsorted(zs, bhi[2], side="right")
            if i0 >= i1 or j0 >= j1 or k0 >= k1:
                continue
            ab = b - a
            L2 = max(float(ab @ ab), 1e-12)
            dx = (xs[i0:i1] - a[0])[None, None, :]
            dy = (ys[j0:j1] - a[1])[None, :, None]
            dz = (zs[k0:k1] - a[2])[:, None, None]
            t = np.clip((dx * ab[0] + dy * ab[1] + dz * ab[2]) / L2, 0.0, 1.0)
            ex, ey, ez = dx - t * ab[0], dy - t * ab[1], dz - t * ab[2]
            d = (ra + (rb - ra) * t) - np.sqrt(ex * ex + ey * ey + ez * ez)
            sub = depth[k0:k1, j0:j1, i0:i1]
            np.maximum(sub, d.astype(np.float32), out=sub)
    return depth


def _every_other(ids: np.ndarray) -> np.ndarray:
    if len(ids) <= 2:
        return ids
    keep = np.r_[ids[:-1:2], ids[-1]]
    return keep


# ======================================================================================
# CT synthesis
# ======================================================================================
def _interp_matrix(n_fine: int, n_coarse: int) -> np.ndarray:
    """``(n_fine, n_coarse)`` smooth (Gaussian-bump) interpolation weights, rows sum to 1."""
    x = np.linspace(0.0, n_coarse - 1.0, n_fine)[:, None]
    w = np.exp(-0.5 * ((x - np.arange(n_coarse)[None, :]) / 0.6) ** 2)
    return (w / w.sum(axis=1, keepdims=True)).astype(np.float32)


def _smooth_field(rng, shape, coarse, amplitude) -> np.ndarray:
    """A smooth random field of about ``amplitude`` std (separable interpolation of a coarse grid)."""
    c = rng.normal(size=tuple(coarse)).astype(np.float32)
    mats = [_interp_matrix(s, cs) for s, cs in zip(shape, coarse)]
    if len(shape) == 2:
        f = mats[0] @ c @ mats[1].T
    else:
        f = np.einsum("ai,ijk->ajk", mats[0], c)
        f = np.einsum("bj,ajk->abk", mats[1], f)
        f = np.einsum("ck,abk->abc", mats[2], f, optimize=True)
    f = f - f.mean()
    return (f * (amplitude / max(float(f.std()), 1e-6))).astype(np.float32)


def _synth_ct(rng, grid: _Grid, depth, stamps, volume: VolumeSize, tree):
    """HU volume: soft tissue, contrast lumen with partial volume, distractor stamps, blur, noise."""
    shape = grid.shape_zyx
    sp = np.asarray(grid.spacing_xyz)
    hu = _smooth_field(rng, shape, (6, 6, 6), rng.uniform(4.0, 9.0))
    hu += np.float32(40.0)
    if volume is VolumeSize.LARGE:  # a body outline with air outside
        nz, ny, nx = shape
        yy, xx = np.mgrid[0:ny, 0:nx].astype(np.float32)
        cx, cy = (nx - 1) / 2, (ny - 1) / 2 + rng.uniform(-10, 10)
        ax, ay = nx * rng.uniform(0.42, 0.48), ny * rng.uniform(0.32, 0.4)
        body = ((xx - cx) / ax) ** 2 + ((yy - cy) / ay) ** 2 <= 1.0
        hu[:, ~body] = np.float32(-1000.0)
    # contrast, fading slightly along the tree, with a partial-volume edge
    c0 = rng.uniform(250.0, 500.0)
    vox = float(np.cbrt(np.prod(sp)))
    zi, yi, xi = np.nonzero(depth > -0.5 * vox)
    if len(zi):
        frac = np.clip(0.5 + depth[zi, yi, xi] / vox, 0.0, 1.0)
        pts = grid.lo + np.column_stack([xi, yi, zi]) * sp
        _, nn = tree.kdtree.query(pts)
        s = tree.arclength_from_root_mm[nn]
        c = c0 * (1.0 - 0.15 * s / max(float(tree.arclength_from_root_mm.max()), 1.0))
        hu[zi, yi, xi] = hu[zi, yi, xi] * (1 - frac) + c * frac
    for sl, m, v in stamps:
        sub = hu[sl]
        sub[m] = np.broadcast_to(v, m.shape)[m]
    # mild blur (scanner PSF), then correlated noise
    sig_mm = rng.uniform(0.35, 0.6)
    hu = ndimage.gaussian_filter(hu, sigma=(sig_mm / sp[2], sig_mm / sp[1], sig_mm / sp[0]), mode="nearest")
    noise = rng.standard_normal(size=shape, dtype=np.float32)
    noise = ndimage.gaussian_filter(noise, sigma=0.7, mode="wrap")
    noise *= np.float32(rng.uniform(8.0, 20.0) / max(float(noise[::4, ::4, ::4].std()), 1e-6))
    hu += noise
    del noise
    np.clip(hu, -1024, 3071, out=hu)
    return hu


def _distractors(rng, grid: _Grid, depth, pad_mm):
    """Bone (spine or ribs) and contrast-filled blobs, kept >= 3 mm from the lumen.

    Each structure is tried at a few random places (scored on a coarse voxel subset) and the one
    that overlaps the vessels least is kept; voxels closer than 3 mm to the lumen are carved out.
    Returns ``(stamps, mask)``: ``stamps`` are ``(slices, submask, hu)`` to paint into the CT.
    """
    shape = grid.shape_zyx
    nz, ny, nx = shape
    sp = np.asarray(grid.spacing_xyz)
    axes = [np.float32(grid.origin_xyz[2]) + np.float32(sp[2]) * np.arange(nz, dtype=np.float32),
            np.float32(grid.origin_xyz[1]) + np.float32(sp[1]) * np.arange(ny, dtype=np.float32),
            np.float32(grid.origin_xyz[0]) + np.float32(sp[0]) * np.arange(nx, dtype=np.float32)]
    free = depth <= -min(3.0, pad_mm - 0.01)  # >= 3 mm outside the lumen
    lo, hi = grid.lo, grid.hi
    ext = hi - lo
    mask = np.zeros(shape, bool)

    def region(q, stride):
        """Slices (z, y, x) of the structure's bounding box and its voxel-centre coordinates."""
        blo, bhi = q["bbox"]
        sl = []
        for k, (a, l, h) in enumerate(zip(axes, blo[::-1], bhi[::-1])):
            i0, i1 = int(np.searchsorted(a, l)), int(np.searchsorted(a, h, side="right"))
            sl.append(slice(i0, max(i1, i0), stride))
        z, y, x = (a[s] for a, s in zip(axes, sl))
        return tuple(sl), (z[:, None, None], y[None, :, None], x[None, None, :])

    def spine_params():
        period = rng.uniform(24, 30)
        cx = rng.uniform(lo[0] + 0.2 * ext[0], hi[0] - 0.2 * ext[0])
        cy = rng.uniform(lo[1] + 0.55 * ext[1], hi[1] + 0.1 * ext[1])
        ax, ay = rng.uniform(14, 20), rng.uniform(11, 15)
        return dict(cx=cx, cy=cy, ax=ax, ay=ay, period=period, disc=rng.uniform(4, 6),
                    phase=rng.uniform(0, period), shell=rng.uniform(950, 1200), core=rng.uniform(700, 850),
                    bbox=(np.array([cx - ax, cy - ay, lo[2] - 5]), np.array([cx + ax, cy + ay, hi[2] + 5])))

    def spine(q, zz, yy, xx):
        rr = ((xx - q["cx"]) / q["ax"]) ** 2 + ((yy - q["cy"]) / q["ay"]) ** 2
        body = (np.mod(zz - q["phase"], q["period"]) > q["disc"]) & (rr <= 1.0)
        shell = rr > (1 - 2.0 / q["ax"]) ** 2
        return body, np.where(shell, np.float32(q["shell"]), np.float32(q["core"]))

    def ribs_params():
        n_ribs = int(rng.integers(2, 4))
        z0 = rng.uniform(lo[2] + 10, hi[2] - 10)
        gap = rng.uniform(18, 26)
        cx, cy = rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1])
        R = rng.uniform(0.45, 0.7) * ext[0]
        zc = [z0 + (j - n_ribs / 2) * gap for j in range(n_ribs)]
        tilt = rng.uniform(-0.3, 0.3)
        reach_z = 5.0 + abs(tilt) * (R + 5.0)
        return dict(cx=cx, cy=cy, R=R, zc=zc, rad=[rng.uniform(3.5, 5.0) for _ in range(n_ribs)], tilt=tilt,
                    value=rng.uniform(700, 1100),
                    bbox=(np.array([cx - R - 5, cy - R - 5, min(zc) - reach_z]),
                          np.array([cx + R + 5, cy + R + 5, max(zc) + reach_z])))

    def ribs(q, zz, yy, xx):
        rho = np.sqrt((xx - q["cx"]) ** 2 + (yy - q["cy"]) ** 2)
        m = False
        for zc, rad in zip(q["zc"], q["rad"]):
            m = m | ((rho - q["R"]) ** 2 + (zz - zc - q["tilt"] * (xx - q["cx"])) ** 2 <= rad * rad)
        return m, np.float32(q["value"])

    def blob_params():
        c = lo + rng.uniform(0.1, 0.9, 3) * ext
        rad = rng.uniform(9, 22, 3)
        return dict(c=c, rad=rad, value=rng.uniform(250, 450), bbox=(c - rad, c + rad))

    def blob(q, zz, yy, xx):
        c, r = q["c"], q["rad"]
        rr = ((xx - c[0]) / r[0]) ** 2 + ((yy - c[1]) / r[1]) ** 2 + ((zz - c[2]) / r[2]) ** 2
        return rr <= 1.0, np.float32(q["value"])

    kinds = [(spine_params, spine) if rng.random() < 0.6 else (ribs_params, ribs)]
    kinds += [(blob_params, blob)] * int(rng.integers(1, 3))
    stamps = []
    for make_params, fn in kinds:
        best, best_score = None, -np.inf
        for _ in range(8):
            q = make_params()
            sl, mesh = region(q, 3)
            fc = free[sl]
            if fc.size == 0:
                continue
            m, _ = fn(q, *mesh)
            m = np.broadcast_to(m, fc.shape)
            score = float((m & fc).sum() - 4 * (m & ~fc).sum())
            if m.any() and score > best_score:
                best, best_score = q, score
        if best is None:
            continue
        sl, mesh = region(best, 1)
        m, v = fn(best, *mesh)
        m = np.broadcast_to(m, free[sl].shape) & free[sl] & ~mask[sl]
        mask[sl] |= m
        stamps.append((sl, m, np.broadcast_to(v, m.shape)))
    return stamps, mask


# ======================================================================================
# pose and views
# ======================================================================================
def _sample_pose(rng, centroid) -> Pose:
    rot = _unit(rng.normal(size=3)) * np.radians(rng.uniform(0.5, 5.0))
    delta = _unit(rng.normal(size=3)) * rng.uniform(3.0, 20.0)
    # pose @ nominal^-1 = Pose(R, delta): rotation about the isocentre, then an offset
    R = so3_exp(rot)
    return Pose(R, -R @ np.asarray(centroid) + delta)


def _sample_angles(rng) -> tuple[float, float]:
    return round(float(rng.uniform(-40, 40)), 2), round(float(rng.uniform(-25, 25)), 2)


def _beam(primary, secondary):
    a, b = np.radians(primary), np.radians(secondary)
    return np.array([np.sin(a) * np.cos(b), -np.cos(a) * np.cos(b), np.sin(b)])


def _sample_views(rng, tree: VesselTree, pose: Pose, detector_px: int) -> tuple[CArm, CArm]:
    pa, sa = _sample_angles(rng)
    sid = round(float(rng.uniform(950, 1200)), 1)
    sod = round(float(rng.uniform(650, 800)), 1)
    shape = (detector_px, detector_px)
    probe = CArm(pa, sa, sid, sod, 1.0, shape)
    uv = probe.project(tree.points_lps_mm, pose)
    extent_det_mm = float(np.max(np.ptp(uv, axis=0)))
    fill = rng.uniform(0.85, 1.3)
    pixel = round(float(np.clip(extent_det_mm / (detector_px * fill), 0.15, 0.4)), 4)
    main = CArm(pa, sa, sid, sod, pixel, shape)
    d0 = _beam(pa, sa)
    for _ in range(1000):
        pb, sb = _sample_angles(rng)
        if np.degrees(np.arccos(np.clip(d0 @ _beam(pb, sb), -1, 1))) >= 30.0:
            break
    sid2 = round(float(rng.uniform(950, 1200)), 1)
    sod2 = round(float(rng.uniform(650, 800)), 1)
    held = CArm(pb, sb, sid2, sod2, pixel, shape)
    return main, held


# ======================================================================================
# guidewire
# ======================================================================================
def _resample(points, step):
    p = np.asarray(points, float)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    n = max(int(np.round(s[-1] / step)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    return np.column_stack([np.interp(t, s, p[:, k]) for k in range(3)]), t, s


def _choose_path(rng, tree: VesselTree, leaf_info, clearance_mm):
    s = tree.arclength_from_root_mm
    cands, weights = [], []
    for leaf, (lev, cut) in leaf_info.items():
        if cut:
            continue
        ids = tree.path_to_root(leaf)
        if tree.radius_mm[ids].min() < clearance_mm + 0.15:
            continue
        cands.append(ids)
        weights.append((1.0 + lev) * s[leaf])
    if not cands:  # fall back to any leaf, cut or not
        for leaf in tree.leaves:
            ids = tree.path_to_root(int(leaf))
            cands.append(ids)
            weights.append(s[leaf])
    weights = np.asarray(weights, float)
    lengths = np.array([s[c[-1]] for c in cands])
    weights[lengths < 0.6 * lengths.max()] *= 0.05
    return cands[int(rng.choice(len(cands), p=weights / weights.sum()))]


def _wire_shape(rng, tree: VesselTree, path_ids, wire_r, cath_r, cath_len_mm):
    """The wire along the whole path (LPS, WIRE_STEP_MM apart) and the path's arclength mapping."""
    step = WIRE_STEP_MM
    P = tree.points_lps_mm[path_ids]
    R = tree.radius_mm[path_ids]
    c, s_new, s_old = _resample(P, step)
    r = np.interp(s_new, s_old, R)
    n = len(c)
    clear = np.full(n, wire_r + WIRE_MARGIN_MM)
    if cath_r > 0:
        clear[s_new <= cath_len_mm + 1.0] = cath_r + WIRE_MARGIN_MM
    rho = np.maximum(r - clear - 0.03, 0.0)
    # curvature of the (smoothed) centerline; normal points to the inner side of bends
    cs = ndimage.gaussian_filter1d(c, 3.0 / step, axis=0, mode="nearest")
    T = _unit(np.gradient(cs, step, axis=0))
    k = np.gradient(T, step, axis=0)
    k -= np.sum(k * T, axis=1, keepdims=True) * T
    kappa = np.linalg.norm(k, axis=1)
    nrm = k / np.maximum(kappa, 1e-9)[:, None]
    hug = rng.uniform(0.7, 1.0)
    outer = -nrm * (rho * hug * np.clip(kappa * rng.uniform(15, 30), 0, 1))[:, None]
    # smooth random wander in the cross-section
    wander = ndimage.gaussian_filter1d(rng.normal(size=(n, 3)), rng.uniform(6, 14) / step, axis=0, mode="nearest")
    wander -= np.sum(wander * T, axis=1, keepdims=True) * T
    wander = _unit(wander) * (rho * rng.uniform(0.2, 0.6))[:, None]
    offset = outer + wander
    # corners where the path turns into a side branch: the wire cuts them (inner side)
    w_corner = np.zeros(n)
    ch = tree.children
    for j in range(1, len(path_ids) - 1):
        node = path_ids[j]
        if len(ch[node]) < 2:
            continue
        t_in = _unit(P[j] - P[max(j - 4, 0)])
        t_out = _unit(P[min(j + 4, len(P) - 1)] - P[j])
        if np.degrees(np.arccos(np.clip(t_in @ t_out, -1, 1))) < 15:
            continue
        sb = np.interp(j, np.arange(len(P)), s_old)
        w_corner = np.maximum(w_corner, np.exp(-0.5 * ((s_new - sb) / 2.5) ** 2))
    inner = nrm * (rho * 0.9)[:, None]
    offset = (1 - w_corner)[:, None] * offset + w_corner[:, None] * inner
    mag = np.linalg.norm(offset, axis=1)
    offset *= (np.minimum(mag, rho) / np.maximum(mag, 1e-12))[:, None]
    # stiffness: the offsets vary smoothly, and kinks of the centreline (bifurcations) are rounded
    stiff = rng.uniform(1.0, 2.0) * (1.5 if wire_r > 0.3 else 1.0)
    offset = ndimage.gaussian_filter1d(offset, stiff / step, axis=0, mode="nearest")
    x = ndimage.gaussian_filter1d(c, 1.0 / step, axis=0, mode="nearest") + offset
    x = _project_into_spheres(x, c, rho)
    # uniform arclength, then make sure of the constraint again
    xr, _, _ = _resample(x, step)
    from scipy.spatial import cKDTree

    _, j = cKDTree(c).query(xr)
    xr = _project_into_spheres(xr, c[j], rho[j])
    # arclength along the path of each wire point (for the tip position per frame)
    return xr, s_new[j]


def _project_into_spheres(x, c, rho):
    v = x - c
    d = np.linalg.norm(v, axis=1)
    f = np.where(d > rho, rho / np.maximum(d, 1e-12), 1.0)
    return c + v * f[:, None]


# ======================================================================================
# X-ray rendering
# ======================================================================================
def _mitre_chains(chains):
    """Segments (a, b, r, n_a, n_b) of polylines with mitred joints (no overlap, no gap)."""
    A, B, Rr, NA, NB = [], [], [], [], []
    for pts, rad in chains:
        if len(pts) < 2:
            continue
        t = _unit(np.diff(pts, axis=0))
        nj = np.empty((len(pts), 3))
        nj[0], nj[-1] = t[0], t[-1]
        if len(pts) > 2:
            nj[1:-1] = _unit(t[:-1] + t[1:])
        A.append(pts[:-1]), B.append(pts[1:])
        Rr.append(0.5 * (rad[:-1] + rad[1:]))
        NA.append(nj[:-1]), NB.append(nj[1:])
    if not A:
        z = np.zeros((0, 3))
        return z, z, np.zeros(0), z, z
    return np.vstack(A), np.vstack(B), np.concatenate(Rr), np.vstack(NA), np.vstack(NB)


def render_tube_line_integral(carm: CArm, pose: Pose, chains, *, supersample: int = 2,
                              return_fine: bool = False) -> np.ndarray:
    """Line integrals (mm of path length) of the X-rays through tubes, per detector pixel.

    Parameters
    ----------
    carm, pose : the view and the true patient pose.
    chains : list of ``(points_lps_mm (n, 3), radius_mm (n,))`` polylines; each is a tube made of
        cylinders with mitred joints, so consecutive pieces neither overlap nor leave gaps.
    supersample : sub-pixel samples per axis (the result is their mean).
    return_fine : also return the ``(H*s, W*s)`` sub-sample image.

    Returns
    -------
    (rows, cols) float32 array of chord lengths (mm) (and the sub-sample image if asked).
    """
    ss = int(supersample)
    H, W = carm.shape
    fine = np.zeros((H * ss, W * ss), np.float32)
    _accumulate_segments(carm, pose, *_mitre_chains(chains), ss=ss, out=fine)
    coarse = _block_mean(fine, ss)
    return (coarse, fine) if return_fine else coarse


def _block_mean(fine, ss):
    if ss == 1:
        return fine.copy()
    import cv2

    H, W = fine.shape[0] // ss, fine.shape[1] // ss
    return cv2.resize(np.ascontiguousarray(fine, np.float32), (W, H), interpolation=cv2.INTER_AREA)


def _accumulate_segments(carm: CArm, pose: Pose, a_all, b_all, r_all, na_all, nb_all, *, ss: int, out):
    """Add the exact chord length of each pixel sub-sample's ray through each mitred cylinder.

    Segment ``k`` is the cylinder of radius ``r_all[k]`` around ``a_all[k] -> b_all[k]``, cut by the
    planes through ``a`` and ``b`` with normals ``na``/``nb``. ``out`` is the ``(H*ss, W*ss)`` image.
    """
    if len(a_all) == 0:
        return out
    H, W = carm.shape
    Pm = carm.projection_matrix(pose)
    Minv = np.linalg.inv(Pm[:, :3])
    C = -Minv @ Pm[:, 3]
    f = carm.focal_px
    ha = np.c_[a_all, np.ones(len(a_all))] @ Pm.T
    hb = np.c_[b_all, np.ones(len(b_all))] @ Pm.T
    uva, uvb = ha[:, :2] / ha[:, 2:], hb[:, :2] / hb[:, 2:]
    rpx = r_all * f / np.minimum(ha[:, 2], hb[:, 2])
    off = (ss - 1) / 2.0
    reach = rpx + 1.0
    ulo = np.minimum(uva[:, 0], uvb[:, 0]) - reach
    uhi = np.maximum(uva[:, 0], uvb[:, 0]) + reach
    vlo = np.minimum(uva[:, 1], uvb[:, 1]) - reach
    vhi = np.maximum(uva[:, 1], uvb[:, 1]) + reach
    I0 = np.maximum(np.floor(ulo * ss + off).astype(int), 0)
    I1 = np.minimum(np.ceil(uhi * ss + off).astype(int) + 1, W * ss)
    J0 = np.maximum(np.floor(vlo * ss + off).astype(int), 0)
    J1 = np.minimum(np.ceil(vhi * ss + off).astype(int) + 1, H * ss)
    T_all = _unit(b_all - a_all)
    W_all = C - a_all
    G1 = np.einsum("ij,ij->i", W_all, na_all)
    G2 = np.einsum("ij,ij->i", C - b_all, nb_all)
    for k in np.flatnonzero((I0 < I1) & (J0 < J1)):
        i0, i1, j0, j1 = I0[k], I1[k], J0[k], J1[k]
        u = (np.arange(i0, i1) - off) / ss
        v = (np.arange(j0, j1) - off) / ss
        # unit ray directions M^-1 (u, v, 1)
        dx = Minv[0, 0] * u[None, :] + (Minv[0, 1] * v + Minv[0, 2])[:, None]
        dy = Minv[1, 0] * u[None, :] + (Minv[1, 1] * v + Minv[1, 2])[:, None]
        dz = Minv[2, 0] * u[None, :] + (Minv[2, 1] * v + Minv[2, 2])[:, None]
        nrm = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
        dx *= nrm
        dy *= nrm
        dz *= nrm
        t, w, r = T_all[k], W_all[k], r_all[k]
        wt = w @ t
        wp = w - wt * t
        ot = dx * t[0] + dy * t[1] + dz * t[2]
        A = np.maximum(1.0 - ot * ot, 1e-12)
        Bq = dx * wp[0] + dy * wp[1] + dz * wp[2]
        disc = Bq * Bq - A * (wp @ wp - r * r)
        hit = disc > 0
        if not hit.any():
            continue
        sq = np.sqrt(np.where(hit, disc, 0.0))
        s_lo = (-Bq - sq) / A
        s_hi = (-Bq + sq) / A
        # start plane (X - a).na >= 0 ; end plane (X - b).nb <= 0, with X = C + s * ray
        na, nb = na_all[k], nb_all[k]
        h1 = dx * na[0] + dy * na[1] + dz * na[2]
        h2 = dx * nb[0] + dy * nb[1] + dz * nb[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            c1 = -G1[k] / h1
            c2 = -G2[k] / h2
        s_lo = np.where(h1 > 0, np.maximum(s_lo, c1), s_lo)
        s_hi = np.where(h1 < 0, np.minimum(s_hi, c1), s_hi)
        s_hi = np.where(h2 > 0, np.minimum(s_hi, c2), s_hi)
        s_lo = np.where(h2 < 0, np.maximum(s_lo, c2), s_lo)
        chord = np.where(hit, np.maximum(s_hi - s_lo, 0.0), 0.0)
        out[j0:j1, i0:i1] += chord.astype(np.float32)
    return out


def _tree_chains(tree: VesselTree):
    """Render chains of the tree: every branch, minus the start of children inside their parent."""
    chains = []
    P, R = tree.points_lps_mm, tree.radius_mm
    for br in tree.branches:
        ids = _every_other(br.point_ids)
        if br.parent >= 0:
            par_ids = tree.branches[br.parent].point_ids
            pp, pr = P[par_ids], R[par_ids]
            k0 = 0
            for k in range(1, len(ids)):
                q = P[ids[k]]
                d = np.linalg.norm(pp - q, axis=1)
                j = int(np.argmin(d))
                if d[j] + R[ids[k]] <= pr[j]:
                    k0 = k
                else:
                    break
            ids = ids[k0:]
        if len(ids) >= 2:
            chains.append((P[ids], R[ids]))
    return chains


def _psf_sigma_px(rng, carm: CArm) -> float:
    focal_spot = rng.uniform(0.3, 0.6)  # mm
    blur_det_mm = focal_spot * (carm.sid_mm - carm.sod_mm) / carm.sod_mm
    det = rng.uniform(0.45, 0.7)  # px
    return float(np.sqrt(det**2 + (blur_det_mm / 2.355 / carm.pixel_mm) ** 2))


def _background_att(rng, shape, amount) -> np.ndarray:
    """Faint anatomy-like residual attenuation: multi-scale smooth texture plus soft bands."""
    H, W = shape
    att = np.zeros(shape, np.float32)
    for coarse, amp in ((4, 0.5), (10, 0.3), (24, 0.15)):
        att += _smooth_field(rng, shape, (coarse, coarse), amp)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32) / max(H, W)
    for _ in range(int(rng.integers(1, 4))):  # rib/diaphragm-like soft bands
        ang = rng.uniform(0, np.pi)
        off = rng.uniform(0.2, 0.8)
        curv = rng.uniform(-0.6, 0.6)
        s = xx * np.cos(ang) + yy * np.sin(ang)
        q = -xx * np.sin(ang) + yy * np.cos(ang)
        dist = s - off - curv * (q - 0.5) ** 2
        att += np.float32(rng.uniform(0.5, 1.2)) * np.exp(-0.5 * (dist / rng.uniform(0.02, 0.05)) ** 2)
    att -= att.min()
    return att * np.float32(amount / max(float(att.max()), 1e-6))


def _gain_field(shape) -> np.ndarray:
    H, W = shape
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    r2 = ((xx - (W - 1) / 2) ** 2 + (yy - (H - 1) / 2) ** 2) / (0.5 * max(H, W)) ** 2
    return (1.0 - 0.12 * r2).astype(np.float32)


def _expose(rng, att, *, b0, n0, psf_px, gain_field, gain):
    """Detector counts for an attenuation image: blur, Poisson quanta, correlation, gain."""
    signal = np.exp(-att) * gain_field * np.float32(gain)
    signal = ndimage.gaussian_filter(signal, psf_px, mode="nearest")
    quanta = rng.poisson(np.maximum(signal, 0) * n0).astype(np.float32)
    img = quanta * np.float32(b0 / n0)
    img = ndimage.gaussian_filter(img, 0.45, mode="nearest")
    img += rng.normal(0.0, 0.002 * b0, size=img.shape).astype(np.float32)
    return np.clip(img, 0, 65535).astype(np.float32)


def _wire_mask(fine_chord, ss, uv_list, shape):
    H, W = shape
    cover = _block_mean((fine_chord > 0).astype(np.float32), ss)
    mask = cover >= 0.34
    for uv in uv_list:
        if len(uv) < 2:
            continue
        # dense 2D samples of the projected centreline (<= 0.25 px apart)
        seg = np.linalg.norm(np.diff(uv, axis=0), axis=1)
        sub = np.maximum(np.ceil(seg / 0.25).astype(int), 1)
        t = np.concatenate([np.arange(k) / k for k in sub])
        i = np.repeat(np.arange(len(seg)), sub)
        dense = np.vstack([uv[i] + (uv[i + 1] - uv[i]) * t[:, None], uv[-1:]])
        ij = np.rint(dense).astype(int)
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < W) & (ij[:, 1] >= 0) & (ij[:, 1] < H)
        mask[ij[ok, 1], ij[ok, 0]] = True
    return mask


# ======================================================================================
# simulate
# ======================================================================================
def simulate(options: PhantomOptions = PhantomOptions(), *, make_ct: bool = True, progress: bool = False) -> PhantomCase:
    """Simulate one case from ``options`` (deterministic per ``options``).

    ``make_ct=False`` skips the CT volume and masks (fast 2D-only data); everything else is the
    same as with ``make_ct=True``.
    """
    from tqdm.auto import tqdm

    if not isinstance(options, PhantomOptions):
        raise InputError(f"simulate: options must be PhantomOptions, got {type(options).__name__}")
    rngs = _rngs(options.seed)
    vsize = VolumeSize(options.volume)
    n_stages = 6 if make_ct else 4
    bar = tqdm(total=n_stages, desc=f"phantom seed {options.seed}", disable=not progress, leave=False)

    def stage(name):
        bar.set_postfix_str(name)

    # ---- tree ------------------------------------------------------------------------
    stage("vessel tree")
    grid, lo, hi = _sample_grid(rngs["grid"], vsize)
    tree, leaf_info = _make_tree(rngs["tree"], lo, hi, grid)
    bar.update()

    # ---- geometry --------------------------------------------------------------------
    pose = _sample_pose(rngs["pose"], tree.centroid_lps_mm)
    carm, held = _sample_views(rngs["pose"], tree, pose, int(options.detector_px))
    if options.biplane:
        held = biplane_plane_b(carm, held, options.plane_b_angles_deg)

    # ---- wire ------------------------------------------------------------------------
    stage("guidewire")
    rw = rngs["wire"]
    diam = float(options.wire_diameter_mm) if options.wire_diameter_mm is not None else float(rw.choice(WIRE_DIAMETERS_MM))
    wire_r = diam / 2.0
    path_ids = _choose_path(rw, tree, leaf_info, wire_r + WIRE_MARGIN_MM)
    s_path = tree.arclength_from_root_mm[path_ids]
    L_path = float(s_path[-1])
    T = int(options.n_frames)
    tip0 = rw.uniform(0.35, 0.55) * L_path
    tip1 = rw.uniform(0.88, 0.97) * L_path
    if T == 1:
        tips = np.array([tip1])
    else:
        inc = rw.dirichlet(np.full(T - 1, 4.0))
        tips = tip0 + (tip1 - tip0) * np.r_[0.0, np.cumsum(inc)]
    cath_outer = rw.uniform(0.8, 1.0)
    cath_inner = cath_outer * rw.uniform(0.7, 0.8)
    cath_len = 0.0
    if options.catheter:
        r_path = tree.radius_mm[path_ids]
        ok = r_path >= cath_outer + WIRE_MARGIN_MM + 0.5
        n_ok = len(ok) if ok.all() else int(np.argmin(ok))
        cath_len = min(rw.uniform(0.3, 0.55) * tip0, float(s_path[max(n_ok - 1, 0)]) - 2.0)
        if cath_len < 8.0:
            cath_len = 0.0
    wire_full, wire_s = _wire_shape(rw, tree, path_ids, wire_r, cath_outer if cath_len > 0 else 0.0, cath_len)
    wire_s = np.maximum.accumulate(wire_s)
    wires = tuple(wire_full[: max(int(np.searchsorted(wire_s, tip, side="right")), 2)].copy() for tip in tips)
    for w in wires:
        w.setflags(write=False)
    if cath_len > 0:
        catheter = wire_full[: max(int(np.searchsorted(wire_s, cath_len)), 2)].copy()
    else:
        catheter = np.zeros((0, 3))
    motion = np.zeros((T, 3))
    if options.motion_mm > 0:
        period = rw.uniform(10, 20)
        phase = rw.uniform(0, 2 * np.pi)
        dirn = _unit(np.array([rw.uniform(-0.2, 0.2), rw.uniform(-0.4, 0.4), 1.0]))
        motion = np.outer(np.sin(2 * np.pi * np.arange(T) / period + phase), dirn) * float(options.motion_mm)
    motion_rot, motion_centre, cardiac = np.zeros((T, 3)), tree.points_lps_mm.mean(axis=0), np.zeros(T)
    if options.breathing_mm > 0 or options.cardiac_mm > 0:
        shift, motion_rot, motion_centre, cardiac = _physiological_motion(options, rw, tree, T)
        motion = motion + shift
    bar.update()

    # ---- CT --------------------------------------------------------------------------
    volume = lumen_mask = dist_mask = None
    if make_ct:
        stage("CT lumen")
        rc, rd = rngs["ct"], rngs["distractor"]
        pad = 4.0
        depth = _lumen_depth_grid(tree, grid, pad_mm=pad)
        lumen_mask = depth >= 0
        if options.distractors:
            stamps, dist_mask = _distractors(rd, grid, depth, pad)
        else:
            stamps, dist_mask = [], np.zeros(grid.shape_zyx, bool)
        bar.update()
        stage("CT synthesis")
        hu = _synth_ct(rc, grid, depth, stamps, vsize, tree)
        del depth, stamps
        volume = Volume(hu, grid.spacing_xyz, grid.origin_xyz, np.eye(3), source=f"phantom seed {options.seed}")
        lumen_mask.setflags(write=False)
        dist_mask.setflags(write=False)
        bar.update()

    # ---- X-ray -----------------------------------------------------------------------
    stage("X-ray roadmap")
    rx, rb = rngs["xa"], rngs["background"]
    shape = carm.shape
    b0 = rx.uniform(3000, 12000)
    n0 = 300.0 * float(options.dose) * (carm.pixel_mm / 0.2) ** 2
    mu_contrast = rx.uniform(0.1, 0.22)  # 1/mm, display-equivalent iodine attenuation
    mu_wire = rx.uniform(0.45, 0.9)  # 1/mm
    mu_cath = rx.uniform(0.2, 0.35)  # 1/mm, braided catheter wall
    gain_field = _gain_field(shape)
    tree_chains = _tree_chains(tree)
    lumen_L, lumen_fine = render_tube_line_integral(carm, pose, tree_chains, supersample=2, return_fine=True)
    vessel_mask = _block_mean((lumen_fine > 0).astype(np.float32), 2) >= 0.5
    psf_main = _psf_sigma_px(rx, carm)
    psf_held = _psf_sigma_px(rx, held)
    roadmap = _expose(rx, mu_contrast * lumen_L, b0=b0, n0=4 * n0, psf_px=psf_main, gain_field=gain_field, gain=1.0)
    bar.update()

    stage("X-ray live frames")
    bg_main = _background_att(rb, shape, rb.uniform(0.15, 0.4)) if options.background else np.zeros(shape, np.float32)
    bg_held = _background_att(rb, shape, rb.uniform(0.15, 0.4)) if options.background else np.zeros(shape, np.float32)
    ss_wire = 3 if int(options.detector_px) == 512 else 2
    frames = np.empty((T,) + shape, np.float32)
    held_frames = np.empty((T,) + shape, np.float32)
    wire_mask = np.zeros((T,) + shape, bool)
    uv_main, uv_held, visible = [], [], []
    n_pts = [len(w) for w in wires]
    wire_segs = _mitre_chains([(wires[-1], np.full(len(wires[-1]), wire_r))])
    static = not (options.motion_mm or options.breathing_mm or options.cardiac_mm)
    views = [(carm, bg_main, psf_main, frames), (held, bg_held, psf_held, held_frames)]
    fine_acc = [np.zeros((shape[0] * ss_wire, shape[1] * ss_wire), np.float32) for _ in views]
    done = [0, 0]  # segments already accumulated (static anatomy: frames only add segments)
    cath_att = [None, None]
    for t in range(T):
        pose_t = pose if static else _frame_pose(pose, motion, motion_rot, motion_centre, t)
        w = _contract(wires[t], motion_centre, float(cardiac[t]))
        if cardiac[t] != 0:
            wire_segs = _mitre_chains([(_contract(wires[-1], motion_centre, float(cardiac[t])),
                                        np.full(len(wires[-1]), wire_r))])
        cath_t = _contract(catheter, motion_centre, float(cardiac[t])) if len(catheter) else catheter
        for iv, (view, bg, psf, out) in enumerate(views):
            if not static:
                fine_acc[iv][:] = 0
                done[iv] = 0
            n_seg = n_pts[t] - 1
            seg = tuple(x[done[iv]:n_seg] for x in wire_segs)
            _accumulate_segments(view, pose_t, *seg, ss=ss_wire, out=fine_acc[iv])
            done[iv] = n_seg
            Lw = _block_mean(fine_acc[iv], ss_wire)
            att = mu_wire * Lw + bg
            if len(catheter):
                if cath_att[iv] is None or not static:
                    Lo = render_tube_line_integral(view, pose_t, [(cath_t, np.full(len(catheter), cath_outer))])
                    Li = render_tube_line_integral(view, pose_t, [(cath_t, np.full(len(catheter), cath_inner))])
                    cath_att[iv] = mu_cath * np.maximum(Lo - Li, 0)
                att = att + cath_att[iv]
            gain = 1.0 + rx.normal(0, 0.015)
            out[t] = _expose(rx, att, b0=b0, n0=n0, psf_px=psf, gain_field=gain_field, gain=gain)
            uv = view.project(w, pose_t)
            if view is carm:
                uv_main.append(uv)
                visible.append(carm.in_image(uv))
                wire_mask[t] = _wire_mask(fine_acc[iv], ss_wire, [uv], shape)
            else:
                uv_held.append(uv)
    held_roadmap = None
    if options.biplane:  # after every other draw, so that plane A and the truth stay as without it
        L_held = render_tube_line_integral(held, pose, tree_chains, supersample=2)
        held_roadmap = _expose(rx, mu_contrast * L_held, b0=b0, n0=4 * n0, psf_px=psf_held, gain_field=gain_field,
                               gain=1.0)
        held_roadmap.setflags(write=False)
    bar.update()
    bar.close()
    for arr in (roadmap, vessel_mask, frames, held_frames, wire_mask, *uv_main, *uv_held, *visible):
        arr.setflags(write=False)
    return PhantomCase(
        options=options,
        volume=volume,
        lumen_mask_zyx=lumen_mask,
        distractor_mask_zyx=dist_mask,
        tree=tree,
        carm=carm,
        pose=pose,
        roadmap=roadmap,
        vessel_mask_2d=vessel_mask,
        frames=frames,
        wire_lps_mm=wires,
        wire_uv_px=tuple(uv_main),
        wire_visible=tuple(visible),
        wire_mask=wire_mask,
        wire_diameter_mm=diam,
        heldout_carm=held,
        heldout_frames=held_frames,
        heldout_wire_uv_px=tuple(uv_held),
        wire_path_point_ids=np.asarray(path_ids, dtype=np.int64),
        motion_lps_mm=motion,
        motion_rotvec_rad=motion_rot,
        motion_centre_lps_mm=motion_centre,
        cardiac_scale=cardiac,
        catheter_lps_mm=catheter,
        catheter_radii_mm=(float(cath_outer), float(cath_inner)) if len(catheter) else (0.0, 0.0),
        heldout_roadmap=held_roadmap,
    )


#: default separation of a biplane's plane B from plane A (LAO/RAO), deg
BIPLANE_DEFAULT_SEPARATION_DEG = 90.0


def biplane_plane_b(plane_a: CArm, drawn: CArm, angles_deg=None) -> CArm:
    """Plane B of a biplane case: the drawn second view's SID and SOD, plane A's pixel size, at
    ``angles_deg`` (primary, secondary) or, by default, 90 deg from plane A in LAO/RAO (towards the
    lateral side nearer to it) at 0 deg CRA/CAU, as a frontal + lateral biplane is used."""
    if angles_deg is None:
        pa = float(plane_a.primary_deg)
        pb = pa - BIPLANE_DEFAULT_SEPARATION_DEG if pa >= 0 else pa + BIPLANE_DEFAULT_SEPARATION_DEG
        angles_deg = (pb, 0.0)
    return CArm(float(angles_deg[0]), float(angles_deg[1]), drawn.sid_mm, drawn.sod_mm, plane_a.pixel_mm, plane_a.shape)


# ======================================================================================
# writing and reading
# ======================================================================================
def _round(a, nd=5):
    return np.round(np.asarray(a, dtype=float), nd).tolist()


def truth_dict(case: PhantomCase) -> dict:
    """The JSON-ready truth record of a case (the content of ``truth.json``)."""
    frames = []
    for t in range(len(case.wire_lps_mm)):
        frames.append({
            "index": t,
            "points_lps_mm": _round(case.wire_lps_mm[t]),
            "uv_px": _round(case.wire_uv_px[t], 4),
            "visible": [bool(v) for v in case.wire_visible[t]],
            "heldout_uv_px": _round(case.heldout_wire_uv_px[t], 4),
            "motion_lps_mm": _round(case.motion_lps_mm[t]) if len(case.motion_lps_mm) else [0.0, 0.0, 0.0],
            "motion_rotvec_rad": _round(case.motion_rotvec_rad[t], 8) if len(case.motion_rotvec_rad) else [0.0] * 3,
            "cardiac_scale": float(case.cardiac_scale[t]) if len(case.cardiac_scale) else 0.0,
            "pose": case.frame_pose(t).to_dict(),
        })
    return {
        "format": "guidewire3d-phantom-truth",
        "version": CACHE_VERSION,
        "seed": int(case.options.seed),
        "options": case.options.to_dict(),
        "carm": case.carm.to_dict(),
        "pose": case.pose.to_dict(),
        "projection_matrix": case.projection_matrix.tolist(),
        "heldout": {"carm": case.heldout_carm.to_dict(), "projection_matrix": case.heldout_projection_matrix.tolist()},
        "tree": case.tree.to_dict(),
        "wire_diameter_mm": float(case.wire_diameter_mm),
        "frames": frames,
        "wire_path_point_ids": [int(i) for i in case.wire_path_point_ids],
        "motion_centre_lps_mm": _round(case.motion_centre_lps_mm),
        "catheter": {"points_lps_mm": _round(case.catheter_lps_mm), "outer_radius_mm": case.catheter_radii_mm[0],
                     "inner_radius_mm": case.catheter_radii_mm[1]},
    }


def write_case(case: PhantomCase, out_dir) -> Path:
    """Write a case: ``ct/`` (DICOM CT series), ``roadmap.dcm``, ``frames.dcm``, ``heldout.dcm``
    (XA), ``truth.json`` and ``truth_masks.npz``.

    Everything goes into a temporary sibling folder that is renamed to ``out_dir`` at the end, so
    a reader never sees a half-written case. ``out_dir`` must be absent or empty.
    """
    from pydicom.uid import generate_uid

    out_dir = io.require_empty_folder(out_dir)

    def write(tmp: Path) -> None:
        study = generate_uid()
        pid = f"GW3D-{case.options.seed}"
        if case.volume is not None:
            io.write_ct_series(case.volume, tmp / "ct", patient_id=pid, study_uid=study)
        io.write_xa(tmp / "roadmap.dcm", case.roadmap[None], case.carm, patient_id=pid, study_uid=study,
                    description="guidewire3d phantom roadmap (subtracted contrast)")
        io.write_xa(tmp / "frames.dcm", case.frames, case.carm, patient_id=pid, study_uid=study,
                    description="guidewire3d phantom live frames")
        io.write_xa(tmp / "heldout.dcm", case.heldout_frames, case.heldout_carm, patient_id=pid, study_uid=study,
                    description="guidewire3d phantom held-out view")
        if case.heldout_roadmap is not None:  # biplane: plane B (the held-out view) with its own roadmap
            io.write_xa(tmp / "roadmap_b.dcm", case.heldout_roadmap[None], case.heldout_carm, patient_id=pid,
                        study_uid=study, description="guidewire3d phantom plane B roadmap (subtracted contrast)")
            io.write_xa(tmp / "frames_b.dcm", case.heldout_frames, case.heldout_carm, patient_id=pid,
                        study_uid=study, description="guidewire3d phantom plane B live frames")
        (tmp / "truth.json").write_text(json.dumps(truth_dict(case)))
        masks = {"wire_mask": case.wire_mask, "vessel_mask_2d": case.vessel_mask_2d}
        if case.lumen_mask_zyx is not None:
            masks["lumen_mask_zyx"] = case.lumen_mask_zyx
            masks["distractor_mask_zyx"] = case.distractor_mask_zyx
        np.savez_compressed(tmp / "truth_masks.npz", **{k: np.asarray(v, bool) for k, v in masks.items()})

    return io.write_folder_atomically(out_dir, write)


def load_truth(case_dir) -> Truth:
    """Read ``truth.json`` (and ``truth_masks.npz`` if present) of a written case."""
    case_dir = Path(case_dir)
    path = case_dir / "truth.json" if case_dir.is_dir() or not case_dir.suffix else case_dir
    if not path.is_file():
        raise InputError(f"{path}: no such file (expected a phantom truth.json)")
    try:
        d = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: corrupt truth file ({e.__class__.__name__})") from None
    if not isinstance(d, dict):
        raise InputError(f"{path}: corrupt truth file (expected a JSON object)")
    try:
        carm = CArm.from_dict(d["carm"])
        held = CArm.from_dict(d["heldout"]["carm"])
        frames = d["frames"]
        truth = Truth(
            carm=carm,
            pose=Pose.from_dict(d["pose"]),
            projection_matrix=np.asarray(d["projection_matrix"], float).reshape(3, 4),
            heldout_carm=held,
            heldout_projection_matrix=np.asarray(d["heldout"]["projection_matrix"], float).reshape(3, 4),
            tree=VesselTree.from_dict(d["tree"]),
            wire_lps_mm=tuple(np.asarray(f["points_lps_mm"], float).reshape(-1, 3) for f in frames),
            wire_uv_px=tuple(np.asarray(f["uv_px"], float).reshape(-1, 2) for f in frames),
            wire_visible=tuple(np.asarray(f["visible"], bool) for f in frames),
            heldout_wire_uv_px=tuple(np.asarray(f["heldout_uv_px"], float).reshape(-1, 2) for f in frames),
            wire_diameter_mm=float(d["wire_diameter_mm"]),
            seed=int(d["seed"]),
            options=dict(d["options"]),
            wire_mask=None,
            vessel_mask_2d=None,
            wire_path_point_ids=np.asarray(d.get("wire_path_point_ids", []), np.int64),
            motion_lps_mm=np.asarray([f.get("motion_lps_mm", [0.0, 0.0, 0.0]) for f in frames], float).reshape(-1, 3),
            motion_rotvec_rad=np.asarray([f.get("motion_rotvec_rad", [0.0] * 3) for f in frames], float).reshape(-1, 3),
            motion_centre_lps_mm=np.asarray(d.get("motion_centre_lps_mm", [0.0] * 3), float).reshape(3),
            cardiac_scale=np.asarray([f.get("cardiac_scale", 0.0) for f in frames], float).reshape(-1),
        )
    except KeyError as e:
        raise InputError(f"{path}: corrupt truth file (missing field {e.args[0]!r})") from None
    except (TypeError, ValueError, IndexError, GeometryError, InputError) as e:
        raise InputError(f"{path}: corrupt truth file ({' '.join(str(e).split())[:120]})") from None
    npz = path.parent / "truth_masks.npz"
    if npz.exists():
        try:
            with np.load(npz) as z:
                wm = z["wire_mask"].astype(bool)
                vm = z["vessel_mask_2d"].astype(bool)
        except Exception as e:  # noqa: BLE001
            raise InputError(f"{npz}: corrupt mask file ({e.__class__.__name__})") from None
        object.__setattr__(truth, "wire_mask", wm)
        object.__setattr__(truth, "vessel_mask_2d", vm)
    return truth


# ======================================================================================
# default case
# ======================================================================================
_BUILTIN_DEFAULT = {"seed": 2024, "n_frames": 10, "wire_diameter_mm": None, "distractors": True,
                    "detector_px": 512, "volume": "small", "background": True, "catheter": True,
                    "motion_mm": 0.0, "dose": 1.0}


def default_options() -> PhantomOptions:
    """The default case's options, from ``resources/phantom_default.json`` (built-in fallback)."""
    d = dict(_BUILTIN_DEFAULT)
    if _DEFAULT_JSON.is_file():
        try:
            d.update(json.loads(_DEFAULT_JSON.read_text()).get("options", {}))
        except (json.JSONDecodeError, AttributeError):
            raise InputError(f"{_DEFAULT_JSON}: invalid JSON for the default phantom options") from None
    return PhantomOptions.from_dict(d)


def _cache_root(cache_dir=None) -> Path:
    if cache_dir is not None:
        return Path(cache_dir)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "guidewire3d"


def default_case_dir(*, cache_dir=None, progress: bool = True) -> Path:
    """The default phantom case (fixed seed), generated once and cached.

    The folder is ``<cache>/phantom-default-v<CACHE_VERSION>-<hash of the options>`` under
    ``cache_dir`` or ``$XDG_CACHE_HOME/guidewire3d`` (``~/.cache/guidewire3d``).
    """
    opts = default_options()
    key = hashlib.sha1(json.dumps(opts.to_dict(), sort_keys=True).encode()).hexdigest()[:10]
    folder = _cache_root(cache_dir) / f"phantom-default-v{CACHE_VERSION}-{key}"
    if (folder / "truth.json").is_file() and (folder / "frames.dcm").is_file():
        return folder
    if folder.exists():  # incomplete leftover (should not happen with atomic writes)
        shutil.rmtree(folder, ignore_errors=True)
    case = simulate(opts, progress=progress)
    try:
        return write_case(case, folder)
    except (InputError, OSError):
        if (folder / "truth.json").is_file():  # written concurrently by another process
            return folder
        raise


# ======================================================================================
# command line
# ======================================================================================
def add_cli_options(p) -> None:
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output folder (created; must be absent or empty): ct/, roadmap.dcm, frames.dcm, "
                        "heldout.dcm, truth.json, truth_masks.npz")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="random seed (non-negative); default 0")
    p.add_argument("--frames", type=int, default=8, metavar="T", help="number of live frames (default 8)")
    p.add_argument("--wire-diameter", type=float, default=None, metavar="MM",
                   help="guidewire diameter in mm (default: 0.36 or 0.89, chosen from the seed)")
    p.add_argument("--distractors", action="store_true",
                   help="add bone (spine or ribs, 700-1200 HU) and contrast-filled blobs to the CT")
    p.add_argument("--detector", type=int, choices=(512, 1024), default=512,
                   help="detector size in pixels, square (default 512)")
    p.add_argument("--volume", choices=[v.value for v in VolumeSize], default="small",
                   help="CT size: small (about 160x160x120, fast) or large (512x512x300); default small")
    p.add_argument("--no-background", action="store_true",
                   help="no faint anatomy-like residual background in the live frames")
    p.add_argument("--no-catheter", action="store_true", help="no guiding catheter over the proximal wire")
    p.add_argument("--motion", type=float, default=0.0, metavar="MM",
                   help="amplitude of per-frame rigid breathing motion in mm (default 0)")
    p.add_argument("--dose", type=float, default=1.0, metavar="X",
                   help="relative fluoroscopy dose; lower is noisier (default 1)")
    p.add_argument("--no-ct", action="store_true", help="skip the CT series (2D data and truth only)")
    p.add_argument("--biplane", action="store_true",
                   help="biplane: also write plane B (the second view, same isocentre) as roadmap_b.dcm and "
                        "frames_b.dcm, each with its own positioner tags (plane A: roadmap.dcm, frames.dcm)")
    p.add_argument("--plane-b-angles-deg", type=float, nargs=2, default=None, metavar=("LAO_RAO", "CRAN_CAUD"),
                   help="plane B's PositionerPrimaryAngle (LAO +) and PositionerSecondaryAngle (CRA +) in degrees "
                        "(with --biplane; default: 90 deg from plane A in LAO/RAO, 0 CRA/CAU)")


_CLI_OPTION_OF_FIELD = {"seed": "--seed", "n_frames": "--frames", "wire_diameter_mm": "--wire-diameter",
                        "detector_px": "--detector", "volume": "--volume", "motion_mm": "--motion", "dose": "--dose",
                        "plane_b_angles_deg": "--plane-b-angles-deg"}


def cli_main(args) -> int:
    import time

    t0 = time.perf_counter()
    try:
        opts = PhantomOptions(
            seed=args.seed, n_frames=args.frames, wire_diameter_mm=args.wire_diameter, distractors=args.distractors,
            detector_px=args.detector, volume=args.volume, background=not args.no_background,
            catheter=not args.no_catheter, motion_mm=args.motion, dose=args.dose,
            **({"biplane": True, "plane_b_angles_deg": getattr(args, "plane_b_angles_deg", None)}
               if getattr(args, "biplane", False) else {}),
        )
    except InputError as e:  # name the command-line option, not the dataclass field
        msg = str(e)
        for name, opt in _CLI_OPTION_OF_FIELD.items():
            msg = msg.replace(f"PhantomOptions.{name}:", f"{opt}:")
        raise InputError(msg) from None
    if getattr(args, "plane_b_angles_deg", None) is not None and not getattr(args, "biplane", False):
        raise InputError("--plane-b-angles-deg: needs --biplane")
    out = io.require_empty_folder(args.out)
    case = simulate(opts, make_ct=not getattr(args, "no_ct", False), progress=True)
    write_case(case, out)
    c, h = case.carm, case.heldout_carm
    vis = np.mean([v.mean() for v in case.wire_visible])
    lines = [
        f"phantom seed {opts.seed} -> {out}  ({time.perf_counter() - t0:.1f} s)",
        f"  tree: {case.tree.n_points} points, {len(case.tree.branches)} branches, "
        f"{case.tree.total_length_mm:.0f} mm, radius {case.tree.radius_mm.min():.2f}-{case.tree.radius_mm.max():.2f} mm",
    ]
    if case.volume is not None:
        v = case.volume
        lines.append(f"  CT: {v.shape_zyx[::-1]} voxels (x,y,z), spacing {tuple(round(s, 3) for s in v.spacing_mm)} mm, "
                     f"distractors {'yes' if opts.distractors else 'no'}")
    lines += [
        f"  main view: {c.primary_deg:+.1f} / {c.secondary_deg:+.1f} deg, SID {c.sid_mm:.0f}, SOD {c.sod_mm:.0f}, "
        f"pixel {c.pixel_mm:.3f} mm, {c.cols}x{c.rows}",
        (f"  plane B (roadmap_b.dcm, frames_b.dcm): {h.primary_deg:+.1f} / {h.secondary_deg:+.1f} deg, "
         f"SID {h.sid_mm:.0f}, SOD {h.sod_mm:.0f}" if opts.biplane else
         f"  held-out view: {h.primary_deg:+.1f} / {h.secondary_deg:+.1f} deg"),
        f"  wire: {case.wire_diameter_mm:.2f} mm, {len(case.frames)} frames, "
        f"{len(case.wire_lps_mm[0])}-{len(case.wire_lps_mm[-1])} points, {100 * vis:.0f}% visible",
    ]
    print("\n".join(lines))
    return 0
