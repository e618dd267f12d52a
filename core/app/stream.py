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

**Two planes** (a biplane C-arm, issues 19/23): the setup holds both planes' live views (a biplane
``reconstruct`` output, or two roadmaps registered jointly by ``biplane.register_biplane``), the
frames of each plane arrive as IMAGE messages of their own device name (or a replay of two runs),
``sources.PairedFrames`` pairs them by source time stamp, and :class:`BiplaneRunner` runs each pair
through ``biplane.BiplaneSession`` (a plane whose frames stop is left out after a timeout: the other
plane's frames are reconstructed alone, and the status says so).
"""
from __future__ import annotations

import gc
import threading
import time
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from guidewire3d import io, reconstruction, registration
from guidewire3d.app import biplane, pipeline
from guidewire3d.app.igtl import DEFAULT_HOST, DEFAULT_PORT, IGTLServer, Space, frame_messages, pack
from guidewire3d.app.outdir import load_outdir, load_plane_b
from guidewire3d.app.pipeline import geometry_overrides
from guidewire3d.app.sources import (
    DEFAULT_PLANE_TIMEOUT_S,
    PLANES,
    FolderSource,
    Frame,
    FramePair,
    LatestFrame,
    PairedFrames,
    PairReplaySource,
    ReplaySource,
    VideoSource,
    check_frame,
)
from guidewire3d.cta import vesselmodel
from guidewire3d.errors import GeometryError, InputError
from guidewire3d.geometry import CArm
from guidewire3d.live import session as live
from guidewire3d.registration import Verdict
from guidewire3d.vesseltree import access_record, check_access, rooted_at_access
from guidewire3d.xray.orderedwire import OrderedWire
from guidewire3d.xray.roadmap import roadmap_centerline

__all__ = ["LiveSetup", "LiveRunner", "LiveSummary", "BiplaneRunner", "BiplaneSummary", "setup_from_outdir",
           "setup_from_inputs", "warm_up", "warm_up_biplane", "add_cli_options", "cli_live", "DEFAULT_DEVICES"]

#: latencies kept for the summary (the last ones; about 11 min at 30 fps)
KEEP_LATENCIES = 20000
#: OpenIGTLink device names of the two planes' IMAGE messages (``--device-a``, ``--device-b``)
DEFAULT_DEVICES = ("PlaneA", "PlaneB")


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
    verdict : registration.Verdict
    frames_carm_b : CArm or None
        Plane B's live view (a biplane setup: ``frames_carm`` is plane A's); None for one plane.
    plane_sources : tuple of str
        Where each plane's view comes from (for the messages that compare a replay's planes with them).
    """

    tree: object
    frames_carm: object
    pose: object
    covariance: object
    description: str
    verdict: object = None  # registration.Verdict of the pose
    frames_carm_b: object = None
    plane_sources: tuple = ()

    @property
    def biplane(self) -> bool:
        return self.frames_carm_b is not None

    @property
    def frames_carms(self) -> tuple:
        """The live views: (plane A's, plane B's) for a biplane, (the one,) otherwise."""
        return (self.frames_carm, self.frames_carm_b) if self.biplane else (self.frames_carm,)


def _access_note(tree, access_lps_mm) -> str:
    """What a setup's description says of the access point ("" without one)."""
    if access_lps_mm is None:
        return ""
    rec = access_record(tree, access_lps_mm)
    return f", rooted at {rec['root_lps_mm']} ({rec['distance_mm']:.1f} mm from the access point)"


def setup_from_outdir(out_dir, *, force: bool = False, access_lps_mm=None) -> LiveSetup:
    """The vessel tree and registration of a ``reconstruct`` output folder (a manual correction
    included: ``registration.json``'s ``pose``). ``access_lps_mm`` (LPS mm, optional): where the wire
    enters; the folder's tree is rooted at its point nearest to it
    (:func:`guidewire3d.vesseltree.rooted_at_access`).

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
    plane_b = load_plane_b(out_dir, load_images=False)
    tree = case.tree if access_lps_mm is None else rooted_at_access(case.tree, access_lps_mm)
    desc = (f"{out_dir}: {tree.n_points} centerline points{_access_note(tree, access_lps_mm)}, {case.pose_source} "
            f"pose (registration {verdict.value})")
    if plane_b is None:
        return LiveSetup(tree, case.frames_carm, case.pose, cov, desc, verdict)
    desc += (f"; biplane: plane A {_angles(case.frames_carm)}, plane B {_angles(plane_b.frames_carm)} "
             f"({_separation_deg(case.frames_carm, plane_b.frames_carm):.0f} deg apart)")
    return LiveSetup(tree, case.frames_carm, case.pose, cov, desc, verdict, plane_b.frames_carm,
                     (f"{out_dir} (plane A)", f"{out_dir} (plane B)"))


def _angles(carm) -> str:
    return f"{carm.primary_deg:+.1f}/{carm.secondary_deg:+.1f} deg"


def _separation_deg(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(a.beam_direction @ b.beam_direction, -1.0, 1.0))))


def setup_from_inputs(cta, roadmap, *, roadmap_frame=None, seeds_lps_mm=None, series_uid=None, overrides=None,
                      force: bool = False, access_lps_mm=None, log=None) -> LiveSetup:
    """CTA vessels -> roadmap centerline -> registration, as ``reconstruct`` does it.

    ``roadmap``: one roadmap file, or a sequence of one or two (plane A, plane B: the joint
    registration ``biplane.register_biplane`` of both roadmaps, as ``reconstruct`` with two
    ``--roadmap``; C-arm ``overrides`` describe one view and are refused then).
    ``access_lps_mm`` (LPS mm, optional): where the wire enters; the tree is rooted at its point
    nearest to it, as ``reconstruct --access-lps`` does.
    """
    roadmaps = [roadmap] if isinstance(roadmap, (str, Path)) else list(roadmap)
    if len(roadmaps) == 2:
        return _setup_biplane_from_inputs(cta, roadmaps, roadmap_frame=roadmap_frame, seeds_lps_mm=seeds_lps_mm,
                                          series_uid=series_uid, overrides=overrides, force=force,
                                          access_lps_mm=access_lps_mm, log=log)
    if len(roadmaps) != 1:
        raise InputError(f"--roadmap: give one (one plane) or two (biplane: plane A, then plane B), got {len(roadmaps)}")
    roadmap = roadmaps[0]
    overrides = io.check_geometry_overrides(overrides)
    road = pipeline.read_xa_input(roadmap, overrides=overrides)
    vol = io.read_volume(cta, series_uid=series_uid, log=log)
    k = pipeline.choose_roadmap_frame(road, roadmap_frame)
    pipeline.check_seeds(vol, seeds_lps_mm)
    if access_lps_mm is not None:
        access_lps_mm = check_access(access_lps_mm, bounds_lps_mm=vol.bounds_lps_mm)
    t0 = time.perf_counter()
    ves = vesselmodel.extract_vessels_any_units(vol, seeds_lps_mm=seeds_lps_mm, log=log)
    tree = pipeline.rooted_vessels(ves, access_lps_mm, log=log).tree
    cl = roadmap_centerline(np.asarray(road.frames[k]),
                            max_radius_px=float(tree.radius_mm.max()) / road.carm.pixel_at_iso_mm * 1.5)
    reg = registration.register(tree, cl.points_uv_px, road.carm, centerline_radius_px=cl.radius_px)
    if log is not None:
        log(f"registration: {reg.verdict.label} ({reg.message}); residual {reg.mean_residual_px:.2f} px "
            f"({time.perf_counter() - t0:.1f} s with the CTA vessels)")
    if not reg.success and not force:
        raise InputError(f"{roadmap}: the registration {reg.verdict.value} its checks ({reg.message}); run "
                         "`guidewire3d reconstruct` and correct it in the viewer, then `live --from OUT`, or give --force")
    desc = f"{cta} + {roadmap} frame {k}: {tree.n_points} centerline points{_access_note(tree, access_lps_mm)}"
    return LiveSetup(tree, road.carm, reg.pose, reg.covariance_6x6, desc, reg.verdict)


def read_biplane_roadmaps(roadmaps, *, roadmap_frame=None, overrides=None) -> list:
    """Both planes' roadmap runs, checked as ``reconstruct`` checks them (before the CTA): positioner
    tags, the roadmap frame, the planes' separation (``biplane.check_planes``)."""
    if any(v is not None for v in (overrides or {}).values()):
        given = [f"--{k.split('_')[0]}" for k, v in overrides.items() if v is not None]
        raise InputError(f"{', '.join(given)}: the C-arm overrides describe one view; with two --roadmap each plane's "
                         "geometry comes from its own DICOM positioner tags")
    roads = [pipeline.read_xa_input(r) for r in roadmaps]
    biplane.check_planes(roads, roads)
    for r in roads:
        pipeline.choose_roadmap_frame(r, roadmap_frame)
    return roads


def _setup_biplane_from_inputs(cta, roadmaps, *, roadmap_frame=None, seeds_lps_mm=None, series_uid=None,
                               overrides=None, force: bool = False, access_lps_mm=None, log=None) -> LiveSetup:
    """Two roadmaps: CTA vessels -> both roadmaps' centerlines -> the joint registration, as
    ``biplane.run`` does it."""
    roads = read_biplane_roadmaps(roadmaps, roadmap_frame=roadmap_frame, overrides=overrides)
    vol = io.read_volume(cta, series_uid=series_uid, log=log)
    pipeline.check_seeds(vol, seeds_lps_mm)
    if access_lps_mm is not None:
        access_lps_mm = check_access(access_lps_mm, bounds_lps_mm=vol.bounds_lps_mm)
    t0 = time.perf_counter()
    ves = vesselmodel.extract_vessels_any_units(vol, seeds_lps_mm=seeds_lps_mm, log=log)
    tree = pipeline.rooted_vessels(ves, access_lps_mm, log=log).tree
    ks, _, cls = zip(*(pipeline.roadmap_centerline_of(road, tree, roadmap_frame) for road in roads))
    breg = biplane.register_biplane(tree, [c.points_uv_px for c in cls], [r.carm for r in roads],
                                    centerline_radius_px=[c.radius_px for c in cls])
    reg = breg.result
    if log is not None:
        log(f"biplane registration: {reg.verdict.label} ({reg.message}) ({time.perf_counter() - t0:.1f} s with the "
            "CTA vessels)")
    if not reg.success and not force:
        raise InputError(f"{roadmaps[0]} + {roadmaps[1]}: the biplane registration {reg.verdict.value} its checks "
                         f"({reg.message}); run `guidewire3d reconstruct` with both planes and correct it in the "
                         "viewer, then `live --from OUT`, or give --force")
    a, b = roads[0].carm, roads[1].carm
    desc = (f"{cta} + {roadmaps[0]} frame {ks[0]} (plane A, {_angles(a)}) + {roadmaps[1]} frame {ks[1]} (plane B, "
            f"{_angles(b)}; {_separation_deg(a, b):.0f} deg apart): {tree.n_points} centerline points"
            f"{_access_note(tree, access_lps_mm)}")
    return LiveSetup(tree, a, reg.pose, reg.covariance_6x6, desc, reg.verdict, b,
                     tuple(str(r) for r in roadmaps))


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


def warm_up_biplane(session) -> None:
    """:func:`warm_up` for a ``biplane.BiplaneSession`` (both planes' segmenters; the heap frozen
    the same way)."""
    rng = np.random.default_rng(0)
    session.warm_up(*(rng.normal(1000.0, 50.0, c.shape).astype(np.float32) for c in session.carms))
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

    def _latency_and_clients(self) -> str:
        """The end of :meth:`line`: the latency percentiles and the clients."""
        lat, what = ((self.latency_sent_s, "source time stamp -> sent") if self.latency_sent_s
                     else (self.latency_processed_s, "source time stamp -> published, no client"))
        s = ""
        if len(lat):
            s += f"; latency ({what}) median {self._pct(lat, 50):.1f} ms, p99 {self._pct(lat, 99):.1f} ms"
        s += f"; {self.connections} client connection(s)"
        if self.skipped_for_slow_clients:
            s += f", {self.skipped_for_slow_clients} bundles skipped for slow clients"
        return s

    def line(self) -> str:
        return (f"{self.frames_in} frames in, {self.processed} processed ({self.ok} ok, {self.uncertain} uncertain, "
                f"{self.failed} failed), {self.dropped} dropped in {self.seconds:.1f} s" + self._latency_and_clients())

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
        self._count(result)
        self._publish(result, frame.timestamp, dict(self.stats(), source=frame.source))
        if self.on_result is not None:
            self.on_result(result)
        return result

    def _count(self, result) -> None:
        s = self.summary
        s.processed += 1
        s.ok += result.verdict is Verdict.OK
        s.uncertain += result.verdict is Verdict.UNCERTAIN
        s.failed += result.verdict is Verdict.FAILED

    def _publish(self, result, ts: float, stats: dict) -> None:
        """The result's messages to every client; the latencies from the source time stamp ``ts``."""
        msgs = frame_messages(result, space=self.space, stats=stats, points=self.points)
        payload = pack(msgs)
        self._lat_proc.append(time.time() - ts)
        if self.server is not None:
            first = []

            def on_sent(t, _ts=ts):
                with self._lock:
                    if not first:
                        first.append(t)
                        self._lat_sent.append(t - _ts)

            self.server.broadcast(payload, on_sent=on_sent)

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
            item = self.mailbox.take(min(0.1, left) if left is not None else 0.1)
            if item is None:
                if self.source is not None and self.source.done.is_set():
                    break
                continue
            self.process(item)
        time.sleep(0.05)  # let the writers send the last bundle
        s = self.summary
        s.seconds = time.monotonic() - t0
        self._final_counts()
        if self.server is not None:
            s.connections, s.skipped_for_slow_clients = self.server.n_connections, self.server.n_skipped
        with self._lock:
            s.latency_processed_s, s.latency_sent_s = list(self._lat_proc), list(self._lat_sent)
        return s

    def _final_counts(self) -> None:
        self.summary.frames_in, self.summary.dropped = self.mailbox.n_in, self.mailbox.n_dropped


# --------------------------------------------------------------------------------------
# two planes: the pairs' loop
# --------------------------------------------------------------------------------------
@dataclass
class BiplaneSummary(LiveSummary):
    """What a biplane live run did. ``processed`` counts pairs and lone frames; per plane (``"A"``,
    ``"B"``): ``frames_in[p] = used[p] + dropped[p]`` (+ frames left waiting at the end).
    ``frames_in``/``dropped`` of :class:`LiveSummary` are the two planes' sums."""

    planes_in: dict = field(default_factory=lambda: {p: 0 for p in PLANES})
    planes_dropped: dict = field(default_factory=lambda: {p: 0 for p in PLANES})
    planes_used: dict = field(default_factory=lambda: {p: 0 for p in PLANES})
    two_view: int = 0  # pairs whose 3D wire came from both planes (views "AB")
    alone: dict = field(default_factory=lambda: {p: 0 for p in PLANES})  # a plane's frame processed alone (timeout)
    one_view: dict = field(default_factory=lambda: {p: 0 for p in PLANES})  # wires from one plane (alone or fallback)
    ignored: int = 0  # IMAGE messages of another device name

    def line(self) -> str:
        s = (f"{self.processed} pairs processed ({self.two_view} from both planes, {self.one_view['A']} from plane A "
             f"only, {self.one_view['B']} from plane B only; {self.ok} ok, {self.uncertain} uncertain, "
             f"{self.failed} failed) in {self.seconds:.1f} s; "
             + "; ".join(f"plane {p}: {self.planes_in[p]} frames in, {self.planes_dropped[p]} dropped"
                         + (f", {self.alone[p]} processed without the other plane" if self.alone[p] else "")
                         for p in PLANES))
        if self.ignored:
            s += f"; {self.ignored} IMAGE messages of other device names ignored"
        return s + self._latency_and_clients()


class BiplaneRunner(LiveRunner):
    """The processing loop of two planes: newest pair -> ``biplane.BiplaneSession`` -> messages.

    A pair's two frames go through ``BiplaneSession.process`` (the two-view wire, or its own
    single-view fallback when one plane's wire is missing or cannot be matched). A plane's frame
    handed out alone by the mailbox (the other plane timed out) or a pair with one bad frame is
    reconstructed from that plane alone (its ``live.Session``), its message starting
    ``one view (plane A only): ...`` as the session's fallback does. Every message is stamped with
    the pair's time stamp (plane A's; plane B's for a plane-B frame alone); the status adds
    ``views``, ``fallback``, ``timestamp_b``, ``projection_error_px`` and per-plane counters.

    Parameters
    ----------
    session : biplane.BiplaneSession
    server : IGTLServer or None
    mailbox : sources.PairedFrames
    devices : pair of str
        The device names of the planes' IMAGE messages (reported in the status).
    ignored : callable, optional
        The number of IMAGE messages of other device names so far (reported in the status).
    Other parameters as :class:`LiveRunner` (``on_result`` gets each ``biplane.BiplaneFrame``).
    """

    def __init__(self, session, server, mailbox: PairedFrames, *, devices=DEFAULT_DEVICES, ignored=None, **kw):
        super().__init__(session, server, mailbox, **kw)
        self.devices = tuple(devices)
        self._ignored = ignored
        self.summary = BiplaneSummary()

    def stats(self) -> dict:
        m, s = self.mailbox, self.summary
        planes = {p: {"device": d, "frames_in": m.n_in[p], "dropped": m.n_dropped[p]}
                  for p, d in zip(PLANES, self.devices)}
        out = {"frames_in": sum(m.n_in.values()), "processed": s.processed, "dropped": sum(m.n_dropped.values()),
               "failed": s.failed, "planes": planes, "pair_tolerance_ms": round(1000.0 * m.tolerance_s, 2)}
        if self._ignored is not None:
            out["ignored"] = int(self._ignored())
        return out

    def _alone(self, k: int, img, index: int, ts: float, why: str):
        """Plane k's frame reconstructed alone (the other plane left out: ``why``)."""
        if getattr(self.session, "motion_tracker", None) is not None:
            # tracking motion (``--track-motion``): through the pair's engine, so that the lone frame updates the
            # pose from its plane alone before it is reconstructed in it (``BiplaneSession.process_one``)
            return self.session.process_one(k, img, why=why, index=index)
        fr = self.session.sessions[k].process(img, index=index, timestamp=ts)
        o = 1 - k
        fallback = f"one view (plane {PLANES[k]} only): plane {PLANES[o]}: {why}"
        fr = replace(fr, message=f"{fallback}. {fr.message}".strip())
        perr = [float("nan"), float("nan")]
        if fr.wire3d:
            perr[k] = float(fr.wire3d.projection_error_px)
        return biplane.BiplaneFrame(fr, PLANES[k] if fr.wire3d else "", fallback, None, tuple(perr), index,
                                    fr.seconds)

    def process(self, pair: FramePair):
        """Process one pair (or a plane's lone frame) and publish its messages; returns the
        ``biplane.BiplaneFrame``."""
        index = self.summary.processed
        ts = pair.timestamp
        imgs, why = [None, None], ["", ""]
        for k, (p, carm) in enumerate(zip(PLANES, self.session.carms)):
            f = pair.frame(p)
            if f is None:
                why[k] = pair.reason or "no frame"
                continue
            img, err = check_frame(f.image, carm.shape) if not f.error else (None, f.error)
            imgs[k], why[k] = img, ("" if img is not None else f"bad frame: {err}")
        if imgs[0] is not None and imgs[1] is not None:
            bf = self.session.process(imgs[0], imgs[1], index=index, index_b=index)
        elif imgs[0] is not None or imgs[1] is not None:
            k = 0 if imgs[0] is not None else 1
            bf = self._alone(k, imgs[k], index, ts, why[1 - k])
        else:
            msg = "; ".join(f"plane {p}: {w}" for p, w in zip(PLANES, why))
            fr = self._bad_frame(index, pair.a or pair.b, msg)
            bf = biplane.BiplaneFrame(fr, "", msg, None, (float("nan"), float("nan")), index, 0.0)
        result = replace(bf.result, timestamp=ts)
        s = self.summary
        self._count(result)
        if pair.complete:
            s.two_view += bf.views == "AB"
        else:
            s.alone[PLANES[0] if pair.a is not None else PLANES[1]] += 1
        if bf.views in PLANES:
            s.one_view[bf.views] += 1

        def ms(x):
            return round(float(x), 4) if np.isfinite(x) else None

        fb = pair.b
        extra = dict(self.stats(), source=" + ".join(f.source for f in (pair.a, pair.b) if f is not None),
                     views=bf.views, fallback=bf.fallback, timestamp_b=None if fb is None else float(fb.timestamp),
                     projection_error_px={"a": ms(bf.projection_error_px[0]), "b": ms(bf.projection_error_px[1])})
        self._publish(result, ts, extra)
        bf = replace(bf, result=result)
        if self.on_result is not None:
            self.on_result(bf)
        return bf

    def _final_counts(self) -> None:
        s, m = self.summary, self.mailbox
        s.planes_in, s.planes_dropped, s.planes_used = dict(m.n_in), dict(m.n_dropped), dict(m.n_used)
        s.frames_in, s.dropped = sum(m.n_in.values()), sum(m.n_dropped.values())
        if self._ignored is not None:
            s.ignored = int(self._ignored())


# --------------------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------------------
def add_cli_options(p) -> None:
    """The options of ``guidewire3d live``."""
    g = p.add_argument_group("setup (once): a previous output folder, or the inputs as for reconstruct")
    g.add_argument("--from", dest="from_out", metavar="OUT",
                   help="a folder written by reconstruct: its vessel tree and registration (manual correction "
                        "included); a biplane output (two --roadmap) sets up both planes")
    g.add_argument("--cta", help="CTA DICOM series folder, or NIfTI/NRRD/MHA file")
    g.add_argument("--roadmap", action="append", default=None,
                   help="XA DICOM with the contrast roadmap (or a PNG/TIFF folder / video with geometry JSON); give "
                        "it twice for a biplane (plane A, then plane B: one joint registration, as reconstruct)")
    g.add_argument("--roadmap-frame", type=int, default=None, metavar="K")
    g.add_argument("--series-uid", default=None)
    g.add_argument("--force", action="store_true", help="go live even if the registration failed its checks")
    s = p.add_argument_group("frame source (default: OpenIGTLink IMAGE messages sent to the server)")
    x = s.add_mutually_exclusive_group()
    x.add_argument("--video", metavar="PATH|DEVICE", help="a video file (paced at its frame rate) or a capture device "
                   "(0, /dev/video0) through OpenCV; geometry: <video>.json beside a file, or --geometry")
    x.add_argument("--watch", metavar="DIR", help="a folder that PNG/TIFF frames appear in (geometry.json in it, or --geometry)")
    x.add_argument("--replay", metavar="XA.dcm", action="append", default=None,
                   help="replay a DICOM XA file at its frame rate (for demos); twice for a biplane setup (plane A, "
                        "then plane B; frames paired as reconstruct pairs them)")
    s.add_argument("--fps", type=float, default=None, help="--replay rate (default: the file's FrameTime, else 15)")
    s.add_argument("--loop", action="store_true", help="--replay / --video file: start again at the end")
    s.add_argument("--geometry", metavar="JSON", help="C-arm geometry of the live frames (primary_deg, secondary_deg, "
                   "sid_mm, sod_mm, pixel_mm); default: the roadmap's, or the source's own")
    bp = p.add_argument_group("two planes (a biplane setup): OpenIGTLink device names and pairing")
    bp.add_argument("--device-a", metavar="NAME", default=None,
                    help=f"device name of plane A's IMAGE messages (biplane default {DEFAULT_DEVICES[0]}; one plane: "
                         "only this device's images are processed, default any device)")
    bp.add_argument("--device-b", metavar="NAME", default=None,
                    help=f"device name of plane B's IMAGE messages (biplane only; default {DEFAULT_DEVICES[1]})")
    bp.add_argument("--pair-tolerance-ms", type=float, default=None, metavar="MS",
                    help="two frames are a pair when their source time stamps are at most this far apart (default: "
                         "half the frame period, measured from each plane's time stamps; 1/30 s until then)")
    bp.add_argument("--plane-timeout", type=float, default=DEFAULT_PLANE_TIMEOUT_S, metavar="S",
                    help="a plane that sent nothing (or nothing to pair with) for S seconds is left out and the other "
                         f"plane's frames are reconstructed alone, until it is back (default {DEFAULT_PLANE_TIMEOUT_S:g})")
    o = p.add_argument_group("output (OpenIGTLink server)")
    o.add_argument("--host", default=DEFAULT_HOST, help="interface to listen on (default 127.0.0.1: this machine only)")
    o.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"TCP port (default {DEFAULT_PORT})")
    o.add_argument("--space", default="lps", choices=[m.value for m in Space],
                   help="coordinates of the wire and tip messages: lps (default) or ras (for 3D Slicer)")
    o.add_argument("--points", action="store_true", help="also send the wire as a POINT message (GuidewirePoints), for "
                   "consumers without POLYDATA such as ros2_igtl_bridge")
    o.add_argument("--segmenter", default="unet", choices=("unet", "ridge"))
    o.add_argument("--track-motion", action="store_true", help="follow breathing and heartbeat: each frame's wire "
                   "updates the pose before it is reconstructed (as reconstruct --track-motion; two planes: each pair's "
                   "wires, a plane's lone frame its own)")
    b = p.add_argument_group("bounds (default: run until Ctrl-C)")
    b.add_argument("--max-frames", type=int, default=None, metavar="N", help="stop after N processed frames (pairs)")
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
        run = io.read_xa(args.replay[0])
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


