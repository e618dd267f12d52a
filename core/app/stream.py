"""Live streaming: frames in from the C-arm, the 3D wire out over OpenIGTLink (``guidewire3d live``).

One process, three parts joined by a one-slot mailbox:

* a **frame source** (a thread): OpenIGTLink IMAGE messages that clients send to the server
  (PLUS, a frame grabber, 3D Slicer), a video file or device (OpenCV), a folder that frames appear
  in, or a DICOM XA file replayed at its frame rate. Each frame carries its source time stamp.
* the **processing loop** (the calling thread): takes the newest frame from the mailbox
  (:class:`LatestFrame`: a frame that a newer one replaced before it was processed is dropped and
  counted; nothing queues up), runs it through ``live.Session`` and publishes the result.
* the **OpenIGTLink server** (:class:`IGTLServer`): every connected client gets, per processed
  frame, ``GuidewireStatus`` (STRING, JSON), ``Guidewire`` (POLYDATA, one polyline proximal -> distal),
  ``GuidewireUncertainty`` (STRING, the per-point 1-sigma in mm) and ``GuidewireTip`` (TRANSFORM:
  the tip position, its z axis along the wire's last 2 mm), each stamped with the source frame's
  time stamp. A frame without a 3D wire sends only the status.

The messages are pyigtl's (``pyigtl.MessageBase.pack`` / ``parse_header`` / ``unpack``). The
transport is ours: pyigtl 0.3.4's ``OpenIGTLinkServer`` serves one client at a time (a second one
waits until the first goes), spins (half a core here) after its client disconnects, and keeps a
shared queue of 100 messages that the next client receives stale. Here each client has a reader thread and a
writer thread with a one-slot outbox (a slow client misses bundles, counted; it never slows the
loop or the other clients). pyigtl cannot receive POLYDATA (its unpack is unfinished), so
:class:`PolyDataMessage` completes it for our own clients (the viewer, the tests, the benchmark).

Coordinates: ``--space lps`` (default, the package's convention) or ``ras`` (3D Slicer reads
POLYDATA and TRANSFORM as RAS, so the wire overlays a CTA loaded in Slicer only with ``ras``).
"""
from __future__ import annotations

import json
import logging
import os
import socket
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np
from guidewire3d import io, reconstruction, registration
from guidewire3d.app import pipeline
from guidewire3d.app.outdir import load_outdir
from guidewire3d.app.pipeline import geometry_overrides
from guidewire3d.cta import vessels3d
from guidewire3d.errors import GeometryError, InputError
from guidewire3d.geometry import CArm
from guidewire3d.live import session as live
from guidewire3d.registration import Verdict
from guidewire3d.xray.orderedwire import OrderedWire
from guidewire3d.xray.roadmap import roadmap_centerline

__all__ = ["LiveWire", "WireFollower", "DEFAULT_PORT", "DEVICE_WIRE", "DEVICE_UNCERTAINTY", "DEVICE_TIP", "DEVICE_STATUS", "DEVICE_POINTS",
           "Space", "Frame",
           "LatestFrame", "PolyDataMessage", "IGTLServer", "IGTLClient", "LiveSetup", "LiveRunner", "LiveSummary",
           "ReplaySource", "VideoSource", "FolderSource", "check_frame", "frame_messages", "tip_matrix",
           "setup_from_outdir", "setup_from_inputs", "parse_host_port", "warm_up", "cli_live"]

log = logging.getLogger(__name__)

DEFAULT_PORT = 18944
DEFAULT_HOST = "127.0.0.1"
DEVICE_WIRE = "Guidewire"
DEVICE_UNCERTAINTY = "GuidewireUncertainty"
DEVICE_TIP = "GuidewireTip"
DEVICE_STATUS = "GuidewireStatus"
DEVICE_POINTS = "GuidewirePoints"  # POINT, only with ``points=True`` (``--points``)
#: the tip direction is the chord over the wire's last TIP_DIRECTION_MM
TIP_DIRECTION_MM = 2.0
#: a message body larger than this closes the connection (a 1024^2 float64 frame is 8 MB)
MAX_BODY_BYTES = 64 * 1024 * 1024
#: a message body that stops arriving for this long closes the connection
BODY_TIMEOUT_S = 5.0
#: socket poll period of the reader threads (how fast they see a stop request)
POLL_S = 0.2
#: latencies kept for the summary (the last ones; about 11 min at 30 fps)
KEEP_LATENCIES = 20000

