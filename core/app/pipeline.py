"""The stages chained: CTA vessels -> 2D roadmap -> registration -> 3D wire per frame.

Used by the CLI (``reconstruct``, ``demo``, ``bench``), the viewer and the Slicer plugin.
``run`` works on in-memory inputs and returns a ``PipelineResult``; ``run_to_outdir`` reads the
files, runs, and writes the OUT_DIR described in the README ("Output folder").
"""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from guidewire3d import io, registration
from guidewire3d.app import export
from guidewire3d.cta import vesselmodel
from guidewire3d.cta.segment import VesselOptions
from guidewire3d.cta.vessels3d import CTAVessels
from guidewire3d.errors import Guidewire3DError, InputError
from guidewire3d.geometry import CArm, Pose
from guidewire3d.live import session as live_engine
from guidewire3d.live.session import FrameResult
from guidewire3d.reconstruction import Wire3D
from guidewire3d.registration import RegistrationResult
from guidewire3d.vesseltree import access_record, check_access, rooted_at_access
from guidewire3d.xray.orderedwire import OrderedWire
from guidewire3d.xray.roadmap import Centerline2D, roadmap_centerline

__all__ = ["PipelineResult", "run", "run_to_outdir", "load_inputs", "choose_roadmap_frame", "check_roadmap_frame",
           "check_seeds", "rooted_vessels", "write_access_record", "input_files", "series_and_input_files"]


@dataclass(frozen=True, eq=False)
class PipelineResult:
    """Everything one run of the chain produced (:func:`run`), what :mod:`guidewire3d.app.export` writes.

    Frame-indexed lists (``wires2d``, ``wires3d``, ``frame_seconds``, ``frame_indices``,
    ``frame_results``) are aligned: entry ``k`` is the live frame ``frame_indices[k]`` of the frames
    run. When the registration was not trusted and not forced, ``reconstructed`` is False and the
    lists are empty.
    """

    volume: io.Volume  #: the CTA as read (LPS, mm)
    vessels: CTAVessels  #: its vessel mask, surface and centerline tree
    roadmap_image: np.ndarray  #: (H, W) the roadmap frame registered to
    roadmap_frame_index: int  #: its index in the roadmap run
    centerline2d: Centerline2D  #: the roadmap's 2D centerline
    carm: CArm  #: the roadmap's C-arm geometry
    frames_carm: CArm  #: the live frames' C-arm geometry
    registration: RegistrationResult  #: the pose, its covariance and verdict
    frames: np.ndarray  #: (K, H, W) the live frames processed
    wires2d: list[OrderedWire | None]  #: ordered 2D wire per frame (None when the frame failed early)
    wires3d: list[Wire3D]  #: 3D wire per frame (``success`` False when not reconstructed)
    timing: dict[str, float] = field(default_factory=dict)  #: seconds per stage
    frame_seconds: list[float] = field(default_factory=list)  #: per frame: segmentation + 2D wire + 3D
    frame_indices: list[int] = field(default_factory=list)  #: index of each frame in the frames run
    reconstructed: bool = True  #: False when a failed registration stopped the frames
    frame_results: list[FrameResult] = field(default_factory=list)  #: per frame: verdict, orientation, motion

    @property
    def pose(self) -> Pose:
        return self.registration.pose

    @property
    def tree(self):
        return self.vessels.tree


def _say(msg: str, log=None) -> None:
    if log is not None:
        log(msg)


VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".mpg", ".mpeg", ".wmv")


def read_xa_input(path, *, overrides=None) -> io.XARun:
    """An XA input: a DICOM file, or a PNG/TIFF folder or a video with a JSON geometry sidecar."""
    p = Path(path)
    if p.is_dir() or p.suffix.lower() in VIDEO_SUFFIXES:
        return io.read_image_sequence(p)
    return io.read_xa(p, overrides=overrides)


def _xa_input_files(path: Path) -> list[Path]:
    """The files :func:`read_xa_input` reads for ``path``: the DICOM file, a video and its sidecar,
    or every file of a frames folder (hidden files aside)."""
    if path.is_dir():
        return sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))
    if path.suffix.lower() in VIDEO_SUFFIXES:
        return [path] + [s for s in (path.with_suffix(path.suffix + ".json"), path.with_suffix(".json")) if s.is_file()]
    return [path]


