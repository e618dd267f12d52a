"""Frames in for ``guidewire3d live``: the frame, the one-slot mailbox between a source and the
processing loop, and the sources that fill it.

A source is a thread: a video file or device (OpenCV), a folder that frames appear in, or a DICOM
XA file replayed at its frame rate (OpenIGTLink IMAGE messages reach the mailbox through the
server's ``on_message``, see ``stream``). Each frame carries its source time stamp. The mailbox
(:class:`LatestFrame`) keeps only the newest frame: a frame that a newer one replaced before it was
processed is dropped and counted; nothing queues up. :func:`check_frame` turns what a source
delivered into the frame the engine takes, or says why it cannot.
"""
from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from guidewire3d.errors import InputError

__all__ = ["Frame", "LatestFrame", "check_frame", "ReplaySource", "VideoSource", "FolderSource"]


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


class ReplaySource:
    """Frames of an ``io.XARun`` at ``fps`` (its frame time by default, 15 fps without one), each
    stamped with the time it is put in the mailbox; ``loop`` repeats the run."""

    def __init__(self, run, *, fps: float | None = None, loop: bool = False):
        self.run, self.loop = run, loop
        ft = getattr(run, "frame_time_ms", None)
        self.fps = float(fps) if fps else (1000.0 / ft if ft else 15.0)
        if not 0.1 <= self.fps <= 1000:
            raise InputError(f"--fps: expected 0.1..1000 frames per second, got {self.fps:g}")
        self.carm = run.carm
        self.name = f"replay of {run.source} at {self.fps:g} fps" + (" (loop)" if loop else "")
        self.done = threading.Event()

    def start(self, mailbox: LatestFrame, stop: threading.Event) -> None:
        def go():
            period = 1.0 / self.fps
            t_next = time.monotonic()
            try:
                while not stop.is_set():
                    for k in range(self.run.n_frames):
                        if stop.is_set():
                            return
                        stop.wait(max(0.0, t_next - time.monotonic()))
                        mailbox.put(Frame(self.run.frames[k], time.time(), f"{Path(self.run.source).name}#{k}"))
                        t_next += period
                    if not self.loop:
                        return
            finally:
                self.done.set()

        _source_thread("replay", go).start()


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
