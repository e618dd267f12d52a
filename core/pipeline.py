"""The stages chained: CTA vessels -> 2D roadmap -> registration -> 3D wire per frame.

Used by the CLI (``reconstruct``, ``demo``, ``bench``), the viewer and the Slicer plugin.
``run`` works on in-memory inputs and returns a ``PipelineResult``; ``run_to_outdir`` reads the
files, runs, and writes the OUT_DIR described in the README ("Output folder").
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from guidewire3d import io
from guidewire3d.errors import InputError
from guidewire3d.geometry import CArm, Pose

__all__ = ["PipelineResult", "run", "run_to_outdir", "load_inputs", "choose_roadmap_frame"]


@dataclass(frozen=True, eq=False)
class PipelineResult:
    volume: io.Volume
    vessels: object  # vessels3d.CTAVessels
    roadmap_image: np.ndarray
    roadmap_frame_index: int
    centerline2d: object  # image2d.Centerline2D
    carm: CArm
    frames_carm: CArm
    registration: object  # registration.RegistrationResult
    frames: np.ndarray
    wires2d: list
    wires3d: list
    timing: dict = field(default_factory=dict)
    frame_seconds: list = field(default_factory=list)  # per live frame: segmentation + 2D wire + 3D
    frame_indices: list = field(default_factory=list)  # index of each live frame in the frames run
    reconstructed: bool = True  # False when a failed registration stopped the frames

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


def load_inputs(cta, roadmap, frames, *, series_uid=None, overrides=None, log=None):
    """Read and validate every input before anything is computed or written."""
    vol = io.read_volume(cta, series_uid=series_uid, log=log)
    road = read_xa_input(roadmap, overrides=overrides)
    same = Path(frames).resolve() == Path(roadmap).resolve()
    live = road if same else read_xa_input(frames, overrides=overrides)
    return vol, road, live


def choose_roadmap_frame(run: io.XARun, roadmap_frame: int | None = None) -> int:
    """The frame of ``run`` to use as the roadmap: the given one, else the most contrast-filled.

    Contrast fill is measured as the fraction of pixels much darker than the frame's median
    (vessels attenuate), a cheap and monotone proxy for opacified vessel area.
    """
    n = run.n_frames
    if roadmap_frame is not None:
        if not 0 <= roadmap_frame < n:
            raise InputError(f"{run.source}: --roadmap-frame {roadmap_frame} out of range (file has {n} frames)")
        return int(roadmap_frame)
    if n == 1:
        return 0
    scores = []
    for f in run.frames:
        sub = f[::4, ::4]
        med = float(np.median(sub))
        mad = float(np.median(np.abs(sub - med))) + 1e-6
        scores.append(float(np.mean(sub < med - 4.0 * mad)))
    return int(np.argmax(scores))


def run(volume: io.Volume, roadmap: io.XARun, frames: io.XARun, *, roadmap_frame: int | None = None,
        seeds_lps_mm=None, method: str = "vessel", segmenter: str = "unet", force: bool = False,
        progress: bool = False, pose: Pose | None = None, log=None) -> PipelineResult:
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
    """
    from guidewire3d import image2d, reconstruction, registration, segmentation, vessels3d

    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    vessels = vessels3d.extract_vessels(volume, seeds_lps_mm=seeds_lps_mm, progress=progress)
    timing["cta_vessels"] = time.perf_counter() - t0
    tree = vessels.tree

    t0 = time.perf_counter()
    k = choose_roadmap_frame(roadmap, roadmap_frame)
    road_img = np.asarray(roadmap.frames[k])
    # the widest CTA vessel, in roadmap pixels at the isocentre, bounds the 2D vesselness scales
    max_radius_px = float(tree.radius_mm.max()) / roadmap.carm.pixel_at_iso_mm * 1.5
    cl2d = image2d.roadmap_centerline(road_img, max_radius_px=max_radius_px)
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

    seg = segmentation.GuidewireSegmenter(method=segmenter)
    tracker = reconstruction.WireTracker(reg.pose, frames.carm, tree, method=method,
                                         registration_covariance=reg.covariance_6x6)
    root_uv = frames.carm.project(tree.points_lps_mm[tree.root], reg.pose)
    seg.segment(live[frame_ids[0]])  # warm-up (inference session, first-call compilation), not timed
    seg.reset()
    frame_seconds = []
    t_frames = time.perf_counter()
    stream = iter_live(live[frame_ids], segmenter=seg, tracker=tracker, proximal_hint_uv=root_uv)
    if progress:
        from tqdm import tqdm

        stream = tqdm(stream, total=len(frame_ids), desc="frames", unit="frame", file=sys.stderr, leave=False)
    for ow, w3, seconds in stream:
        wires2d.append(ow)
        wires3d.append(w3)
        frame_seconds.append(seconds)
    timing["frames"] = time.perf_counter() - t_frames
    return PipelineResult(volume, vessels, road_img, k, cl2d, roadmap.carm, frames.carm, reg,
                          live[frame_ids], wires2d, wires3d, timing, frame_seconds, frame_ids)