def input_files(cta, roadmap, frames, *, series_uid=None) -> dict:
    """What ``report.json`` records of a run's input files (``inputs.files``): for ``cta``,
    ``roadmap`` and ``frames``, the ``{"name", "size", "sha256"}`` of each file read
    (:func:`io.file_fingerprints`; the CTA: the files of the series read, ``series_uid`` or the
    automatic choice, named relative to their folder). A run compares them to tell whether the files
    of a finished output changed since it was made.

    Raises
    ------
    InputError, DicomError
        An input is missing or unreadable, or the folder lacks the series.
    """
    return series_and_input_files(cta, roadmap, frames, series_uid=series_uid)[1]


def series_and_input_files(cta, roadmap, frames, *, series_uid=None, plane_b=None) -> tuple[str, dict]:
    """The series uid of the CTA's files ("" for a NIfTI/NRRD/MHA file) and :func:`input_files`; with ``plane_b``
    (a biplane run's ``(roadmap, frames)`` of plane B) also ``roadmap_b`` and ``frames_b``."""
    cta = Path(cta)
    uid, ct_files = io.volume_files(cta, series_uid=series_uid)
    out = {"cta": io.file_fingerprints(ct_files, root=cta if cta.is_dir() else None)}
    xa = [("roadmap", roadmap), ("frames", frames)]
    if plane_b is not None:
        xa += [("roadmap_b", plane_b[0]), ("frames_b", plane_b[1])]
    for role, path in xa:
        path = Path(path)
        out[role] = io.file_fingerprints(_xa_input_files(path), root=path if path.is_dir() else None)
    return uid, out


def load_inputs(cta, roadmap, frames, *, series_uid=None, overrides=None, log=None):
    """Read and validate every input before anything is computed or written.

    The XA files are read first (they are quick to check), then the CTA.
    """
    overrides = io.check_geometry_overrides(overrides)
    road = read_xa_input(roadmap, overrides=overrides)
    same = Path(frames).resolve() == Path(roadmap).resolve()
    live = road if same else read_xa_input(frames, overrides=overrides)
    vol = io.read_volume(cta, series_uid=series_uid, log=log)
    return vol, road, live


# a roadmap frame whose neighbouring pixels correlate less than this is noise, not an image: measured
# (lag-1 correlation at half resolution) 0.80-0.98 on simulated roadmaps (seeds 0-7, dose 1 and 0.1),
# 0.70-0.99 on the 40 shared real angiograms, 0.14-0.85 on simulated live frames, -0.01 on white noise
MIN_NEIGHBOUR_CORRELATION = 0.05


def check_roadmap_frame(run: io.XARun, k: int) -> None:
    """InputError naming the file and the frame if frame ``k`` of ``run`` cannot be a roadmap: a
    constant image (all zero, say), or noise without spatial structure."""
    f = np.asarray(run.frames[k], dtype=np.float64)
    lo, hi = float(f.min()), float(f.max())
    if hi - lo <= 1e-6 * max(abs(hi), 1.0):
        raise InputError(f"{run.source}: roadmap frame {k} has no contrast (every pixel is {lo:g}); "
                         "choose another with --roadmap-frame")
    sub = f[::2, ::2]
    c = sub - sub.mean()
    var = float(np.mean(c * c))
    corr = min(float(np.mean(c[:, 1:] * c[:, :-1])), float(np.mean(c[1:] * c[:-1]))) / var
    if corr < MIN_NEIGHBOUR_CORRELATION:
        raise InputError(f"{run.source}: roadmap frame {k} looks like noise (neighbouring pixels correlate "
                         f"{corr:.2f}, an angiogram > 0.5); choose another with --roadmap-frame")


def choose_roadmap_frame(run: io.XARun, roadmap_frame: int | None = None) -> int:
    """The frame of ``run`` to use as the roadmap: the given one, else the most contrast-filled.

    Contrast fill is measured as the fraction of pixels much darker than the frame's median
    (vessels attenuate), a cheap and monotone proxy for opacified vessel area. The frame is
    checked with :func:`check_roadmap_frame`.
    """
    n = run.n_frames
    if roadmap_frame is not None:
        if not 0 <= roadmap_frame < n:
            raise InputError(f"{run.source}: --roadmap-frame {roadmap_frame} out of range (file has {n} frames, "
                             f"0..{n - 1})")
        k = int(roadmap_frame)
    elif n == 1:
        k = 0
    else:
        scores = []
        for f in run.frames:
            sub = f[::4, ::4]
            med = float(np.median(sub))
            mad = float(np.median(np.abs(sub - med))) + 1e-6
            scores.append(float(np.mean(sub < med - 4.0 * mad)))
        k = int(np.argmax(scores))
    check_roadmap_frame(run, k)
    return k


