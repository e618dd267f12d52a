"""Live streaming: frames in from the C-arm, the 3D wire out over OpenIGTLink (``guidewire3d live``).

One process, three parts joined by a one-slot mailbox:

* a **frame source** (a thread, ``sources``): OpenIGTLink IMAGE messages that clients send to the
  server (PLUS, a frame grabber, 3D Slicer), a video file or device (OpenCV), a folder that frames
  appear in, or a DICOM XA file replayed at its frame rate. Each frame carries its source time stamp.
* the **processing loop** (the calling thread, :class:`LiveRunner`): takes the newest frame from
  the mailbox (``sources.LatestFrame``: a frame that a newer one replaced before it was processed
  is dropped and counted; nothing queues up), runs it through ``live.Session`` and publishes the
  result.
* the **OpenIGTLink server** (``igtl.IGTLServer``): every connected client gets the frame's
  messages (``igtl.frame_messages``: status, wire, uncertainty, tip).

This module holds the loop, the setup made once before it (:func:`setup_from_outdir`,
:func:`setup_from_inputs`) and the command (:func:`cli_live`).
"""
from __future__ import annotations

import gc
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from guidewire3d import io, reconstruction, registration
from guidewire3d.app import pipeline
from guidewire3d.app.igtl import DEFAULT_HOST, DEFAULT_PORT, IGTLServer, Space, frame_messages, pack
from guidewire3d.app.outdir import load_outdir
from guidewire3d.app.pipeline import geometry_overrides
from guidewire3d.app.sources import Frame, FolderSource, LatestFrame, ReplaySource, VideoSource, check_frame
from guidewire3d.cta import vessels3d
from guidewire3d.errors import GeometryError, InputError
from guidewire3d.geometry import CArm
from guidewire3d.live import session as live
from guidewire3d.registration import Verdict
from guidewire3d.xray.orderedwire import OrderedWire
from guidewire3d.xray.roadmap import roadmap_centerline

__all__ = ["LiveSetup", "LiveRunner", "LiveSummary", "setup_from_outdir", "setup_from_inputs", "warm_up",
           "add_cli_options", "cli_live"]

#: latencies kept for the summary (the last ones; about 11 min at 30 fps)
KEEP_LATENCIES = 20000


# --------------------------------------------------------------------------------------
# setup: the vessel tree and the registration, once
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class LiveSetup:
    """What a live session needs, made once.

    Attributes
    ----------
    tree : VesselTree
    frames_carm : CArm
        The live view (frames that come with no geometry of their own use it).
    pose : Pose
        ``T_iso_from_lps`` (a manual correction when there is one).
    covariance : (6, 6) ndarray or None
        The pose covariance (None for a hand-corrected pose, whose covariance is not known).
    description : str
    """

    tree: object
    frames_carm: object
    pose: object
    covariance: object
    description: str
    verdict: object = None  # registration.Verdict of the pose


def setup_from_outdir(out_dir, *, force: bool = False) -> LiveSetup:
    """The vessel tree and registration of a ``reconstruct`` output folder (a manual correction
    included: ``registration.json``'s ``pose``).

    Raises
    ------
    InputError
        Not an output folder, no ``registration_inputs.npz``, or an automatic registration that
        failed its checks (unless ``force``).
    """
    case = load_outdir(out_dir, load_images=False)
    if case.tree is None:
        raise InputError(f"{Path(out_dir) / 'registration_inputs.npz'}: missing (the vessel tree); "
                         "rerun reconstruct")
    try:
        verdict = Verdict(str(case.registration.get("verdict") or "ok"))
    except ValueError:
        verdict = Verdict.FAILED
    if case.pose_source == "automatic" and verdict is not Verdict.OK and not force:
        raise InputError(f"{out_dir}: the registration is {verdict.value} ({case.registration.get('message', '')}); "
                         f"correct it with `guidewire3d view {out_dir}` or give --force")
    cov = None
    if np.allclose(case.pose.matrix, case.automatic_pose.matrix):
        c = case.registration.get("covariance_6x6")
        c = np.asarray(c, float) if c is not None else None
        cov = c if c is not None and c.shape == (6, 6) and np.all(np.isfinite(c)) else None
    desc = (f"{out_dir}: {case.tree.n_points} centerline points, {case.pose_source} pose "
            f"(registration {verdict.value})")
    return LiveSetup(case.tree, case.frames_carm, case.pose, cov, desc, verdict)