_HEADER_SIZE = 58  # pyigtl.MessageBase.IGTL_HEADER_SIZE (OpenIGTLink header v1/v2)
_LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0])


class Space(Enum):
    """The coordinates of the 3D messages."""

    LPS = "lps"  # DICOM patient coordinates, the package's convention
    RAS = "ras"  # 3D Slicer's world coordinates


# --------------------------------------------------------------------------------------
# the mailbox
# --------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------
# messages
# --------------------------------------------------------------------------------------
def _pyigtl():
    try:
        import pyigtl
    except ImportError:  # pragma: no cover - a dependency of the package
        raise InputError("live streaming needs the pyigtl package (pip install pyigtl)") from None
    return pyigtl


def _polydata_class():
    pyigtl = _pyigtl()

    class _PolyData(pyigtl.PolyDataMessage):
        """pyigtl's POLYDATA with a working unpack (points and cells; attributes are skipped)."""

        def _unpack_content(self, content):
            head = struct.Struct("> 10I")
            n_pts, _nv, size_v, _nl, size_l, _np, size_p, _ns, size_s, _na = head.unpack(content[:head.size])
            pos = head.size
            self.points = np.frombuffer(content[pos:pos + 12 * n_pts], dtype=">f4").reshape(-1, 3).astype(float)
            pos += 12 * n_pts
            arrays = []
            for size in (size_v, size_l, size_p, size_s):
                arrays.append(np.frombuffer(content[pos:pos + size], dtype=">u4").astype(np.int64))
                pos += size
            self.vertices, self.lines, self.polygons, self.triangle_strips = arrays
            self.attributes = None

        def polylines(self) -> list[np.ndarray]:
            """The point ids of each line cell."""
            out, k, ln = [], 0, np.asarray(self.lines if self.lines is not None else [], np.int64)
            while k < len(ln):
                n = int(ln[k])
                out.append(ln[k + 1:k + 1 + n])
                k += n + 1
            return out

    return _PolyData


class _Lazy:
    """``PolyDataMessage`` resolves to the class on first use (pyigtl is imported then)."""

    _cls = None

    def __call__(self, *args, **kwargs):
        return self.cls(*args, **kwargs)

    @property
    def cls(self):
        if _Lazy._cls is None:
            _Lazy._cls = _polydata_class()
        return _Lazy._cls


#: ``PolyDataMessage(points=..., lines=..., device_name=..., timestamp=...)``: pyigtl's, receivable
PolyDataMessage = _Lazy()


def _message_types() -> dict:
    pyigtl = _pyigtl()
    types = dict(pyigtl.messages.message_type_to_class_constructor)
    types["POLYDATA"] = PolyDataMessage.cls
    return types


def tip_matrix(points_mm, *, direction_mm: float = TIP_DIRECTION_MM) -> np.ndarray:
    """A 4x4 rigid frame at the wire's tip: translation the last point, z axis the direction of the
    chord over the last ``direction_mm`` of the wire (pointing distally).

    Parameters
    ----------
    points_mm : (N, 3) array_like of float, N >= 2
        The wire, proximal -> distal.
    """
    p = np.asarray(points_mm, float).reshape(-1, 3)
    tip = p[-1]
    d = tip - p
    dist = np.linalg.norm(d, axis=1)
    far = np.nonzero(dist >= direction_mm)[0]
    z = d[far[-1]] if len(far) else d[0]
    n = float(np.linalg.norm(z))
    z = z / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, tip
    return m


def _to_space(points, space: Space) -> np.ndarray:
    p = np.asarray(points, float).reshape(-1, 3)
    return p @ _LPS_TO_RAS if space is Space.RAS else p.copy()