class _PlaneView:
    """A plane's view for ``biplane.check_planes`` (its ``carm`` and where it comes from)."""

    def __init__(self, carm, source):
        self.carm, self.source = carm, source


def _read_biplane_replays(args, setup_views):
    """Both planes' replay runs, checked against the setup's planes (``biplane.check_planes``: the same
    plane order and angles), and their frame pairs (``biplane.pair_frames``)."""
    runs = [io.read_xa(r) for r in args.replay]
    biplane.check_planes(setup_views, runs)
    for run, view, p in zip(runs, setup_views, PLANES):
        if tuple(run.frames.shape[1:]) != tuple(view.carm.shape):
            raise InputError(f"{run.source}: frame size {tuple(run.frames.shape[1:])} differs from plane {p}'s view "
                             f"{tuple(view.carm.shape)} ({view.source})")
    pairs = biplane.pair_frames(runs[0], runs[1], range(runs[0].n_frames), range(runs[1].n_frames))
    return runs, pairs


def _check_args(args) -> None:
    roadmaps = args.roadmap or []
    if args.from_out and (args.cta or roadmaps):
        what = "two --roadmap" if len(roadmaps) == 2 else "--cta and --roadmap"
        raise InputError(f"live: give --from OUT, or {what}, not both (a biplane OUT holds both planes' setup)")
    if not args.from_out and not (args.cta and roadmaps):
        raise InputError("live: give --from OUT (a reconstruct output folder), or --cta and --roadmap (twice for a "
                         "biplane)")
    if len(roadmaps) > 2:
        raise InputError(f"--roadmap: give one (one plane) or two (biplane: plane A, then plane B), got {len(roadmaps)}")
    if args.replay and len(args.replay) > 2:
        raise InputError(f"--replay: give one (one plane) or two (biplane: plane A, then plane B), got {len(args.replay)}")
    if args.device_a is not None and args.device_a == (args.device_b or DEFAULT_DEVICES[1]) or \
            args.device_b is not None and args.device_b == (args.device_a or DEFAULT_DEVICES[0]):
        name = args.device_b if args.device_b is not None else args.device_a
        raise InputError(f"--device-a and --device-b: both planes are named {name!r}; each plane's IMAGE messages "
                         "need a device name of their own")
    for opt, v in (("--device-a", args.device_a), ("--device-b", args.device_b)):
        if v is not None and not str(v).strip():
            raise InputError(f"{opt}: expected a device name, got an empty one")
    if args.pair_tolerance_ms is not None and not args.pair_tolerance_ms > 0:
        raise InputError(f"--pair-tolerance-ms: expected a positive number of milliseconds, got {args.pair_tolerance_ms}")
    if not args.plane_timeout > 0:
        raise InputError(f"--plane-timeout: expected a positive number of seconds, got {args.plane_timeout}")
    if args.max_frames is not None and args.max_frames < 1:
        raise InputError(f"--max-frames: expected a positive integer, got {args.max_frames}")
    if args.duration is not None and not args.duration > 0:
        raise InputError(f"--duration: expected a positive number of seconds, got {args.duration}")
    if not 0 <= args.port < 65536:
        raise InputError(f"--port: {args.port} out of range 0..65535")


