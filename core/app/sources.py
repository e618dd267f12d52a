"""Frames in for ``guidewire3d live``: the frame, the one-slot mailbox between a source and the
processing loop, and the sources that fill it.

A source is a thread: a video file or device (OpenCV), a folder that frames appear in, or a DICOM
XA file replayed at its frame rate (OpenIGTLink IMAGE messages reach the mailbox through the
server's ``on_message``, see ``stream``). Each frame carries its source time stamp. The mailbox
(:class:`LatestFrame`) keeps only the newest frame: a frame that a newer one replaced before it was
processed is dropped and counted; nothing queues up. :func:`check_frame` turns what a source
delivered into the frame the engine takes, or says why it cannot.

Two planes (a biplane C-arm): :class:`PairedFrames` is the mailbox of the two streams. It pairs a
frame of plane A with the frame of plane B whose source time stamp is nearest, within a tolerance,
and hands out the newest complete pair; frames older than a pair handed out are dropped and counted
per plane, and each plane keeps at most a few frames. A plane whose frames stop (or never pair)
does not stall the other: after a timeout the other plane's newest frame is handed out alone, with
the reason. :class:`PairReplaySource` replays two XA runs as pairs.
"""
from __future__ import annotations

import os
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from guidewire3d.errors import InputError

__all__ = ["Frame", "LatestFrame", "check_frame", "ReplaySource", "VideoSource", "FolderSource", "PLANES",
           "FramePair", "PairedFrames", "PairReplaySource", "DEFAULT_PERIOD_S", "DEFAULT_PLANE_TIMEOUT_S",
           "KEEP_PER_PLANE", "PARTNER_WAIT_S"]

PLANES = ("A", "B")
#: the frame period assumed until a plane's time stamps show their own (15 fps)
DEFAULT_PERIOD_S = 1.0 / 15.0
#: a plane that sent nothing for this long (or no pair formed for this long) is left out: the other
#: plane's frames are processed alone (single-view fallback)
DEFAULT_PLANE_TIMEOUT_S = 0.5
#: frames kept per plane while they wait for their partner (older ones are dropped and counted)
KEEP_PER_PLANE = 8
#: time stamps per plane over which the frame period is measured (their median interval)
PERIOD_WINDOW = 16
#: before a silent plane is left out, the other plane's frames wait at least this long (or the pairing
#: tolerance, if longer) for a partner (the loop may have been busy: then nothing came from either)
PARTNER_WAIT_S = 0.1


@dataclass(frozen=True, eq=False)
class Frame:
    """A frame as a source delivered it.

    Attributes
    ----------
    image : ndarray or None
        As received (any dtype and shape; :func:`check_frame` decides); None when the source could
        not read it (``error`` says why).
    timestamp : float
        Source time stamp, seconds since 1970 (the OpenIGTLink header's, or the time the source
        read the frame).
    source : str
        Where it came from (``igtl:<device>``, a file name, ...).
    error : str
    """

    image: object
    timestamp: float
    source: str = ""
    error: str = ""


class LatestFrame:
    """A one-slot mailbox between a source thread and the processing loop.

    ``put`` replaces a frame that was not taken yet: that frame is dropped and counted
    (``n_dropped``). ``take`` returns the newest frame. Nothing ever queues.
    """

    def __init__(self):
        self._cond = threading.Condition()
        self._frame: Frame | None = None
        self._closed = False
        self.n_in = 0
        self.n_dropped = 0

    def put(self, frame: Frame) -> None:
        with self._cond:
            self.n_in += 1
            if self._frame is not None:
                self.n_dropped += 1
            self._frame = frame
            self._cond.notify_all()

    def skipped(self, n: int) -> None:
        """Count ``n`` frames that a source saw but did not deliver because newer ones were there."""
        with self._cond:
            self.n_in += int(n)
            self.n_dropped += int(n)

    def take(self, timeout_s: float) -> Frame | None:
        """The newest frame, waiting up to ``timeout_s``; None when there is none (or closed)."""
        with self._cond:
            if self._frame is None and not self._closed:
                self._cond.wait(timeout=max(float(timeout_s), 0.0))
            f, self._frame = self._frame, None
            return f

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