def frame_messages(result, *, space: Space = Space.LPS, stats: dict | None = None, points: bool = False) -> list:
    """The pyigtl messages of one processed frame, each stamped with the frame's time stamp.

    Parameters
    ----------
    result : live.FrameResult
    space : Space
    stats : dict, optional
        Counters added to the status JSON (frames in, processed, dropped, failed).
    points : bool
        Also send the wire as a POINT message (``GuidewirePoints``, each point's diameter twice its
        1-sigma uncertainty), for consumers that cannot read POLYDATA (ros2_igtl_bridge).

    Returns
    -------
    list of pyigtl messages
        ``GuidewireStatus`` first; then, when there is a 3D wire, ``Guidewire``,
        ``GuidewireUncertainty``, ``GuidewireTip`` (and ``GuidewirePoints``).
    """
    pyigtl = _pyigtl()
    ts = float(result.timestamp) if np.isfinite(result.timestamp) else time.time()
    ori = result.orientation
    has_wire = bool(result) and len(result.wire3d.points_lps_mm) >= 2
    pts = np.asarray(result.wire3d.points_lps_mm, float).reshape(-1, 3) if has_wire else np.zeros((0, 3))
    status = {"frame": int(result.index), "verdict": result.verdict.value, "message": str(result.message),
              "timestamp": ts, "space": space.value.upper(), "n_points": int(len(pts)),
              "length_mm": round(float(result.wire3d.length_mm), 3) if has_wire else None,
              "tip_confidence": ori.confidence if ori is not None else None,
              "processing_ms": round(1000.0 * float(result.seconds), 2)}
    motion = getattr(result, "motion", None)
    if motion is not None:  # live --track-motion: the frame's own pose update
        status["motion"] = {"verdict": motion.verdict.value, "message": str(motion.message)}
    if stats:
        status.update(stats)
    out = [pyigtl.StringMessage(json.dumps(status), device_name=DEVICE_STATUS, timestamp=ts)]
    if not has_wire:
        return out
    n = len(pts)
    lines = np.concatenate([[n], np.arange(n)]).astype(np.uint32)
    out.append(PolyDataMessage(points=_to_space(pts, space).astype(np.float32), lines=lines,
                               device_name=DEVICE_WIRE, timestamp=ts))
    unc = np.asarray(result.wire3d.uncertainty_mm, float).reshape(-1)
    out.append(pyigtl.StringMessage(" ".join(f"{u:.3f}" for u in unc), device_name=DEVICE_UNCERTAINTY, timestamp=ts))
    m = tip_matrix(pts)
    if space is Space.RAS:
        f = np.diag([-1.0, -1.0, 1.0, 1.0])
        m = f @ m @ f
    out.append(pyigtl.TransformMessage(m, device_name=DEVICE_TIP, timestamp=ts))
    if points:
        out.append(pyigtl.PointMessage(_to_space(pts, space), diameters=[2.0 * float(u) for u in unc],
                                       device_name=DEVICE_POINTS, timestamp=ts))
    return out


def pack(messages) -> bytes:
    """The messages as one byte string (pyigtl's packing)."""
    return b"".join(m.pack() for m in messages)


# --------------------------------------------------------------------------------------
# socket I/O (pyigtl's header parsing and message classes)
# --------------------------------------------------------------------------------------
class _Closed(Exception):
    """The peer closed the connection, or sent something that is not OpenIGTLink."""


def _recv_exact(sock, n: int, stop: threading.Event, *, idle_ok: bool) -> bytes | None:
    """``n`` bytes, or None when ``idle_ok`` and nothing arrived within one poll period."""
    buf = bytearray()
    waited = 0.0  # time spent waiting for data, counted in poll periods (a thread that was not
    # scheduled, e.g. while another one held the GIL, has not waited for the peer)
    while len(buf) < n:
        if stop.is_set():
            raise _Closed("stopping")
        try:
            chunk = sock.recv(min(n - len(buf), 1 << 20))
        except (socket.timeout, BlockingIOError):
            if idle_ok and not buf:
                return None
            waited += POLL_S
            if waited > BODY_TIMEOUT_S:
                raise _Closed(f"a message stalled for {BODY_TIMEOUT_S:g} s") from None
            continue
        except OSError as e:
            raise _Closed(str(e)) from None
        if not chunk:
            raise _Closed("closed by the peer")
        buf += chunk
        waited = 0.0
    return bytes(buf)


