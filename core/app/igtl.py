"""OpenIGTLink for ``guidewire3d live``: the messages of a processed frame, the server that sends them
to every client, and the client that reads them back (the viewer, the Slicer module, the tests).

* **Messages** (:func:`frame_messages`): per processed frame, ``GuidewireStatus`` (STRING, JSON),
  ``Guidewire`` (POLYDATA, one polyline proximal -> distal), ``GuidewireUncertainty`` (STRING, the
  per-point 1-sigma in mm) and ``GuidewireTip`` (TRANSFORM: the tip position, its z axis along the
  wire's last 2 mm), each stamped with the source frame's time stamp. A frame without a 3D wire
  sends only the status. :class:`WireFollower` turns what a client received back into a
  :class:`LiveWire`.
* **Server** (:class:`IGTLServer`) and **client** (:class:`IGTLClient`). The messages are pyigtl's
  (``pyigtl.MessageBase.pack`` / ``parse_header`` / ``unpack``). The transport is ours: pyigtl
  0.3.4's ``OpenIGTLinkServer`` serves one client at a time (a second one waits until the first
  goes), spins (half a core here) after its client disconnects, and keeps a shared queue of 100
  messages that the next client receives stale. Here each client has a reader thread and a writer
  thread with a one-slot outbox (a slow client misses bundles, counted; it never slows the loop or
  the other clients). pyigtl cannot receive POLYDATA (its unpack is unfinished), so
  :class:`PolyDataMessage` completes it for our own clients.

Coordinates: ``--space lps`` (default, the package's convention) or ``ras`` (3D Slicer reads
POLYDATA and TRANSFORM as RAS, so the wire overlays a CTA loaded in Slicer only with ``ras``).
"""
from __future__ import annotations

import json
import logging
import socket
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass
from enum import Enum

import numpy as np
from guidewire3d.errors import InputError

__all__ = ["DEFAULT_HOST", "DEFAULT_PORT", "DEVICE_WIRE", "DEVICE_UNCERTAINTY", "DEVICE_TIP", "DEVICE_STATUS",
           "DEVICE_POINTS", "TIP_DIRECTION_MM", "Space", "PolyDataMessage", "frame_messages", "tip_matrix", "pack",
           "status_of", "read_message", "IGTLServer", "IGTLClient", "LiveWire", "WireFollower", "parse_host_port"]

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

_HEADER_SIZE = 58  # pyigtl.MessageBase.IGTL_HEADER_SIZE (OpenIGTLink header v1/v2)
_LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0])


class Space(Enum):
    """The coordinates of the 3D messages."""

    LPS = "lps"  # DICOM patient coordinates, the package's convention
    RAS = "ras"  # 3D Slicer's world coordinates


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


# --------------------------------------------------------------------------------------
# the live wire read back (what a client received)
# --------------------------------------------------------------------------------------
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
