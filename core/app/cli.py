"""Command line: ``guidewire3d {demo,phantom,reconstruct,vessels,segment,view,live,bench,batch,listen}``.

Bad input prints one line (``guidewire3d: error: ...``) and exits with status 2; ``--verbose``
shows the traceback instead.
"""
from __future__ import annotations

import argparse
import sys
import traceback

from guidewire3d.errors import Guidewire3DError
from guidewire3d.methods import ReconMethod, SegMethod, choices

EXIT_BAD_INPUT = 2
# the choices of --method and --segmenter (guidewire3d.methods imports nothing heavy)
RECON_METHODS = choices(ReconMethod)
SEGMENTERS = choices(SegMethod)


class _UsageError(Exception):
    """A command-line usage error (argparse's), printed as one line like every other error."""


class _Parser(argparse.ArgumentParser):
    """argparse, with a usage error raised (one line, exit 2 from ``main``) instead of printing the
    usage block and exiting."""

    def error(self, message):
        raise _UsageError(f"{message} (see '{self.prog} --help')")


def _parse_xyz(text: str) -> tuple[float, float, float]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected x,y,z in mm, got {text!r}") from None
    if len(vals) != 3:
        raise argparse.ArgumentTypeError(f"expected x,y,z in mm, got {text!r}")
    return vals


def _add_access_option(p: argparse.ArgumentParser, *, note: str = "") -> None:
    """``--access-lps``: where the wire enters the vessels (``guidewire3d.vesseltree.rooted_at_access``);
    ``note``: what the option means for this command, added to its help."""
    p.add_argument("--access-lps", type=_parse_xyz, default=None, metavar="X,Y,Z",
                   help="where the wire enters the vessels, in LPS mm (the sheath tip, or a femoral or radial puncture "
                        "within 150 mm of the CTA's vessels): the vessel tree is rooted at its point nearest to it. "
                        "The reconstruction assumes the wire advances from the root: by default the lower end of the "
                        "tree's aorta, where a transfemoral wire enters (a tree without an aorta: its widest end, a "
                        "coronary ostium); give this for transradial wires and any other entry. Write "
                        "--access-lps=X,Y,Z when X is negative" + (f". {note}" if note else ""))


def _add_geometry_overrides(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("C-arm geometry overrides (replace or supply XA tags)")
    g.add_argument("--sid", type=float, metavar="MM", help="DistanceSourceToDetector (0018,1110)")
    g.add_argument("--sod", type=float, metavar="MM", help="DistanceSourceToPatient (0018,1111)")
    g.add_argument("--pixel", type=float, metavar="MM", help="ImagerPixelSpacing (0018,1164)")
    g.add_argument("--primary", type=float, metavar="DEG", help="PositionerPrimaryAngle (0018,1510), LAO +")
    g.add_argument("--secondary", type=float, metavar="DEG", help="PositionerSecondaryAngle (0018,1511), CRA +")


# --- handlers of reconstruct, demo and bench -----------------------------------------------
# The stages are imported when a command runs, so that `--help` and the other commands start fast.
def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr)


def _viewer_screenshot(out_dir, path):
    """``screenshot.png`` of an output folder, rendered offscreen by the viewer's own scene code."""
    from guidewire3d.viewer.app import render_outdir_screenshot

    return render_outdir_screenshot(out_dir, path)


def _plan_screenshot(folder, path):
    """``screenshot.png`` of a vessel plan (``guidewire3d vessels``), rendered offscreen by the viewer's scene code."""
    from guidewire3d.viewer.plan_scene import render_plan_screenshot

    return render_plan_screenshot(folder, path)