def setup_from_inputs(cta, roadmap, *, roadmap_frame=None, seeds_lps_mm=None, series_uid=None, overrides=None,
                      force: bool = False, log=None) -> LiveSetup:
    """CTA vessels -> roadmap centerline -> registration, as ``reconstruct`` does it."""
    overrides = io.check_geometry_overrides(overrides)
    road = pipeline.read_xa_input(roadmap, overrides=overrides)
    vol = io.read_volume(cta, series_uid=series_uid, log=log)
    k = pipeline.choose_roadmap_frame(road, roadmap_frame)
    pipeline.check_seeds(vol, seeds_lps_mm)
    t0 = time.perf_counter()
    ves = vessels3d.extract_vessels(vol, seeds_lps_mm=seeds_lps_mm)
    tree = ves.tree
    cl = roadmap_centerline(np.asarray(road.frames[k]),
                            max_radius_px=float(tree.radius_mm.max()) / road.carm.pixel_at_iso_mm * 1.5)
    reg = registration.register(tree, cl.points_uv_px, road.carm, centerline_radius_px=cl.radius_px)
    if log is not None:
        log(f"registration: {reg.verdict.label} ({reg.message}); residual {reg.mean_residual_px:.2f} px "
            f"({time.perf_counter() - t0:.1f} s with the CTA vessels)")
    if not reg.success and not force:
        raise InputError(f"{roadmap}: the registration {reg.verdict.value} its checks ({reg.message}); run "
                         "`guidewire3d reconstruct` and correct it in the viewer, then `live --from OUT`, or give --force")
    return LiveSetup(tree, road.carm, reg.pose, reg.covariance_6x6,
                     f"{cta} + {roadmap} frame {k}: {tree.n_points} centerline points", reg.verdict)


def warm_up(session) -> None:
    """Load the network and run it once before the first live frame (a constant frame would not
    reach the network: the segmenter skips it), so the first frame does not pay for it; then
    collect and freeze the heap made so far (``gc.freeze``).

    Without the freeze, Python's full (generation 2) garbage collection walks every object of the
    setup (the vessel tree, the network, the libraries) now and then in the middle of a frame: it
    took 226 ms once in 240 frames of ``bench_live``'s sequence on the 2-core reference host, a frame
    of 4x the usual latency and the frames dropped behind it. Frozen objects are never collected
    by the cycle collector (they are freed as usual when nothing refers to them); this process is
    the live server's own, so nothing else is affected.
    """
    rng = np.random.default_rng(0)
    session.warm_up(rng.normal(1000.0, 50.0, session.carm.shape).astype(np.float32))
    gc.collect()
    gc.freeze()


# --------------------------------------------------------------------------------------
# the processing loop
# --------------------------------------------------------------------------------------
@dataclass
class LiveSummary:
    """What a live run did. ``frames_in = processed + dropped`` (+ one frame left in the mailbox)."""

    frames_in: int = 0
    processed: int = 0
    dropped: int = 0
    ok: int = 0
    uncertain: int = 0
    failed: int = 0
    connections: int = 0
    skipped_for_slow_clients: int = 0
    seconds: float = 0.0
    latency_processed_s: list = field(default_factory=list)  # source time stamp -> messages published
    latency_sent_s: list = field(default_factory=list)  # source time stamp -> first client's copy written

    @staticmethod
    def _pct(x, q):
        return 1000.0 * float(np.percentile(x, q)) if len(x) else float("nan")

    def line(self) -> str:
        lat, what = ((self.latency_sent_s, "source time stamp -> sent") if self.latency_sent_s
                     else (self.latency_processed_s, "source time stamp -> published, no client"))
        s = (f"{self.frames_in} frames in, {self.processed} processed ({self.ok} ok, {self.uncertain} uncertain, "
             f"{self.failed} failed), {self.dropped} dropped in {self.seconds:.1f} s")
        if len(lat):
            s += f"; latency ({what}) median {self._pct(lat, 50):.1f} ms, p99 {self._pct(lat, 99):.1f} ms"
        s += f"; {self.connections} client connection(s)"
        if self.skipped_for_slow_clients:
            s += f", {self.skipped_for_slow_clients} bundles skipped for slow clients"
        return s

    def to_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if not k.startswith("latency")}
        for k in ("latency_processed_s", "latency_sent_s"):
            x = getattr(self, k)
            d[k.replace("_s", "_ms")] = {"p50": self._pct(x, 50), "p99": self._pct(x, 99), "n": len(x)}
        return d