def _send_all(sock, data: bytes, stop: threading.Event) -> None:
    """``sock.sendall`` that keeps the socket's poll timeout (a reader thread shares the socket, and
    changing its timeout while the reader is in ``recv`` makes that ``recv`` fail with EAGAIN)."""
    view = memoryview(data)
    while view:
        if stop.is_set():
            raise _Closed("stopping")
        try:
            n = sock.send(view)
        except (socket.timeout, BlockingIOError):
            continue
        except OSError as e:
            raise _Closed(str(e)) from None
        view = view[n:]


def read_message(sock, stop: threading.Event, types: dict):
    """The next message on ``sock`` (a pyigtl message; None when idle for one poll period or of an
    unknown type). Raises ``_Closed`` when the connection ends or the stream is not OpenIGTLink."""
    pyigtl = _pyigtl()
    header = _recv_exact(sock, _HEADER_SIZE, stop, idle_ok=True)
    if header is None:
        return None
    try:
        fields = pyigtl.MessageBase.parse_header(header)
    except (struct.error, UnicodeDecodeError) as e:
        raise _Closed(f"not an OpenIGTLink header ({e})") from None
    size = int(fields["body_size"])
    if size > MAX_BODY_BYTES:
        raise _Closed(f"message body of {size} bytes refused (limit {MAX_BODY_BYTES})")
    body = _recv_exact(sock, size, stop, idle_ok=False) if size else b""
    cls = types.get(fields["message_type"])
    if cls is None:
        return None
    msg = cls()
    try:
        msg.unpack(fields, body)
    except Exception as e:  # noqa: BLE001 - a malformed message body: reported, the connection goes on
        log.warning("unreadable %s message from %s: %s", fields["message_type"], fields["device_name"], e)
        return None
    msg.received_at = time.time()
    return msg


class _Connection:
    """One client of the server: a reader thread and a writer thread with a one-slot outbox."""

    def __init__(self, server: "IGTLServer", sock: socket.socket, peer):
        self.server, self.sock, self.peer = server, sock, peer
        self.stop = threading.Event()
        self._cond = threading.Condition()
        self._outbox: tuple[bytes, object] | None = None
        self.n_sent = 0
        self.n_skipped = 0
        sock.settimeout(POLL_S)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.reader = threading.Thread(target=self._read, name=f"igtl-read-{peer}", daemon=True)
        self.writer = threading.Thread(target=self._write, name=f"igtl-write-{peer}", daemon=True)

    def start(self):
        self.reader.start()
        self.writer.start()

    def offer(self, payload: bytes, on_sent) -> None:
        with self._cond:
            if self._outbox is not None:
                self.n_skipped += 1
            self._outbox = (payload, on_sent)
            self._cond.notify_all()

    def close(self) -> None:
        self.stop.set()
        with self._cond:
            self._cond.notify_all()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass

    def _read(self):
        types = _message_types()
        try:
            while not self.stop.is_set():
                msg = read_message(self.sock, self.stop, types)
                if msg is not None and self.server.on_message is not None:
                    self.server.on_message(msg)
        except _Closed as e:
            if not self.stop.is_set():
                log.info("client %s: %s", self.peer, e)
        finally:
            self._end()

    def _write(self):
        try:
            while not self.stop.is_set():
                with self._cond:
                    while self._outbox is None and not self.stop.is_set():
                        self._cond.wait(timeout=1.0)
                    item, self._outbox = self._outbox, None
                if item is None:
                    continue
                payload, on_sent = item
                _send_all(self.sock, payload, self.stop)
                self.n_sent += 1
                if on_sent is not None:
                    on_sent(time.time())
        except _Closed as e:
            if not self.stop.is_set():
                log.info("client %s: send failed (%s)", self.peer, e)
        finally:
            self._end()

    def _end(self):
        self.close()
        self.server._forget(self)