def _check_plane_options(args, two: bool) -> None:
    """The options that need (or do not fit) two planes, once the setup says how many there are."""
    replays = args.replay or []
    if two:
        for opt, given in (("--video", args.video), ("--watch", args.watch), ("--geometry", args.geometry)):
            if given:
                raise InputError(f"{opt}: not available with two planes (a biplane setup takes OpenIGTLink IMAGE "
                                 "messages of two device names, or --replay twice)")
        if len(replays) == 1:
            raise InputError(f"--replay {replays[0]}: the setup has two planes; give --replay twice (plane A, then "
                             "plane B)")
        return
    if len(replays) == 2:
        raise InputError(f"--replay {replays[1]}: two replays need a biplane setup (a biplane reconstruct output, or "
                         "two --roadmap)")
    for opt, given in (("--device-b", args.device_b), ("--pair-tolerance-ms", args.pair_tolerance_ms),
                       ("--plane-timeout", args.plane_timeout != DEFAULT_PLANE_TIMEOUT_S)):
        if given:
            raise InputError(f"{opt}: only with two planes (a biplane reconstruct output, or two --roadmap)")


def cli_live(args) -> int:
    """Entry point of ``guidewire3d live``: set up once, serve until Ctrl-C or a bound, print a summary."""
    import sys

    _check_args(args)

    def say(m):
        print(m, file=sys.stderr)
    roadmaps = args.roadmap or []
    replays = None
    access = getattr(args, "access_lps", None)
    if args.from_out:
        setup = setup_from_outdir(args.from_out, force=args.force, access_lps_mm=access)
        _check_plane_options(args, setup.biplane)
        if setup.biplane and args.replay:
            replays = _read_biplane_replays(args, [_PlaneView(c, src) for c, src in
                                                   zip(setup.frames_carms, setup.plane_sources)])
    else:
        _check_plane_options(args, len(roadmaps) == 2)
        if len(roadmaps) == 2:  # every input checked before the CTA
            roads = read_biplane_roadmaps(roadmaps, roadmap_frame=args.roadmap_frame,
                                          overrides=geometry_overrides(args))
            if args.replay:
                replays = _read_biplane_replays(args, roads)
        setup = setup_from_inputs(args.cta, roadmaps, roadmap_frame=args.roadmap_frame, series_uid=args.series_uid,
                                  overrides=geometry_overrides(args), force=args.force, access_lps_mm=access, log=say)
    if setup.biplane:
        return _serve_biplane(args, setup, replays, say)
    source, carm = _make_source(args, setup)
    session = live.Session(setup.tree, carm, setup.pose, registration_covariance=setup.covariance,
                           segmenter=args.segmenter, track_motion=args.track_motion)
    warm_up(session)
    mailbox = LatestFrame()
    ignored = _Ignored(say, {args.device_a: "A"} if args.device_a else None)

    def on_message(msg):
        if msg.message_type == "IMAGE" and ignored.plane_of(msg.device_name):
            mailbox.put(Frame(getattr(msg, "image", None), float(msg.timestamp), f"igtl:{msg.device_name}"))

    what = (source.name if source is not None else
            f"OpenIGTLink IMAGE messages of device {args.device_a!r}" if args.device_a else
            "OpenIGTLink IMAGE messages (any device name)")

    def runner_of(server):
        return LiveRunner(session, server, mailbox, space=Space(args.space), max_frames=args.max_frames,
                          duration_s=args.duration, source=source, points=args.points)

    return _serve(args, setup, source, mailbox, on_message, what, runner_of)