class LiveRunner:
    """The processing loop: newest frame -> ``live.Session`` -> messages to every client.

    Parameters
    ----------
    session : live.Session
    server : IGTLServer or None
        None: results only go to ``on_result``.
    mailbox : LatestFrame
    space : Space
    max_frames : int, optional
        Stop after this many processed frames.
    duration_s : float, optional
        Stop after this long.
    source : object, optional
        A source with a ``done`` event: the run stops once it is done and the mailbox is empty.
    on_result : callable, optional
        Called with each ``live.FrameResult`` (after its messages are offered).
    points : bool
        Also send ``GuidewirePoints`` (see :func:`frame_messages`).
    """

    def __init__(self, session, server, mailbox: LatestFrame, *, space: Space = Space.LPS, max_frames=None,
                 duration_s=None, source=None, on_result=None, points: bool = False):
        self.session, self.server, self.mailbox = session, server, mailbox
        self.space = Space(space)
        self.max_frames = None if max_frames is None else int(max_frames)
        self.duration_s = None if duration_s is None else float(duration_s)
        self.source = source
        self.on_result = on_result
        self.points = bool(points)
        self.summary = LiveSummary()
        self._lat_proc: deque = deque(maxlen=KEEP_LATENCIES)
        self._lat_sent: deque = deque(maxlen=KEEP_LATENCIES)
        self._lock = threading.Lock()

    def stats(self) -> dict:
        s = self.summary
        return {"frames_in": self.mailbox.n_in, "processed": s.processed, "dropped": self.mailbox.n_dropped,
                "failed": s.failed}

    @staticmethod
    def _bad_frame(index, frame: Frame, message: str):
        """The FAILED result of a frame that never reached the engine (wrong size, NaN, unreadable)."""
        msg = f"bad frame: {message}"
        return live.FrameResult(index, OrderedWire(points_uv_px=np.zeros((0, 2)), success=False, message=msg),
                                reconstruction.Wire3D.failed(msg), Verdict.FAILED, msg, None, 0.0, frame.timestamp)

    def process(self, frame: Frame):
        """Process one frame and publish its messages; returns the ``live.FrameResult``."""
        index = self.summary.processed
        img, why = check_frame(frame.image, self.session.carm.shape) if not frame.error else (None, frame.error)
        if img is None:
            result = self._bad_frame(index, frame, why)
        else:
            result = self.session.process(img, index=index, timestamp=frame.timestamp)
        s = self.summary
        s.processed += 1
        s.ok += result.verdict is Verdict.OK
        s.uncertain += result.verdict is Verdict.UNCERTAIN
        s.failed += result.verdict is Verdict.FAILED
        msgs = frame_messages(result, space=self.space, stats=dict(self.stats(), source=frame.source),
                              points=self.points)
        payload = pack(msgs)
        ts = frame.timestamp
        self._lat_proc.append(time.time() - ts)
        if self.server is not None:
            first = []

            def on_sent(t, _ts=ts):
                with self._lock:
                    if not first:
                        first.append(t)
                        self._lat_sent.append(t - _ts)

            self.server.broadcast(payload, on_sent=on_sent)
        if self.on_result is not None:
            self.on_result(result)
        return result

    def run(self, stop: threading.Event | None = None) -> LiveSummary:
        """Process frames until ``stop`` is set, ``max_frames`` or ``duration_s`` is reached, or the
        source is done; returns the summary."""
        stop = stop or threading.Event()
        t0 = time.monotonic()
        while not stop.is_set():
            if self.max_frames is not None and self.summary.processed >= self.max_frames:
                break
            left = None if self.duration_s is None else self.duration_s - (time.monotonic() - t0)
            if left is not None and left <= 0:
                break
            frame = self.mailbox.take(min(0.1, left) if left is not None else 0.1)
            if frame is None:
                if self.source is not None and self.source.done.is_set():
                    break
                continue
            self.process(frame)
        time.sleep(0.05)  # let the writers send the last bundle
        s = self.summary
        s.seconds = time.monotonic() - t0
        s.frames_in, s.dropped = self.mailbox.n_in, self.mailbox.n_dropped
        if self.server is not None:
            s.connections, s.skipped_for_slow_clients = self.server.n_connections, self.server.n_skipped
        with self._lock:
            s.latency_processed_s, s.latency_sent_s = list(self._lat_proc), list(self._lat_sent)
        return s