class IGTLServer:
    """An OpenIGTLink server for any number of clients (pyigtl messages, threads per client).

    Parameters
    ----------
    host : str
        Interface to bind (default 127.0.0.1: this machine only).
    port : int
        TCP port (0: any free port; see ``port`` after construction).
    on_message : callable, optional
        Called from a client's reader thread with each message received (a pyigtl message; its
        ``received_at`` is the time of arrival).
    """

    def __init__(self, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, *, on_message=None):
        _pyigtl()
        self.on_message = on_message
        try:
            self._sock = socket.create_server((host, int(port)), reuse_port=False)
        except OSError as e:
            raise InputError(f"--host {host} --port {port}: cannot listen ({e.strerror or e})") from None
        self._sock.settimeout(POLL_S)
        self.host, self.port = self._sock.getsockname()[:2]
        self._lock = threading.Lock()
        self._conns: list[_Connection] = []
        self.n_connections = 0
        self.n_skipped_closed = 0  # bundles a slow client missed, of clients gone
        self._stop = threading.Event()
        self._accept_thread = threading.Thread(target=self._accept, name="igtl-accept", daemon=True)
        self._accept_thread.start()

    @property
    def n_clients(self) -> int:
        with self._lock:
            return len(self._conns)

    @property
    def n_skipped(self) -> int:
        """Bundles not sent to a client because a newer one replaced them (a slow client)."""
        with self._lock:
            return self.n_skipped_closed + sum(c.n_skipped for c in self._conns)

    def _accept(self):
        while not self._stop.is_set():
            try:
                sock, peer = self._sock.accept()
            except socket.timeout:
                continue
            except OSError:
                break
            conn = _Connection(self, sock, f"{peer[0]}:{peer[1]}")
            with self._lock:
                self._conns.append(conn)
                self.n_connections += 1
            log.info("client %s connected", conn.peer)
            conn.start()

    def _forget(self, conn: _Connection):
        with self._lock:
            if conn in self._conns:
                self._conns.remove(conn)
                self.n_skipped_closed += conn.n_skipped
                try:
                    conn.sock.close()
                except OSError:
                    pass

    def broadcast(self, payload: bytes, *, on_sent=None) -> int:
        """Offer ``payload`` to every client (never blocks); returns the number of clients.
        ``on_sent(t)`` is called by each client's writer once its copy is written to the socket."""
        with self._lock:
            conns = list(self._conns)
        for c in conns:
            c.offer(payload, on_sent)
        return len(conns)

    def close(self) -> None:
        self._stop.set()
        try:
            self._sock.close()
        except OSError:
            pass
        with self._lock:
            conns = list(self._conns)
        for c in conns:
            c.close()
        self._accept_thread.join(timeout=2.0)
        for c in conns:
            c.reader.join(timeout=2.0)
            c.writer.join(timeout=2.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class IGTLClient:
    """A small OpenIGTLink client: sends pyigtl messages, keeps what it receives.

    Received messages (pyigtl's, POLYDATA included; each with ``received_at``) go to a bounded
    deque (``keep`` newest) and to a latest-per-device dict. With ``reconnect`` it connects again
    after the server goes away.
    """

    def __init__(self, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, *, keep: int = 1024,
                 reconnect: bool = True, connect_timeout_s: float = 5.0):
        self.host, self.port, self.reconnect = host, int(port), reconnect
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._received: deque = deque(maxlen=int(keep))
        self._latest: dict = {}
        self._sock = None
        self._connected = threading.Event()
        self.n_received = 0
        self.n_connects = 0
        self._types = _message_types()
        self._thread = threading.Thread(target=self._run, name="igtl-client", daemon=True)
        self._thread.start()
        if connect_timeout_s and not self._connected.wait(connect_timeout_s):
            self.close()
            raise ConnectionError(f"no OpenIGTLink server at {host}:{port}")

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    def _run(self):
        while not self._stop.is_set():
            try:
                sock = socket.create_connection((self.host, self.port), timeout=1.0)
            except OSError:
                if not self.reconnect and self.n_connects:
                    return
                self._stop.wait(0.2)
                continue
            sock.settimeout(POLL_S)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._sock = sock
            self.n_connects += 1
            self._connected.set()
            try:
                while not self._stop.is_set():
                    msg = read_message(sock, self._stop, self._types)
                    if msg is None:
                        continue
                    with self._lock:
                        self._received.append(msg)
                        self._latest[msg.device_name] = msg
                        self.n_received += 1
            except _Closed:
                pass
            finally:
                self._connected.clear()
                self._sock = None
                try:
                    sock.close()
                except OSError:
                    pass
            if not self.reconnect:
                return

    def send(self, message) -> None:
        """Send one pyigtl message (raises ConnectionError when not connected)."""
        data = message.pack()
        with self._send_lock:
            sock = self._sock
            if sock is None:
                raise ConnectionError(f"not connected to {self.host}:{self.port}")
            try:
                _send_all(sock, data, self._stop)
            except _Closed as e:  # the connection ended meanwhile
                raise ConnectionError(f"{self.host}:{self.port}: {e}") from None

    def messages(self) -> list:
        """The messages received since the last call (oldest first)."""
        with self._lock:
            out = list(self._received)
            self._received.clear()
        return out

    def latest(self, device_name: str):
        with self._lock:
            return self._latest.get(device_name)

    def wait_for(self, predicate, *, timeout_s: float):
        """The first received message (consumed in order) for which ``predicate(msg)`` is true, or None
        after ``timeout_s``; the messages before it are consumed too."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            with self._lock:
                while self._received:
                    m = self._received.popleft()
                    if predicate(m):
                        return m
            time.sleep(0.005)
        return None

    def close(self) -> None:
        self._stop.set()
        sock = self._sock
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        self._thread.join(timeout=2.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def status_of(message) -> dict:
    """The JSON of a ``GuidewireStatus`` message."""
    return json.loads(message.string)


@dataclass(frozen=True)
class LiveWire:
    """One frame's wire as a ``guidewire3d live`` server sent it, back in LPS mm."""

    points_lps_mm: np.ndarray  #: (N, 3)
    uncertainty_mm: np.ndarray  #: (N,) per-point 1-sigma; zeros when the frame's uncertainty did not arrive
    status: dict  #: the frame's ``GuidewireStatus`` (frame, verdict, message, dropped, space, ...)
    timestamp: float  #: the source frame's timestamp (s)


class WireFollower:
    """Follows a ``guidewire3d live`` server through an :class:`IGTLClient`: what every display of
    the live wire (the viewer's ``view --live``, the Slicer module) reads, with no drawing here.

    ``poll()`` consumes the received messages in order (a frame's status comes before its wire) and
    returns the newest :class:`LiveWire` when a new wire arrived (``None`` otherwise); ``status``
    always holds the newest ``GuidewireStatus`` (a frame without a wire updates only that). Points
    sent in RAS (``live --space ras``) are converted back to LPS.
    """

    def __init__(self, client):
        self.client = client
        self.status: dict = {}
        self.n_updates = 0
        self.wire: LiveWire | None = None
        self._wire_msg = self._unc_msg = None

    def poll(self) -> LiveWire | None:
        changed = False
        for m in self.client.messages():
            if m.device_name == DEVICE_STATUS:
                self.status = status_of(m)
            elif m.device_name == DEVICE_WIRE:
                self._wire_msg, changed = m, True
            elif m.device_name == DEVICE_UNCERTAINTY:
                self._unc_msg, changed = m, True
        if not changed or self._wire_msg is None:
            return None
        pts = np.asarray(self._wire_msg.points, float).reshape(-1, 3)
        if str(self.status.get("space", Space.LPS.value)).upper() == Space.RAS.value.upper():
            pts = pts * np.array([-1.0, -1.0, 1.0])
        unc = np.zeros(len(pts))
        u = self._unc_msg
        if u is not None and u.timestamp == self._wire_msg.timestamp:
            vals = np.array(u.string.split(), float)
            unc = vals if len(vals) == len(pts) else unc
        self.wire = LiveWire(pts, unc, dict(self.status), float(self._wire_msg.timestamp))
        self.n_updates += 1
        return self.wire


def parse_host_port(text: str, *, option: str = "--live") -> tuple[str, int]:
    """``"HOST:PORT"`` (or ``":PORT"``, ``"PORT"``) -> ``(host, port)``."""
    host, _, port = str(text).rpartition(":")
    try:
        p = int(port)
    except ValueError:
        raise InputError(f"{option}: expected HOST:PORT such as 127.0.0.1:{DEFAULT_PORT}, got {text!r}") from None
    if not 0 < p < 65536:
        raise InputError(f"{option}: port {p} out of range 1..65535")
    return host or DEFAULT_HOST, p


# --------------------------------------------------------------------------------------
# frames
# --------------------------------------------------------------------------------------
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
    reach the network: the segmenter skips it), so the first frame does not pay for it."""
    rng = np.random.default_rng(0)
    session.warm_up(rng.normal(1000.0, 50.0, session.carm.shape).astype(np.float32))


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