class _Ignored:
    """The device names whose IMAGE messages go to a plane (None: any, to plane A); the others are
    counted and named once on stderr."""

    def __init__(self, say, planes: dict | None):
        self.say, self.planes = say, planes
        self.n = 0
        self._names: set = set()
        self._lock = threading.Lock()

    def plane_of(self, name: str) -> str | None:
        if self.planes is None:
            return PLANES[0]
        p = self.planes.get(name)
        if p is None:
            with self._lock:
                self.n += 1
                new = name not in self._names
                self._names.add(name)
            if new:
                known = ", ".join(f"plane {q}: {d!r}" for d, q in self.planes.items())
                self.say(f"live: ignoring IMAGE messages of device {name!r} ({known})")
        return p

    def count(self) -> int:
        with self._lock:
            return self.n


def _serve_biplane(args, setup: LiveSetup, replays, say) -> int:
    devices = (args.device_a or DEFAULT_DEVICES[0], args.device_b or DEFAULT_DEVICES[1])
    session = biplane.BiplaneSession(setup.tree, setup.frames_carms, setup.pose,
                                     registration_covariance=setup.covariance, segmenter=args.segmenter,
                                     track_motion=bool(args.track_motion))
    warm_up_biplane(session)
    tol = None if args.pair_tolerance_ms is None else args.pair_tolerance_ms / 1000.0
    mailbox = PairedFrames(tolerance_s=tol, timeout_s=args.plane_timeout)
    source = None
    if replays is not None:
        runs, pairs = replays
        source = PairReplaySource(runs, pairs, fps=args.fps, loop=args.loop)
    ignored = _Ignored(say, {devices[0]: PLANES[0], devices[1]: PLANES[1]})

    def on_message(msg):
        if msg.message_type == "IMAGE":
            p = ignored.plane_of(msg.device_name)
            if p is not None:
                mailbox.put(p, Frame(getattr(msg, "image", None), float(msg.timestamp), f"igtl:{msg.device_name}"))

    pairing = (f"pairs within {args.pair_tolerance_ms:g} ms" if tol is not None
               else "pairs within half the frame period")
    what = (source.name if source is not None else
            f"OpenIGTLink IMAGE messages, plane A: device {devices[0]!r}, plane B: device {devices[1]!r}")
    what += f"; {pairing}; a plane silent for {args.plane_timeout:g} s is left out"

    def runner_of(server):
        return BiplaneRunner(session, server, mailbox, devices=devices, ignored=ignored.count,
                             space=Space(args.space), max_frames=args.max_frames, duration_s=args.duration,
                             source=source, points=args.points)

    try:
        return _serve(args, setup, source, mailbox, on_message, what, runner_of)
    finally:
        session.close()


def _serve(args, setup: LiveSetup, source, mailbox, on_message, what: str, runner_of) -> int:
    """Serve until Ctrl-C (SIGTERM) or a bound; print the summary."""
    import signal

    server = IGTLServer(args.host, args.port, on_message=None if source is not None else on_message)
    stop = threading.Event()
    previous = {}

    def on_signal(signum, _frame):
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, on_signal)
    try:
        print(f"live: {setup.description}", flush=True)
        print(f"live: listening on {server.host}:{server.port} (OpenIGTLink, {Space(args.space).value.upper()}); "
              f"frames: {what}; Ctrl-C stops", flush=True)
        if source is not None:
            source.start(mailbox, stop)
        summary = runner_of(server).run(stop)
    finally:
        stop.set()
        mailbox.close()
        server.close()
        for sig, h in previous.items():
            signal.signal(sig, h)
    print(f"live: {summary.line()}", flush=True)
    return 0