# --------------------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------------------
def add_cli_options(p) -> None:
    """The options of ``guidewire3d live``."""
    g = p.add_argument_group("setup (once): a previous output folder, or the inputs as for reconstruct")
    g.add_argument("--from", dest="from_out", metavar="OUT",
                   help="a folder written by reconstruct: its vessel tree and registration (manual correction included)")
    g.add_argument("--cta", help="CTA DICOM series folder, or NIfTI/NRRD/MHA file")
    g.add_argument("--roadmap", help="XA DICOM with the contrast roadmap (or a PNG/TIFF folder / video with geometry JSON)")
    g.add_argument("--roadmap-frame", type=int, default=None, metavar="K")
    g.add_argument("--series-uid", default=None)
    g.add_argument("--force", action="store_true", help="go live even if the registration failed its checks")
    s = p.add_argument_group("frame source (default: OpenIGTLink IMAGE messages sent to the server)")
    x = s.add_mutually_exclusive_group()
    x.add_argument("--video", metavar="PATH|DEVICE", help="a video file (paced at its frame rate) or a capture device "
                   "(0, /dev/video0) through OpenCV; geometry: <video>.json beside a file, or --geometry")
    x.add_argument("--watch", metavar="DIR", help="a folder that PNG/TIFF frames appear in (geometry.json in it, or --geometry)")
    x.add_argument("--replay", metavar="XA.dcm", help="replay a DICOM XA file at its frame rate (for demos)")
    s.add_argument("--fps", type=float, default=None, help="--replay rate (default: the file's FrameTime, else 15)")
    s.add_argument("--loop", action="store_true", help="--replay / --video file: start again at the end")
    s.add_argument("--geometry", metavar="JSON", help="C-arm geometry of the live frames (primary_deg, secondary_deg, "
                   "sid_mm, sod_mm, pixel_mm); default: the roadmap's, or the source's own")
    o = p.add_argument_group("output (OpenIGTLink server)")
    o.add_argument("--host", default=DEFAULT_HOST, help="interface to listen on (default 127.0.0.1: this machine only)")
    o.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"TCP port (default {DEFAULT_PORT})")
    o.add_argument("--space", default="lps", choices=[m.value for m in Space],
                   help="coordinates of the wire and tip messages: lps (default) or ras (for 3D Slicer)")
    o.add_argument("--points", action="store_true", help="also send the wire as a POINT message (GuidewirePoints), for "
                   "consumers without POLYDATA such as ros2_igtl_bridge")
    o.add_argument("--segmenter", default="unet", choices=("unet", "ridge"))
    o.add_argument("--track-motion", action="store_true", help="follow breathing and heartbeat: each frame's wire "
                   "updates the pose before it is reconstructed (as reconstruct --track-motion)")
    b = p.add_argument_group("bounds (default: run until Ctrl-C)")
    b.add_argument("--max-frames", type=int, default=None, metavar="N", help="stop after N processed frames")
    b.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")