def check_frame(image, shape) -> tuple[np.ndarray | None, str]:
    """A frame as the engine takes it (``(rows, cols)`` float32), or None and the reason.

    Accepts ``(rows, cols)``, ``(1, rows, cols)`` (an OpenIGTLink 2D image as PLUS sends it:
    i = columns, j = rows, k = 1), ``(rows, cols, 1)`` (what ``pyigtl.ImageMessage`` makes of a 2D
    array) and 3- or 4-component colour (converted to grey).
    """
    if image is None:
        return None, "no image"
    a = np.asarray(image)
    if a.ndim == 4 and a.shape[0] == 1:  # (k=1, rows, cols, components)
        a = a[0]
    if a.ndim == 3 and 1 in a.shape:  # (1, rows, cols); (rows, cols, 1) is pyigtl's packing of a 2D array
        a = a[0] if a.shape[0] == 1 else a[..., 0] if a.shape[-1] == 1 else a
    if a.ndim == 3 and a.shape[-1] in (3, 4):
        a = a[..., :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    if a.ndim != 2:
        return None, f"expected a 2D frame, got an array of shape {tuple(np.asarray(image).shape)}"
    if tuple(a.shape) != tuple(shape):
        return None, f"frame size {tuple(a.shape)} differs from the C-arm view's {tuple(shape)}"
    f = np.asarray(a, dtype=np.float32)
    bad = int(f.size - np.count_nonzero(np.isfinite(f)))
    if bad:
        return None, f"{bad} non-finite pixels (NaN or inf)"
    return f, ""


def _source_thread(name, target):
    return threading.Thread(target=target, name=name, daemon=True)


def _start_paced(name: str, items, fps: float, loop: bool, stop: threading.Event, emit, done: threading.Event) -> None:
    """In a source thread: ``emit(item, time stamp)`` for each of ``items`` at ``fps`` (from the start
    again with ``loop``) until ``stop``; ``done`` is set when it ends."""
    def go():
        period = 1.0 / fps
        t_next = time.monotonic()
        try:
            while not stop.is_set():
                for item in items:
                    if stop.is_set():
                        return
                    stop.wait(max(0.0, t_next - time.monotonic()))
                    emit(item, time.time())
                    t_next += period
                if not loop:
                    return
        finally:
            done.set()

    _source_thread(name, go).start()


def _replay_fps(run, fps) -> float:
    """A replay's rate: ``fps`` (``--fps``), else the run's FrameTime, else 15; InputError outside 0.1..1000."""
    ft = getattr(run, "frame_time_ms", None)
    rate = float(fps) if fps else (1000.0 / ft if ft else 15.0)
    if not 0.1 <= rate <= 1000:
        raise InputError(f"--fps: expected 0.1..1000 frames per second, got {rate:g}")
    return rate


class ReplaySource:
    """Frames of an ``io.XARun`` at ``fps`` (its frame time by default, 15 fps without one), each
    stamped with the time it is put in the mailbox; ``loop`` repeats the run."""

    def __init__(self, run, *, fps: float | None = None, loop: bool = False):
        self.run, self.loop = run, loop
        self.fps = _replay_fps(run, fps)
        self.carm = run.carm
        self.name = f"replay of {run.source} at {self.fps:g} fps" + (" (loop)" if loop else "")
        self.done = threading.Event()

    def start(self, mailbox: LatestFrame, stop: threading.Event) -> None:
        name = Path(self.run.source).name

        def emit(k, ts):
            mailbox.put(Frame(self.run.frames[k], ts, f"{name}#{k}"))

        _start_paced("replay", range(self.run.n_frames), self.fps, self.loop, stop, emit, self.done)


class VideoSource:
    """Frames from OpenCV: a video file (paced at its frame rate) or a capture device (as fast as it
    delivers); each stamped with the time it was read."""

    def __init__(self, spec, carm, *, loop: bool = False):
        import cv2

        self.spec, self.carm, self.loop = spec, carm, loop
        self.device = str(spec).isdigit() or str(spec).startswith("/dev/")
        arg = int(spec) if str(spec).isdigit() else str(spec)
        self.cap = cv2.VideoCapture(arg)
        if not self.cap.isOpened():
            raise InputError(f"--video {spec}: cannot open (not a readable video or capture device)")
        fps = float(self.cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.fps = fps if 0.1 <= fps <= 1000 else 15.0
        self.name = f"video device {spec}" if self.device else f"video {spec} at {self.fps:g} fps"
        self.done = threading.Event()

    def start(self, mailbox: LatestFrame, stop: threading.Event) -> None:
        import cv2

        def go():
            period = 1.0 / self.fps
            t_next = time.monotonic()
            k = 0
            try:
                while not stop.is_set():
                    if not self.device:
                        stop.wait(max(0.0, t_next - time.monotonic()))
                        t_next += period
                    ok, im = self.cap.read()
                    if not ok:
                        if self.loop and not self.device and k:
                            self.cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                            continue
                        return
                    grey = cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) if im.ndim == 3 else im
                    mailbox.put(Frame(grey.astype(np.float32), time.time(), f"{self.spec}#{k}"))
                    k += 1
            finally:
                self.cap.release()
                self.done.set()

        _source_thread("video", go).start()


class FolderSource:
    """Frames that appear in a folder (PNG/TIFF/JPEG, newest by name): each new file is read once it
    is complete and stamped with its modification time. When several appeared since the last look,
    only the newest is read and the others count as dropped."""

    SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg")
    POLL_S = 0.01
    RETRIES = 20  # an unreadable file (still being written) is tried again this many times

    def __init__(self, folder, carm):
        self.folder, self.carm = Path(folder), carm
        if not self.folder.is_dir():
            raise InputError(f"--watch {folder}: not a folder")
        self.name = f"new frames in {self.folder}"
        self.done = threading.Event()

    def _names(self) -> list[str]:
        try:
            return sorted(e.name for e in os.scandir(self.folder) if e.name.lower().endswith(self.SUFFIXES))
        except OSError:
            return []

    def start(self, mailbox: LatestFrame, stop: threading.Event) -> None:
        import cv2

        seen = set(self._names())  # frames already there are the past, not the live stream
        tries: dict[str, int] = {}

        def go():
            try:
                while not stop.is_set():
                    new = [n for n in self._names() if n not in seen]
                    if not new:
                        stop.wait(self.POLL_S)
                        continue
                    name = new[-1]
                    path = self.folder / name
                    im = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
                    if im is None and tries.get(name, 0) < self.RETRIES:
                        tries[name] = tries.get(name, 0) + 1
                        stop.wait(self.POLL_S)
                        continue
                    seen.update(new)
                    tries.clear()
                    if len(new) > 1:
                        mailbox.skipped(len(new) - 1)
                    try:
                        ts = path.stat().st_mtime
                    except OSError:
                        ts = time.time()
                    if im is None:
                        mailbox.put(Frame(None, ts, name, error=f"{name}: unreadable image"))
                        continue
                    if im.ndim == 3:
                        im = cv2.cvtColor(im, cv2.COLOR_BGRA2GRAY if im.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
                    mailbox.put(Frame(im.astype(np.float32), ts, name))
            finally:
                self.done.set()

        _source_thread("folder", go).start()


# --------------------------------------------------------------------------------------
# two planes: pairs of frames
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class FramePair:
    """What :class:`PairedFrames` hands out: a frame of each plane, or one plane's frame alone
    (``a`` or ``b`` None) with ``reason`` saying why the other is missing."""

    a: Frame | None
    b: Frame | None
    reason: str = ""

    @property
    def complete(self) -> bool:
        return self.a is not None and self.b is not None

    @property
    def timestamp(self) -> float:
        """The pair's time stamp: plane A's (plane B's when A is missing)."""
        return float(self.a.timestamp if self.a is not None else self.b.timestamp)

    def frame(self, plane: str) -> Frame | None:
        return self.a if plane == PLANES[0] else self.b


class PairedFrames:
    """The mailbox of two planes' streams (biplane): frames in per plane, the newest complete pair out.

    * **Pair**: a frame of plane A and the frame of plane B whose source time stamp is nearest to it,
      if within ``tolerance_s`` (default: half the frame period, measured as the median interval of
      each plane's recent time stamps, the longer of the two planes'; ``DEFAULT_PERIOD_S`` until a
      plane has two frames). :meth:`take` hands out the pair with the newest plane-A frame.
    * **Stale frames**: when a pair is handed out, each plane's frames that came before its own frame
      of the pair are dropped and counted per plane (``n_dropped``); when a lone frame is, its plane's
      older frames and the other plane's frames older than it by more than the tolerance. Each plane keeps at most ``keep`` frames (the oldest is dropped and
      counted when a newer one arrives): nothing queues without bound.
    * **A silent plane**: when one plane sent nothing for ``timeout_s`` (switched off, unplugged), or no
      partner came for a plane's frames for ``timeout_s`` although both send (time stamps too far
      apart), that plane's newest frame is handed out alone (plane A first), with the reason. Before
      the silent plane is left out, the other's frames wait ``PARTNER_WAIT_S`` (or the tolerance) for
      a partner (after a loop busy for longer than the timeout, the partner is on its way); while the
      plane stays left out, the next frames go at once.

    ``n_in[p] = n_used[p] + n_dropped[p] + waiting(p)`` for each plane ``p``.

    Parameters
    ----------
    tolerance_s : float, optional
        Pairing tolerance (s); default half the measured frame period.
    timeout_s : float
        See above.
    keep : int
        Frames kept per plane.
    clock : callable
        Monotonic seconds (tests pass their own).
    """

    def __init__(self, *, tolerance_s: float | None = None, timeout_s: float = DEFAULT_PLANE_TIMEOUT_S,
                 keep: int = KEEP_PER_PLANE, clock=time.monotonic):
        if tolerance_s is not None and not tolerance_s > 0:
            raise InputError(f"pairing tolerance: expected a positive number of seconds, got {tolerance_s}")
        if not timeout_s > 0:
            raise InputError(f"plane timeout: expected a positive number of seconds, got {timeout_s}")
        if int(keep) < 1:
            raise InputError(f"frames kept per plane: expected at least 1, got {keep}")
        self.fixed_tolerance_s = None if tolerance_s is None else float(tolerance_s)
        self.timeout_s, self.keep, self._clock = float(timeout_s), int(keep), clock
        self._cond = threading.Condition()
        self._closed = False
        now = clock()
        self._buf = {p: deque() for p in PLANES}  # (Frame, arrival time) oldest first
        self._stamps = {p: deque(maxlen=PERIOD_WINDOW + 1) for p in PLANES}
        self._last_arrival = {p: now for p in PLANES}  # the start counts as an arrival
        self._waiting_since = {p: None for p in PLANES}  # arrival of the oldest frame waiting since the last take
        self._left_out = {p: False for p in PLANES}  # the plane is left out (the other's frames go alone)
        self.n_in = {p: 0 for p in PLANES}
        self.n_dropped = {p: 0 for p in PLANES}
        self.n_used = {p: 0 for p in PLANES}
        self.n_pairs = 0
        self.n_alone = {p: 0 for p in PLANES}

    # --- in ----------------------------------------------------------------------------
    def put(self, plane: str, frame: Frame) -> None:
        if plane not in PLANES:
            raise ValueError(f"plane must be one of {PLANES}, got {plane!r}")
        with self._cond:
            now = self._clock()
            buf = self._buf[plane]
            self.n_in[plane] += 1
            while len(buf) >= self.keep:
                buf.popleft()
                self.n_dropped[plane] += 1
            buf.append((frame, now))
            if self._waiting_since[plane] is None:
                self._waiting_since[plane] = now
            self._last_arrival[plane] = now
            if np.isfinite(frame.timestamp):
                self._stamps[plane].append(float(frame.timestamp))
            self._cond.notify_all()

    # --- out ---------------------------------------------------------------------------
    def period_s(self, plane: str) -> float:
        """The plane's frame period: the median interval of its recent time stamps."""
        t = np.asarray(self._stamps[plane], float)
        d = np.diff(t)
        d = d[d > 0]
        return float(np.median(d)) if len(d) else DEFAULT_PERIOD_S

    def _tolerance(self) -> float:
        if self.fixed_tolerance_s is not None:
            return self.fixed_tolerance_s
        return 0.5 * max(self.period_s(p) for p in PLANES)

    @property
    def tolerance_s(self) -> float:
        """The pairing tolerance now (s)."""
        with self._cond:
            return self._tolerance()

    def waiting(self, plane: str) -> int:
        with self._cond:
            return len(self._buf[plane])

    def _drop_older(self, plane: str, t: float, tol: float) -> None:
        buf = self._buf[plane]
        keep = deque(x for x in buf if not x[0].timestamp < t - tol)
        if len(keep) < len(buf):
            self.n_dropped[plane] += len(buf) - len(keep)
            self._buf[plane] = keep
            self._waiting_since[plane] = keep[0][1] if keep else None

    def _taken(self, plane: str) -> None:
        """Plane ``plane`` gave a frame: its wait for a partner starts again with what is left."""
        self.n_used[plane] += 1
        buf = self._buf[plane]
        self._waiting_since[plane] = buf[0][1] if buf else None

    def _pick(self, now: float) -> FramePair | None:
        """The newest complete pair, else a lone frame once a plane timed out, else None."""
        tol = self._tolerance()
        A, B = self._buf["A"], self._buf["B"]
        if A and B:
            tb = np.array([f.timestamp for f, _ in B], float)
            for i in range(len(A) - 1, -1, -1):
                fa = A[i][0]
                gap = np.abs(tb - fa.timestamp)
                j = len(gap) - 1 - int(np.argmin(gap[::-1]))  # the nearest; of equals, the newest
                if gap[j] <= tol:
                    fb = B[j][0]
                    # each plane's frames that came before its frame of the pair are stale
                    for p, n in (("A", i), ("B", j)):
                        buf = self._buf[p]
                        self.n_dropped[p] += n
                        self._buf[p] = deque(list(buf)[n + 1:])
                        self._taken(p)
                    self.n_pairs += 1
                    self._left_out = {q: False for q in PLANES}
                    return FramePair(fa, fb)
        for k, p in enumerate(PLANES):
            q = PLANES[1 - k]
            if not self._buf[p]:
                continue
            silent = now - self._last_arrival[q]
            unpaired = now - self._waiting_since[p]
            # plane p's frames wait a little for a partner before plane q is left out (a sender that
            # waits for each result sends nothing while the loop is busy, longer than the timeout
            # maybe), unless plane q is left out already
            if silent > self.timeout_s and (unpaired >= self._grace(tol) or self._left_out[q]):
                reason = f"no frame from plane {q} for {silent:.1f} s"
            elif unpaired > self.timeout_s:
                reason = (f"no plane {q} frame within {1000 * tol:.0f} ms of plane {p}'s for {unpaired:.1f} s "
                          "(source time stamps too far apart?)")
            else:
                continue
            f, _ = self._buf[p].pop()
            self.n_dropped[p] += len(self._buf[p])  # the plane's older frames
            self._buf[p].clear()
            self._drop_older(q, f.timestamp, tol)
            self._taken(p)
            self._left_out[q] = True
            self.n_alone[p] += 1
            return FramePair(f, None, reason) if p == "A" else FramePair(None, f, reason)
        return None

    def _grace(self, tol: float) -> float:
        return min(self.timeout_s, max(tol, PARTNER_WAIT_S))

    def _next_due(self, now: float) -> float:
        """Seconds until a lone frame could become due (the plane timeout), for the wait."""
        tol = self._tolerance()
        due = []
        for k, p in enumerate(PLANES):
            if self._buf[p]:
                q = PLANES[1 - k]
                silent_due = self._last_arrival[q] + self.timeout_s
                if not self._left_out[q]:
                    silent_due = max(silent_due, self._waiting_since[p] + self._grace(tol))
                due.append(min(silent_due, self._waiting_since[p] + self.timeout_s) - now)
        return min(max(min(due), 0.001), self.timeout_s) if due else float("inf")

    def take(self, timeout_s: float) -> FramePair | None:
        """The newest complete pair (or a lone frame, see the class), waiting up to ``timeout_s``; None
        when there is none (or closed)."""
        end = self._clock() + max(float(timeout_s), 0.0)
        with self._cond:
            while True:
                now = self._clock()
                got = self._pick(now)
                if got is not None or self._closed:
                    return got
                left = end - now
                if left <= 0:
                    return None
                self._cond.wait(timeout=min(left, self._next_due(now) + 1e-3))

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


class PairReplaySource:
    """Two planes' XA runs replayed as pairs at ``fps`` (plane A's frame time by default, 15 fps
    without one): each pair's two frames are put in a :class:`PairedFrames` with the same time stamp
    (when they are put); ``loop`` repeats the runs.

    Parameters
    ----------
    runs : pair of io.XARun
    pairs : list of (int, int)
        The frames of A and B that go together (``biplane.pair_frames``).
    """

    def __init__(self, runs, pairs, *, fps: float | None = None, loop: bool = False):
        self.runs, self.pairs, self.loop = tuple(runs), list(pairs), loop
        if len(self.runs) != 2 or not self.pairs:
            raise InputError("a biplane replay needs two runs and at least one pair of frames")
        self.fps = _replay_fps(self.runs[0], fps)
        self.name = (f"replay of {self.runs[0].source} (plane A) and {self.runs[1].source} (plane B), "
                     f"{len(self.pairs)} pairs at {self.fps:g} fps" + (" (loop)" if loop else ""))
        self.done = threading.Event()

    def start(self, mailbox: PairedFrames, stop: threading.Event) -> None:
        def emit(pair, ts):
            for p, run, k in zip(PLANES, self.runs, pair):
                mailbox.put(p, Frame(run.frames[k], ts, f"{Path(run.source).name}#{k}"))

        _start_paced("replay-pairs", self.pairs, self.fps, self.loop, stop, emit, self.done)