def _run_reconstruct(args) -> int:
    from guidewire3d.app import pipeline
    from guidewire3d.registration import Verdict

    # biplane (issue 23): two --roadmap and two --frames (plane A, then plane B); one of each is one view
    n_road, n_frames = len(args.roadmap), len(args.frames)
    if n_road == 2 and n_frames == 2:
        return _run_reconstruct_biplane(args)
    if n_road != 1 or n_frames != 1:
        raise _UsageError(f"--roadmap and --frames: give one of each (one view) or two of each (biplane: plane A, "
                          f"then plane B), got {n_road} and {n_frames} (see 'guidewire3d reconstruct --help')")
    args.roadmap, args.frames = args.roadmap[0], args.frames[0]
    result = pipeline.run_to_outdir(
        args.cta, args.roadmap, args.frames, args.out, series_uid=args.series_uid,
        overrides=pipeline.geometry_overrides(args), roadmap_frame=args.roadmap_frame, seeds_lps_mm=args.seed_lps,
        method=args.method, segmenter=args.segmenter, force=args.force, images=not args.no_images,
        progress=True, track_motion=args.track_motion, access_lps_mm=args.access_lps, log=_stderr,
        screenshot=_viewer_screenshot,
    )
    n_ok = sum(1 for w in result.wires3d if w.success)
    n_unsure = sum(1 for fr in result.frame_results if fr.verdict.value == "uncertain")
    unsure = f" ({n_unsure} UNCERTAIN: see verdict_message in report.json)" if n_unsure else ""
    print(f"wrote {args.out}: registration {result.registration.verdict.label} "
          f"({result.registration.mean_residual_px:.2f} px), {n_ok}/{len(result.wires3d)} frames reconstructed{unsure}")
    if not result.reconstructed:
        why = ("is uncertain (the overlay fits, the roadmap does not settle the pose)"
               if result.registration.verdict is Verdict.UNCERTAIN else "failed")
        _stderr(f"guidewire3d: registration {why}; frames were not reconstructed. Correct it with "
                f"`guidewire3d view {args.out}` or rerun with --force.")
        return 1
    return 0


def _run_reconstruct_biplane(args) -> int:
    """``guidewire3d reconstruct`` with two ``--roadmap`` and two ``--frames`` (plane A, plane B)."""
    from guidewire3d.app import biplane, pipeline
    from guidewire3d.errors import InputError
    from guidewire3d.registration import Verdict

    given = [f"--{k.replace('_mm', '').replace('_deg', '')}" for k, v in pipeline.geometry_overrides(args).items()
             if v is not None]
    if given:
        raise InputError(f"{', '.join(given)}: the C-arm overrides describe one view; with two --roadmap each plane's "
                         "own positioner tags are required")
    result = biplane.run_to_outdir(args.cta, args.roadmap, args.frames, args.out, series_uid=args.series_uid,
                           roadmap_frame=args.roadmap_frame, seeds_lps_mm=args.seed_lps, method=args.method,
                           segmenter=args.segmenter, force=args.force, images=not args.no_images, progress=True,
                           access_lps_mm=args.access_lps, track_motion=bool(getattr(args, "track_motion", False)),
                           log=_stderr, screenshot=_viewer_screenshot)
    reg = result.registration.result
    n_ok = sum(1 for p in result.pairs if p)
    n_two = sum(1 for p in result.pairs if p.views == "AB")
    n_unsure = sum(1 for p in result.pairs if p.result.verdict.value == "uncertain")
    unsure = f" ({n_unsure} UNCERTAIN: see verdict_message in report.json)" if n_unsure else ""
    res = ", ".join(f"{v.plane} {v.mean_residual_px:.2f} px" for v in result.registration.views)
    motion = biplane.motion_summary(result.pairs)
    tracked = (f"; motion tracked in {motion['tracked_pairs']} pairs, {motion['planes']['AB']} from both planes, "
               f"{motion['verdicts']['ok']} ok" if motion is not None else "")
    print(f"wrote {args.out}: biplane registration {reg.verdict.label} ({res}), {n_ok}/{len(result.pairs)} frame pairs "
          f"reconstructed, {n_two} from both planes{unsure}{tracked}")
    if not result.plane_a.reconstructed:
        why = ("is uncertain (the overlays fit, the roadmaps do not settle the pose)"
               if reg.verdict is Verdict.UNCERTAIN else "failed")
        print(f"guidewire3d: biplane registration {why}; frames were not reconstructed. Rerun with --force to "
              "reconstruct anyway.", file=sys.stderr)
        return 1
    return 0


def _run_demo(args) -> int:
    from guidewire3d.app import bench
    from guidewire3d.errors import InputError

    if args.seed is not None and args.seed < 0:
        raise InputError(f"--seed {args.seed}: expected a non-negative integer")
    return bench.run_demo(out=args.out, seed=args.seed, screenshot=_viewer_screenshot)


def _run_bench(args) -> int:
    from guidewire3d.app import bench

    return bench.run_bench(n_cases=args.cases, out=args.out)


# --- subcommands ----------------------------------------------------------------------
def _add_phantom_parser(sub, full: bool = True) -> None:
    p = sub.add_parser("phantom", help="write a simulated case (DICOM CT + XA + truth.json)",
                       description="Write a simulated case with ground truth: DICOM CT series, XA roadmap and "
                                   "live frames, a held-out second view, and truth.json.")
    if full:
        from guidewire3d import phantom

        phantom.add_cli_options(p)
        p.set_defaults(func=phantom.cli_main)