def check_seeds(volume: io.Volume, seeds_lps_mm, *, option: str = "--seed-lps") -> None:
    """InputError naming ``option`` if a seed point lies outside the CTA, or (a CT in HU) has no
    contrast-filled voxel (``VesselOptions.lumen_min_hu``) within ``VesselOptions.seed_radius_mm``:
    cheap checks, done before the vessel stage (which checks a seed in a volume not in HU against its
    own intensity model)."""
    if seeds_lps_mm is None:
        return
    opt = VesselOptions()
    seeds = np.asarray(seeds_lps_mm, dtype=float).reshape(-1, 3)
    sp_zyx = np.asarray(volume.spacing_mm)[::-1]
    r_vox = np.ceil(opt.seed_radius_mm / sp_zyx).astype(int)
    hu = vesselmodel.looks_like_hu(volume)
    for s in seeds:
        label = f"{option}={','.join(f'{v:g}' for v in s)}"
        if not np.all(np.isfinite(s)):
            raise InputError(f"{label}: not a finite point")
        idx = volume.lps_to_index_zyx(s[None])[0]
        shape = np.array(volume.shape_zyx)
        if np.any(idx < -0.5) or np.any(idx > shape - 0.5):
            lo, hi = volume.bounds_lps_mm
            raise InputError(f"{label}: outside the CTA {volume.source} (LPS bounds "
                             f"{np.round(lo, 1).tolist()} .. {np.round(hi, 1).tolist()} mm)")
        if not hu:  # not in HU: the vessel stage's intensity model checks the seed (extract_vessels_auto)
            continue
        c = np.rint(idx).astype(int)
        lo_i, hi_i = np.maximum(c - r_vox, 0), np.minimum(c + r_vox + 1, shape)
        win = volume.array_zyx[lo_i[0]:hi_i[0], lo_i[1]:hi_i[1], lo_i[2]:hi_i[2]]
        if float(win.max()) < opt.lumen_min_hu:
            raise InputError(f"{label}: not inside a vessel of {volume.source} (no voxel of "
                             f"{opt.lumen_min_hu:g} HU or more within {opt.seed_radius_mm:g} mm; the brightest is "
                             f"{float(win.max()):.0f} HU)")