def _geometry(path, shape):
    geo = io._read_sidecar(Path(path))
    geo.setdefault("shape", list(shape))
    try:
        return CArm.from_dict(geo)
    except GeometryError as e:
        raise GeometryError(f"{path}: {e}") from None
    except (TypeError, ValueError) as e:
        raise GeometryError(f"{path}: invalid geometry ({e})") from None


def _make_source(args, setup: LiveSetup):
    """(source or None for OpenIGTLink, the live frames' CArm)."""
    carm = _geometry(args.geometry, setup.frames_carm.shape) if args.geometry else setup.frames_carm
    if args.replay:
        run = io.read_xa(args.replay)
        src = ReplaySource(run, fps=args.fps, loop=args.loop)
        return src, (carm if args.geometry else run.carm)
    if args.video:
        v = Path(args.video)
        side = v.with_suffix(v.suffix + ".json") if v.exists() else None
        if side is not None and not side.exists():
            side = v.with_suffix(".json")
        if not args.geometry and side is not None and side.exists():
            carm = _geometry(side, carm.shape)
        return VideoSource(args.video, carm, loop=args.loop), carm
    if args.watch:
        side = Path(args.watch) / "geometry.json"
        if not args.geometry and side.exists():
            carm = _geometry(side, carm.shape)
        return FolderSource(args.watch, carm), carm
    return None, carm


def _check_args(args) -> None:
    if args.from_out and (args.cta or args.roadmap):
        raise InputError("live: give --from OUT, or --cta and --roadmap, not both")
    if not args.from_out and not (args.cta and args.roadmap):
        raise InputError("live: give --from OUT (a reconstruct output folder), or --cta and --roadmap")
    if args.max_frames is not None and args.max_frames < 1:
        raise InputError(f"--max-frames: expected a positive integer, got {args.max_frames}")
    if args.duration is not None and not args.duration > 0:
        raise InputError(f"--duration: expected a positive number of seconds, got {args.duration}")
    if not 0 <= args.port < 65536:
        raise InputError(f"--port: {args.port} out of range 0..65535")


def cli_live(args) -> int:
    """Entry point of ``guidewire3d live``: set up once, serve until Ctrl-C or a bound, print a summary."""
    import signal
    import sys

    _check_args(args)

    def say(m):
        print(m, file=sys.stderr)
    if args.from_out:
        setup = setup_from_outdir(args.from_out, force=args.force)
    else:
        setup = setup_from_inputs(args.cta, args.roadmap, roadmap_frame=args.roadmap_frame, series_uid=args.series_uid,
                                  overrides=geometry_overrides(args), force=args.force, log=say)
    source, carm = _make_source(args, setup)
    session = live.Session(setup.tree, carm, setup.pose, registration_covariance=setup.covariance,
                           segmenter=args.segmenter, track_motion=args.track_motion)
    warm_up(session)
    mailbox = LatestFrame()

    def on_message(msg):
        if msg.message_type == "IMAGE":
            mailbox.put(Frame(getattr(msg, "image", None), float(msg.timestamp), f"igtl:{msg.device_name}"))

    server = IGTLServer(args.host, args.port, on_message=None if source is not None else on_message)
    stop = threading.Event()
    previous = {}

    def on_signal(signum, _frame):
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, on_signal)
    try:
        print(f"live: {setup.description}", flush=True)
        what = source.name if source is not None else "OpenIGTLink IMAGE messages (any device name)"
        print(f"live: listening on {server.host}:{server.port} (OpenIGTLink, {Space(args.space).value.upper()}); "
              f"frames: {what}; Ctrl-C stops", flush=True)
        if source is not None:
            source.start(mailbox, stop)
        runner = LiveRunner(session, server, mailbox, space=Space(args.space), max_frames=args.max_frames,
                            duration_s=args.duration, source=source, points=args.points)
        summary = runner.run(stop)
    finally:
        stop.set()
        mailbox.close()
        server.close()
        for sig, h in previous.items():
            signal.signal(sig, h)
    print(f"live: {summary.line()}", flush=True)
    return 0