def _add_reconstruct_parser(sub) -> None:
    p = sub.add_parser("reconstruct", help="run the whole chain on a CTA and XA files",
                       description="CTA vessels -> 2D analysis -> registration -> 3D wire per frame; writes "
                                   "report.json, VTP/STL, screenshots into --out. Biplane: give --roadmap and --frames "
                                   "twice (plane A, then plane B; each with its own positioner tags): one registration "
                                   "explains both roadmaps and each frame pair's wire is triangulated (README, Biplane).")
    p.add_argument("--cta", required=True, help="CTA DICOM series folder, or NIfTI/NRRD/MHA file")
    p.add_argument("--roadmap", required=True, action="append",
                   help="XA DICOM with the contrast roadmap; give it twice for a biplane (plane A, then plane B)")
    p.add_argument("--frames", required=True, action="append",
                   help="XA DICOM with the live frames (may be the roadmap file); twice for a biplane, in the order "
                        "of --roadmap (pairs matched by FrameTime, else by index)")
    p.add_argument("--out", required=True, help="output folder (created; must be empty or absent)")
    p.add_argument("--roadmap-frame", type=int, default=None, metavar="K",
                   help="frame of --roadmap to use (default: the most contrast-filled)")
    p.add_argument("--seed-lps", type=_parse_xyz, action="append", default=None, metavar="X,Y,Z",
                   help="seed point in LPS mm inside the vessels (repeatable; write --seed-lps=X,Y,Z when X is negative)")
    p.add_argument("--series-uid", default=None, help="SeriesInstanceUID to read from the CTA folder")
    p.add_argument("--method", default="vessel", choices=RECON_METHODS,
                   help="3D reconstruction: vessel (default: depth from the CTA vessel tree), paper (the paper's "
                        "closed-form depth, for comparison), bspline (baseline)")
    p.add_argument("--segmenter", default="unet", choices=SEGMENTERS,
                   help="guidewire segmentation: unet (default) or ridge (classical, no network)")
    p.add_argument("--force", action="store_true", help="reconstruct even if the registration failed")
    p.add_argument("--track-motion", action="store_true",
                   help="follow breathing / heartbeat: update the pose in each frame from its wire; biplane: in each "
                        "frame pair from both planes' wires (see README, Motion)")
    p.add_argument("--no-images", action="store_true", help="skip screenshot/overlay/metrics PNGs")
    _add_access_option(p)
    _add_geometry_overrides(p)

    p.set_defaults(func=_run_reconstruct)


def _add_demo_parser(sub) -> None:
    p = sub.add_parser("demo", help="generate the default phantom case and reconstruct it",
                       description="Generate (or reuse) the default simulated case, run reconstruct on it, "
                                   "and print the errors against the simulator's ground truth.")
    p.add_argument("--out", default="guidewire3d-demo", help="output folder (default: ./guidewire3d-demo)")
    p.add_argument("--seed", type=int, default=None, help="phantom seed (default: the fixed demo seed)")

    p.set_defaults(func=_run_demo)


def _add_view_parser(sub) -> None:
    p = sub.add_parser("view", help="desktop viewer on an output folder or on inputs",
                       description="Open the pyvista viewer on a reconstruct output folder "
                                   "(or on --cta/--roadmap/--frames), or on a vessel plan written by "
                                   "`guidewire3d vessels`, or render a screenshot offscreen.")
    p.add_argument("out_dir", nargs="?", help="a folder written by reconstruct/demo/vessels; with --cta/--roadmap/"
                                              "--frames, the folder their run writes (default: a new temporary folder)")
    p.add_argument("--cta")
    p.add_argument("--roadmap")
    p.add_argument("--frames")
    p.add_argument("--screenshot", metavar="PATH", help="render offscreen to PATH and exit")
    p.add_argument("--frame", type=int, default=0, metavar="K", help="frame to show (default 0)")
    p.add_argument("--size", default="1200x800", metavar="WxH", help="window/screenshot size")
    p.add_argument("--live", metavar="HOST:PORT", help="follow a `guidewire3d live` server (e.g. 127.0.0.1:18944): "
                   "the wire tube shows its newest wire (in OUT_DIR's scene when given)")
    _add_access_option(p, note="With --cta/--roadmap/--frames only (the run before the viewer opens, as reconstruct "
                               "--access-lps); an existing OUT_DIR holds its tree rooted already (report.json 'access')")

    def run(args):
        from guidewire3d.viewer import app

        return app.cli_main(args)

    p.set_defaults(func=run)