def run(volume: io.Volume, roadmap: io.XARun, frames: io.XARun, *, roadmap_frame: int | None = None,
        seeds_lps_mm=None, method: str = "vessel", segmenter: str = "unet", force: bool = False,
        progress: bool = False, pose: Pose | None = None, track_motion: bool = False, access_lps_mm=None,
        log=None) -> PipelineResult:
    """Run the whole chain on in-memory inputs.

    Parameters
    ----------
    volume : io.Volume
        The CTA in HU.
    roadmap, frames : io.XARun
        The contrast roadmap run and the live frames (may be the same run).
    pose : Pose, optional
        A pose to use instead of registering (e.g. a user-corrected one); it is refined by LM only.
    force : bool
        Reconstruct even when the registration reports failure.
    track_motion : bool
        Update the pose in every live frame from its wire (``motion.MotionTracker``, the
        registration as its prior) and reconstruct the frame in it.
    access_lps_mm : (3,) array_like of float, optional
        Where the wire enters the vessels (LPS mm: the puncture or the sheath tip): the tree is rooted
        at its point nearest to it (:func:`guidewire3d.vesseltree.rooted_at_access`), since the engine
        assumes the wire advances from the root. Default: the tree's own root (the lower end of its aorta,
        where a transfemoral wire enters: :func:`guidewire3d.vesseltree.rooted_at_caudal_end`; without an
        aorta its widest end).
    """
    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    vessels = vesselmodel.extract_vessels_any_units(volume, seeds_lps_mm=seeds_lps_mm, progress=progress, log=log)
    timing["cta_vessels"] = time.perf_counter() - t0
    vessels = rooted_vessels(vessels, access_lps_mm, log=log)
    tree = vessels.tree

    t0 = time.perf_counter()
    k, road_img, cl2d = roadmap_centerline_of(roadmap, tree, roadmap_frame)
    timing["roadmap_2d"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if pose is None:
        reg = registration.register(tree, cl2d.points_uv_px, roadmap.carm, centerline_radius_px=cl2d.radius_px)
    else:
        reg = registration.refine(tree, cl2d.points_uv_px, roadmap.carm, pose, centerline_radius_px=cl2d.radius_px)
    timing["registration"] = time.perf_counter() - t0
    _say(f"registration: {reg.verdict.label} ({reg.message}); "
         f"residual {reg.mean_residual_px:.2f} px, {reg.iterations} iterations", log)

    live = np.asarray(frames.frames)
    if live is roadmap.frames or frames is roadmap:
        frame_ids = [i for i in range(frames.n_frames) if i != k] or [k]
    else:
        frame_ids = list(range(frames.n_frames))
    wires2d, wires3d = [], []
    if not reg.success and not force:
        timing["frames"] = 0.0
        return PipelineResult(volume, vessels, road_img, k, cl2d, roadmap.carm, frames.carm, reg,
                              live[frame_ids], wires2d, wires3d, timing, [], frame_ids, reconstructed=False)

    session = live_engine.Session(tree, frames.carm, reg.pose, registration_covariance=reg.covariance_6x6,
                                  segmenter=segmenter, method=method, track_motion=track_motion)
    session.warm_up(live[frame_ids[0]])  # inference session, first-call compilation: not timed
    frame_seconds, frame_results = [], []
    t_frames = time.perf_counter()
    stream = session.run(live[frame_ids])
    if progress:
        from tqdm import tqdm

        stream = tqdm(stream, total=len(frame_ids), desc="frames", unit="frame", file=sys.stderr, leave=False)
    for fr in stream:
        frame_results.append(fr)
        wires2d.append(fr.wire2d)
        wires3d.append(fr.wire3d)
        frame_seconds.append(fr.seconds)
    timing["frames"] = time.perf_counter() - t_frames
    return PipelineResult(volume, vessels, road_img, k, cl2d, roadmap.carm, frames.carm, reg,
                          live[frame_ids], wires2d, wires3d, timing, frame_seconds, frame_ids,
                          frame_results=frame_results)


def rooted_vessels(vessels: CTAVessels, access_lps_mm, *, log=None) -> CTAVessels:
    """``vessels`` with its tree rooted at the access point (:func:`~guidewire3d.vesseltree.rooted_at_access`);
    ``vessels`` itself when ``access_lps_mm`` is None."""
    if access_lps_mm is None:
        return vessels
    tree = rooted_at_access(vessels.tree, access_lps_mm)
    rec = access_record(tree, access_lps_mm)
    _say(f"access point {rec['access_lps_mm']}: the vessel tree is rooted at its point {rec['root_lps_mm']} "
         f"({rec['distance_mm']:.1f} mm from it)", log)
    return dataclasses.replace(vessels, tree=tree)


def write_access_record(out_dir, tree, access_lps_mm) -> None:
    """Add ``"access"`` (:func:`~guidewire3d.vesseltree.access_record`) to ``out_dir/report.json``;
    nothing when ``access_lps_mm`` is None (the report stays as it was)."""
    if access_lps_mm is None:
        return
    path = Path(out_dir) / "report.json"
    rep = json.loads(path.read_text())
    rep["access"] = access_record(tree, access_lps_mm)
    io.atomic_write_text(path, json.dumps(rep, indent=1))


def roadmap_centerline_of(roadmap: io.XARun, tree, roadmap_frame=None):
    """``(k, image, Centerline2D)``: the roadmap frame used (:func:`choose_roadmap_frame`) and its 2D
    centerline, its vesselness scales bounded by the widest CTA vessel in roadmap pixels."""
    k = choose_roadmap_frame(roadmap, roadmap_frame)
    image = np.asarray(roadmap.frames[k])
    max_radius_px = float(tree.radius_mm.max()) / roadmap.carm.pixel_at_iso_mm * 1.5
    return k, image, roadmap_centerline(image, max_radius_px=max_radius_px)


def geometry_overrides(args) -> dict:
    """The C-arm overrides of a parsed command line (``--sid --sod --pixel --primary --secondary``;
    absent or ``None``: the DICOM tags' values), as :func:`load_inputs` takes them."""
    return {
        "sid_mm": getattr(args, "sid", None),
        "sod_mm": getattr(args, "sod", None),
        "pixel_mm": getattr(args, "pixel", None),
        "primary_deg": getattr(args, "primary", None),
        "secondary_deg": getattr(args, "secondary", None),
    }


MIN_FREE_MB = 32  # refuse to start with less free space where --out goes (4 frames take 3 MB, images 5 MB more)


def run_to_outdir(cta, roadmap, frames, out_dir, *, series_uid=None, overrides=None, roadmap_frame=None,
                  seeds_lps_mm=None, method="vessel", segmenter="unet", force=False, images=True,
                  progress=True, replace=False, truth=None, track_motion=False, access_lps_mm=None, log=None,
                  screenshot=None) -> PipelineResult:
    """Read the files, run, and write the output folder atomically (a staging folder renamed at the end).

    Everything that can be checked is checked before the heavy work: the output location
    (writable, empty, not being written by another run), every input file, the roadmap frame and
    the seed points. ``replace`` lets a previous output (a folder with ``report.json``) be replaced.
    While the run works its staging folder holds ``out_dir`` (``io.staged_folder``): a second run
    into the same folder is refused. ``screenshot(out_dir, png_path)``, when given (the front ends
    pass the viewer's offscreen renderer), writes ``screenshot.png`` with the other images.
    ``access_lps_mm`` (see :func:`run`): the folder holds the rooted tree, and ``report.json`` the access
    point and the root chosen for it (``"access"``).
    """
    out_dir = Path(out_dir)
    replace = bool(replace and (out_dir / "report.json").is_file())
    io.require_empty_folder(out_dir, replace=replace, min_free_mb=MIN_FREE_MB)
    t0 = time.perf_counter()
    try:  # before the files are read: one that changes meanwhile looks changed to a later run, never the same
        files_uid, files = series_and_input_files(cta, roadmap, frames, series_uid=series_uid)
    except Guidewire3DError:
        files_uid, files = None, None  # load_inputs names the bad input
    vol, road, live = load_inputs(cta, roadmap, frames, series_uid=series_uid, overrides=overrides, log=log)
    if files_uid != vol.series_uid:  # the folder changed between the two reads
        files = input_files(cta, roadmap, frames, series_uid=vol.series_uid or None)
    roadmap_frame = choose_roadmap_frame(road, roadmap_frame)
    check_seeds(vol, seeds_lps_mm)
    if access_lps_mm is not None:
        access_lps_mm = check_access(access_lps_mm, bounds_lps_mm=vol.bounds_lps_mm)
    t_load = time.perf_counter() - t0
    with io.staged_folder(out_dir, replace=replace) as staging:
        result = run(vol, road, live, roadmap_frame=roadmap_frame, seeds_lps_mm=seeds_lps_mm, method=method,
                     segmenter=segmenter, force=force, progress=progress, track_motion=track_motion,
                     access_lps_mm=access_lps_mm, log=log)
        result.timing["load_inputs"] = t_load
        inputs = {
            "cta": str(Path(cta).resolve()),
            "roadmap": str(Path(roadmap).resolve()),
            "frames": str(Path(frames).resolve()),
            "roadmap_frame": result.roadmap_frame_index,
            "series_uid": vol.series_uid,
            "method": str(getattr(method, "value", method)),
            "segmenter": str(getattr(segmenter, "value", segmenter)),
            "forced": bool(force),
            "track_motion": bool(track_motion),
        }
        if access_lps_mm is not None:
            inputs["access_lps_mm"] = [round(float(v), 3) for v in access_lps_mm]
        inputs["files"] = files

        def write(staging: Path) -> None:
            t0 = time.perf_counter()
            export.write_outdir(result, staging, inputs=inputs, images=images, truth=truth,
                                screenshot=screenshot)
            result.timing["export"] = time.perf_counter() - t0
            export.write_report(result, staging, inputs=inputs, truth=truth)  # again, with export timing
            write_access_record(staging, result.tree, access_lps_mm)

        io.write_into(out_dir, staging, write)
    return result