def iter_live(frames, *, segmenter, tracker, proximal_hint_uv=None, pipelined: bool = False):
    """The live path: yield ``(ordered_wire, wire3d, seconds)`` for each frame, in order.

    Per frame: guidewire mask (``segmenter.segment``), ordered 2D wire, 3D wire (``tracker.update``).
    With ``pipelined`` the mask of frame t+1 is computed in a worker thread while frame t's 2D
    and 3D wire are computed (the segmenter's ROI tracking depends only on its own previous
    mask, so the order of results is unchanged). On the 2-core reference machine this gave no
    throughput gain (the 2D/3D half holds the GIL) and doubled the latency
    (``scripts/bench_live.py``), so it is off by default. ``seconds`` is each frame's latency,
    from its submission to its 3D wire.
    """
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    from guidewire3d import image2d
    from guidewire3d.reconstruction import Wire3D

    def finish(frame, mask, t0):
        ow = image2d.ordered_wire(mask, image=frame, proximal_hint_uv=proximal_hint_uv)
        w3 = tracker.update(ow.points_uv_px, image=frame) if ow else Wire3D.failed(f"2D wire not found: {ow.message}")
        return ow, w3, time.perf_counter() - t0

    if not pipelined:
        for frame in frames:
            t0 = time.perf_counter()
            yield finish(frame, segmenter.segment(frame), t0)
        return
    it = iter(frames)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="gw3d-seg") as pool:
        pending: deque = deque()

        def submit():
            frame = next(it, None)
            if frame is not None:
                pending.append((frame, time.perf_counter(), pool.submit(segmenter.segment, frame)))

        submit()
        submit()
        while pending:
            frame, t0, fut = pending.popleft()
            mask = fut.result()
            submit()
            yield finish(frame, mask, t0)


def run_to_outdir(cta, roadmap, frames, out_dir, *, series_uid=None, overrides=None, roadmap_frame=None,
                  seeds_lps_mm=None, method="vessel", segmenter="unet", force=False, images=True,
                  progress=True, replace=False, truth=None, log=None) -> PipelineResult:
    """Read the files, run, and write the output folder atomically (a staging folder renamed at the end)."""
    from guidewire3d import export

    out_dir = Path(out_dir)
    if not (replace and (out_dir / "report.json").exists()):
        io.require_empty_folder(out_dir)
    t0 = time.perf_counter()
    vol, road, live = load_inputs(cta, roadmap, frames, series_uid=series_uid, overrides=overrides, log=log)
    t_load = time.perf_counter() - t0
    result = run(vol, road, live, roadmap_frame=roadmap_frame, seeds_lps_mm=seeds_lps_mm, method=method,
                 segmenter=segmenter, force=force, progress=progress, log=log)
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
    }

    def write(staging: Path) -> None:
        t0 = time.perf_counter()
        export.write_outdir(result, staging, inputs=inputs, images=images, truth=truth)
        result.timing["export"] = time.perf_counter() - t0
        export.write_report(result, staging, inputs=inputs, truth=truth)  # again, with export timing

    io.write_folder_atomically(out_dir, write)
    return result


# --------------------------------------------------------------------------------------
# CLI entry points
# --------------------------------------------------------------------------------------
def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr)


def cli_reconstruct(args) -> int:
    from guidewire3d.cli import geometry_overrides

    result = run_to_outdir(
        args.cta, args.roadmap, args.frames, args.out, series_uid=args.series_uid,
        overrides=geometry_overrides(args), roadmap_frame=args.roadmap_frame, seeds_lps_mm=args.seed_lps,
        method=args.method, segmenter=args.segmenter, force=args.force, images=not args.no_images,
        progress=True, log=_stderr,
    )
    n_ok = sum(1 for w in result.wires3d if w.success)
    print(f"wrote {args.out}: registration {result.registration.verdict.label} "
          f"({result.registration.mean_residual_px:.2f} px), {n_ok}/{len(result.wires3d)} frames reconstructed")
    if not result.reconstructed:
        from guidewire3d.registration import Verdict

        why = ("is uncertain (the overlay fits, the roadmap does not settle the pose)"
               if result.registration.verdict is Verdict.UNCERTAIN else "failed")
        _stderr(f"guidewire3d: registration {why}; frames were not reconstructed. Correct it with "
                f"`guidewire3d view {args.out}` or rerun with --force.")
        return 1
    return 0


def cli_demo(args) -> int:
    from guidewire3d import bench

    return bench.run_demo(out=args.out, seed=args.seed)


def cli_bench(args) -> int:
    from guidewire3d import bench

    return bench.run_bench(n_cases=args.cases, out=args.out)