def _add_bench_parser(sub) -> None:
    p = sub.add_parser("bench", help="benchmarks on simulated cases (the paper's tables with 3D errors)",
                       description="Run the stage and end-to-end benchmarks over N simulated cases and print "
                                   "the paper's Table I and II layouts; writes CSV and Markdown.")
    p.add_argument("--cases", type=int, default=10, help="number of simulated cases (default 10)")
    p.add_argument("--out", default="bench-results", help="folder for CSV/Markdown tables")

    p.set_defaults(func=_run_bench)


def _add_live_parser(sub, full: bool = True) -> None:
    p = sub.add_parser("live", help="stream: live frames in, the 3D wire out over OpenIGTLink (3D Slicer, robots)",
                       description="Set up once (--from OUT, or --cta/--roadmap), then reconstruct the newest live "
                                   "frame (OpenIGTLink IMAGE, --video, --watch or --replay) and send Guidewire "
                                   "(POLYDATA), GuidewireUncertainty and GuidewireStatus (STRING), GuidewireTip "
                                   "(TRANSFORM) to every OpenIGTLink client. Ctrl-C stops and prints a summary.")

    def run(args):
        from guidewire3d.app import stream

        return stream.cli_live(args)

    if full:
        from guidewire3d.app.stream import add_cli_options

        add_cli_options(p)
        _add_access_option(p)
        _add_geometry_overrides(p)
        p.set_defaults(func=run)


def _add_segment_parser(sub, full: bool = True) -> None:
    p = sub.add_parser("segment", help="2D analysis of angiograms / frames: vessel and guidewire masks, ordered wire",
                       description="Segment the vessels and the guidewire of XA DICOM files or PNG/TIFF/JPEG "
                                   "images (no C-arm geometry needed); writes <name>_vessels.png, "
                                   "<name>_wire.png and segment.json (the ordered wire) into --out.")
    if full:
        from guidewire3d.app import batch2d

        batch2d.add_cli_options(p)
        p.set_defaults(func=batch2d.cli_segment)


# --- batch and listen (issue 24): many studies on Dask, studies received over DICOM -------------
def _add_batch_parser(sub, full: bool = True) -> None:
    p = sub.add_parser("batch", help="reconstruct many studies (a CSV manifest or a DICOM tree) on a Dask cluster",
                       description="Run reconstruct on every study of MANIFEST, one Dask task per study (a local "
                                   "cluster of --workers processes, or --scheduler), into DIR/<study>/ as "
                                   "reconstruct writes it, and DIR/summary.csv. Failed studies are retried, then "
                                   "recorded; a rerun skips a finished study made with the same options and fails one made "
                                   "with others (remove its folder to reconstruct it). Exit 1 if a study failed.")
    if full:
        from guidewire3d.app import batch

        batch.add_cli_options(p)
        _add_access_option(p, note="Every study's, recorded in its report.json as reconstruct records it; a "
                                   "manifest's access_lps column overrides it per study (\"x,y,z\" quoted; none: the "
                                   "automatic root; empty: this point)")
        p.set_defaults(func=batch.cli_batch)


def _add_listen_parser(sub, full: bool = True) -> None:
    p = sub.add_parser("listen", help="DICOM C-STORE receiver: file incoming studies and reconstruct each one",
                       description="A DICOM storage SCP (pynetdicom) that files incoming instances under "
                                   "STORE/<study>/<series>/ and reconstructs a study into OUT/<study>/ once it has "
                                   "a CT series and XA runs and nothing new arrived for --quiet-seconds (or on "
                                   "SIGUSR1). Ctrl-C stops.")
    if full:
        from guidewire3d.app import dicomnet

        dicomnet.add_cli_options(p)
        _add_access_option(p, note="Every received study's, recorded in its report.json as reconstruct records it")
        p.set_defaults(func=dicomnet.cli_listen)


