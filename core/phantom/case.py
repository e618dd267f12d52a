"""One simulated case: what to simulate (:class:`PhantomOptions`), :func:`simulate`, and the
:class:`PhantomCase` it returns with its ground truth.

Everything is procedural and reproducible from one integer seed, each stage drawing from its own
random stream (:func:`_rngs`): the anatomy (``anatomy``), the CTA (``ct``), the pose, views and
images (``xray``) and the patient's motion (``motion``).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

import numpy as np
from guidewire3d.errors import InputError
from guidewire3d.geometry import CArm, Pose
from guidewire3d.io import Volume
from guidewire3d.phantom.anatomy import (
    WIRE_DIAMETERS_MM,
    WIRE_MARGIN_MM,
    VolumeSize,
    _choose_path,
    _make_tree,
    _sample_grid,
    _wire_shape,
)
from guidewire3d.phantom.ct import _distractors, _lumen_depth_grid, _synth_ct
from guidewire3d.phantom.motion import _contract, _frame_pose, _patient_motion
from guidewire3d.phantom.xray import (
    _accumulate_segments,
    _background_att,
    _block_mean,
    _expose,
    _gain_field,
    _mitre_chains,
    _psf_sigma_px,
    _sample_pose,
    _sample_views,
    _tree_chains,
    _wire_mask,
    biplane_plane_b,
    render_tube_line_integral,
)
from guidewire3d.vesseltree import VesselTree

__all__ = ["PhantomOptions", "PhantomCase", "simulate"]


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
    # physiological motion (see ``motion._physiological_motion``): breathing, peak-to-peak mostly
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
    """A simulated case with its ground truth (see ``guidewire3d.phantom`` and its modules for the model)."""

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


# ======================================================================================
# random streams
# ======================================================================================
_STAGES = ("grid", "tree", "pose", "wire", "ct", "distractor", "xa", "background")


def _rngs(seed: int) -> dict[str, np.random.Generator]:
    """Independent generators per stage, so that e.g. ``make_ct=False`` changes nothing else."""
    ss = np.random.SeedSequence([int(seed), 0x6A3D_2024])
    return {name: np.random.default_rng(s) for name, s in zip(_STAGES, ss.spawn(len(_STAGES)))}


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
    motion, motion_rot, motion_centre, cardiac = _patient_motion(options, rw, tree, T)
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