def _add_vessels_parser(sub) -> None:  # issue 17: the vessel tree alone, any angiographic volume
    p = sub.add_parser("vessels", help="vessel tree of a CTA, MRA or 3DRA alone (planning): centerline, surface, JSON",
                       description="Find the contrast lumen's intensity in the volume itself (HU CTA, MRA in any "
                                   "units, 3DRA), segment vessels of 0.5-16 mm radius and write centerline.vtp, "
                                   "vessels.stl, vessels.vtp and vessels.json (branches, lengths, radii, the "
                                   "estimated intensities) into --out. A volume without a plausible vessel tree is "
                                   "refused (exit 2) with the reason; --seed-lps picks the tree containing a point "
                                   "(seeds in separate structures: one tree each). screenshot.png shows the plan; "
                                   "`guidewire3d view OUT` opens it.")
    p.add_argument("--cta", required=True, help="the volume: a DICOM series folder (CT or MR), or a NIfTI/NRRD/MHA file "
                                                "(CTA in HU, MRA in any units, 3DRA)")
    p.add_argument("--out", required=True, help="output folder (created; must be empty or absent)")
    p.add_argument("--seed-lps", type=_parse_xyz, action="append", default=None, metavar="X,Y,Z",
                   help="a point in LPS mm inside a vessel lumen: the result is the connected tree containing it "
                        "(repeatable; the tree is rooted at its aorta's lower end, or without an aorta at its end "
                        "nearest the first seed along its widest lumens; write --seed-lps=X,Y,Z when X is negative)")
    p.add_argument("--series-uid", default=None, help="SeriesInstanceUID to read from a DICOM folder")
    p.add_argument("--no-screenshot", action="store_true", help="do not render screenshot.png (offscreen VTK)")
    _add_access_option(p)

    def run(args):
        from guidewire3d.app import vesselplan

        return vesselplan.cli_main(args, screenshot=None if args.no_screenshot else _plan_screenshot)

    p.set_defaults(func=run)


COMMANDS = ("demo", "phantom", "reconstruct", "vessels", "segment", "view", "live", "bench", "batch", "listen")
# commands whose options come from their (heavy) module: only the command being run imports it
_HEAVY_OPTIONS = {"phantom", "live", "segment", "batch", "listen"}


def command_of(argv) -> str | None:
    """The subcommand named in ``argv`` (the first argument that is not an option), or None."""
    return next((a for a in argv if not a.startswith("-")), None)


def build_parser(command: str | None = "all") -> argparse.ArgumentParser:
    """The command line parser. ``command``: the subcommand whose options are built (``"all"``: every
    one); the others are listed by name and help only, so that ``guidewire3d --help`` and each command
    import only their own modules."""
    parser = _Parser(
        prog="guidewire3d",
        description="Real-time 3D guidewire reconstruction from a CTA and single-view DSA.",
    )
    parser.add_argument("--verbose", action="store_true", help="show tracebacks and debug messages")
    sub = parser.add_subparsers(dest="command", metavar="{" + ",".join(COMMANDS) + "}")
    sub.required = True
    _add_demo_parser(sub)
    full = {name: command == "all" or name == command for name in _HEAVY_OPTIONS}
    _add_phantom_parser(sub, full["phantom"])
    _add_reconstruct_parser(sub)
    _add_vessels_parser(sub)
    _add_segment_parser(sub, full["segment"])
    _add_view_parser(sub)
    _add_live_parser(sub, full["live"])
    _add_bench_parser(sub)
    _add_batch_parser(sub, full["batch"])
    _add_listen_parser(sub, full["listen"])
    return parser


def _close_progress_bars() -> None:
    """Close the tqdm bars an error interrupted, so that the error starts on a line of its own
    (a terminal's line is cleared by the bar; a log file gets a line break after the bar)."""
    std = sys.modules.get("tqdm.std")
    bars = list(getattr(getattr(std, "tqdm", None), "_instances", ()))
    for bar in bars:
        try:
            bar.close()
        except Exception:  # noqa: BLE001 - a bar that cannot be closed must not hide the error
            pass
    if bars and not sys.stderr.isatty():
        sys.stderr.write("\n")


def _error(msg: str) -> int:
    _close_progress_bars()
    sys.stdout.flush()
    print(f"guidewire3d: error: {' '.join(str(msg).split())}", file=sys.stderr)
    return EXIT_BAD_INPUT


def main(argv=None) -> int:
    """Run the command line; returns the exit status (2 for bad input, with one line on stderr)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(command_of(argv))
    try:
        args = parser.parse_args(argv)
    except _UsageError as e:
        return _error(str(e))
    try:
        rc = args.func(args)
        return int(rc or 0)
    except _UsageError as e:
        return _error(str(e))
    except Guidewire3DError as e:
        if args.verbose:
            _close_progress_bars()
            traceback.print_exc()
        return _error(str(e))
    except OSError as e:  # an I/O failure the readers and writers did not name (a safety net)
        if args.verbose:
            _close_progress_bars()
            traceback.print_exc()
        where = f"{e.filename}: " if e.filename else ""
        return _error(f"{where}{e.strerror or e}")
    except KeyboardInterrupt:
        _close_progress_bars()
        print("guidewire3d: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
