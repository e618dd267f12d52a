"""``guidewire3d live``: frames in over OpenIGTLink (and the other sources), the 3D wire out.

Every socket is on 127.0.0.1 and every wait is bounded in time. The reference is ``reconstruct``
(``pipeline.run_to_outdir``) on the same frames of the small simulated case: the server is set up
from its output folder (``--from OUT``), as a user would after correcting a registration.
"""
from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from guidewire3d import io
from guidewire3d.live import session as live
from guidewire3d.app import igtl, pipeline, sources, stream
from guidewire3d.errors import InputError
from guidewire3d.registration import Verdict

pyigtl = pytest.importorskip("pyigtl")

MATCH_MM = 0.05  # the brief: streamed points within 0.05 mm of reconstruct's
FLOAT32_MM = 1e-3  # POLYDATA / TRANSFORM carry float32 (about 3e-5 mm at 300 mm)
UNC_DECIMALS_MM = 6e-4  # GuidewireUncertainty is written with 3 decimals (report.json has 4)
WAIT_S = 120.0  # per frame on a loaded 2-core machine (a frame takes 20-400 ms; the first one loads the UNet)
HOST = "127.0.0.1"


# --------------------------------------------------------------------------------------
# fixtures
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def live_out(small_case_dir, tmp_path_factory):
    """``reconstruct`` on the small case: the output folder and its report."""
    out = tmp_path_factory.mktemp("live_server") / "out"
    d = small_case_dir
    pipeline.run_to_outdir(d / "ct", d / "roadmap.dcm", d / "frames.dcm", out, images=False, progress=False)
    return out, json.loads((out / "report.json").read_text())


@pytest.fixture(scope="module")
def frames(small_case_dir):
    """The live frames exactly as ``reconstruct`` read them."""
    return io.read_xa(small_case_dir / "frames.dcm").frames


@pytest.fixture(scope="module")
def setup(live_out):
    return stream.setup_from_outdir(live_out[0])


@contextlib.contextmanager
def serving(setup, *, track_motion=False, **runner_kw):
    """A live server on a free port with its processing loop in a thread."""
    session = live.Session(setup.tree, setup.frames_carm, setup.pose, registration_covariance=setup.covariance,
                           track_motion=track_motion)
    stream.warm_up(session)
    mailbox = sources.LatestFrame()

    def on_message(msg):
        if msg.message_type == "IMAGE":
            mailbox.put(sources.Frame(msg.image, float(msg.timestamp), f"igtl:{msg.device_name}"))

    server = igtl.IGTLServer(HOST, 0, on_message=on_message)
    runner = stream.LiveRunner(session, server, mailbox, duration_s=600.0, **runner_kw)
    stop = threading.Event()
    thread = threading.Thread(target=runner.run, args=(stop,), daemon=True)
    thread.start()
    try:
        yield server, runner, thread
    finally:
        stop.set()
        thread.join(timeout=30)
        server.close()


def image_message(frame, ts):
    """A 2D frame as PLUS sends it: i = columns, j = rows, k = 1 (other arrays as they are)."""
    a = np.asarray(frame)
    return pyigtl.ImageMessage(a[None] if a.ndim == 2 else a, device_name="Image_Reference", timestamp=ts)


def _wire3d(points, uncertainty):
    """A successful ``Wire3D`` with the given points (the fields the messages read)."""
    from dataclasses import replace

    from guidewire3d import reconstruction

    n = len(points)
    return replace(reconstruction.Wire3D.failed("-"), points_lps_mm=np.asarray(points, float),
                   uncertainty_mm=np.asarray(uncertainty, float), length_mm=1.0, success=True, message="ok",
                   tree_point_ids=np.zeros(n, np.int64), arclength_mm=np.zeros(n), curvature_per_mm=np.zeros(n))


def next_status(client, timeout_s=WAIT_S):
    m = client.wait_for(lambda m: m.device_name == igtl.DEVICE_STATUS, timeout_s=timeout_s)
    assert m is not None, "no GuidewireStatus within the time limit"
    return m, igtl.status_of(m)


def bundle_after(client, status_msg, timeout_s=10.0):
    """The messages of the frame whose status was ``status_msg`` (same time stamp), by device name."""
    out = {igtl.DEVICE_STATUS: status_msg}
    end = time.monotonic() + timeout_s
    while len(out) < 4 and time.monotonic() < end:
        m = client.wait_for(lambda m: m.timestamp == status_msg.timestamp, timeout_s=0.2)
        if m is not None:
            out[m.device_name] = m
    return out


def assert_bundle_matches(got, rec, ts):
    """A frame's messages ``got`` (by device name) against its ``reconstruct`` record ``rec``: a failed
    frame has no wire; else status, wire, uncertainty and tip, all stamped ``ts``, the wire's points
    within ``MATCH_MM`` and the uncertainty to its decimals. Returns ``(points, reference)`` or None."""
    if not rec["success"]:
        assert igtl.DEVICE_WIRE not in got
        return None
    assert set(got) == {igtl.DEVICE_STATUS, igtl.DEVICE_WIRE, igtl.DEVICE_UNCERTAINTY, igtl.DEVICE_TIP}
    for m in got.values():
        assert abs(m.timestamp - ts) < 1e-6, m.device_name
    ref = np.asarray(rec["points_lps_mm"])
    pts = got[igtl.DEVICE_WIRE].points
    assert pts.shape == ref.shape
    assert np.abs(pts - ref).max() <= MATCH_MM
    unc = np.array(got[igtl.DEVICE_UNCERTAINTY].string.split(), float)
    np.testing.assert_allclose(unc, rec["uncertainty_mm"], atol=UNC_DECIMALS_MM)
    return pts, ref


# --------------------------------------------------------------------------------------
# the stream matches reconstruct
# --------------------------------------------------------------------------------------
def test_streamed_wires_match_reconstruct(setup, live_out, frames):
    _, report = live_out
    recs = report["frames"]
    assert len(recs) == len(frames) and sum(r["success"] for r in recs) >= 3, [r["message"] for r in recs]
    with serving(setup) as (server, runner, _), igtl.IGTLClient(HOST, server.port) as client:
        t0 = time.time() - 100.0
        for k, (frame, rec) in enumerate(zip(frames, recs)):
            ts = t0 + 0.1 * k + 0.012345  # any source time stamp: it must come back on every message
            client.send(image_message(frame, ts))  # sent one at a time: none is dropped
            msg, st = next_status(client)
            assert st["frame"] == k and abs(msg.timestamp - ts) < 1e-6
            assert st["verdict"] == rec["verdict"], (st, rec["verdict_message"])
            assert st["space"] == "LPS" and st["dropped"] == 0
            got = bundle_after(client, msg)
            matched = assert_bundle_matches(got, rec, ts)
            if matched is None:
                continue
            pts, ref = matched
            assert np.abs(pts - ref).max() <= FLOAT32_MM  # in fact: the same wire, in float32
            [ids] = got[igtl.DEVICE_WIRE].polylines()  # one polyline, proximal -> distal
            np.testing.assert_array_equal(ids, np.arange(len(ref)))
            tip = np.asarray(got[igtl.DEVICE_TIP].matrix, float)
            np.testing.assert_allclose(tip[:3, 3], ref[-1], atol=FLOAT32_MM)
            np.testing.assert_allclose(tip[:3, :3] @ tip[:3, :3].T, np.eye(3), atol=1e-5)
            chord = ref[-1] - ref[np.nonzero(np.linalg.norm(ref[-1] - ref, axis=1) >= igtl.TIP_DIRECTION_MM)[0][-1]]
            np.testing.assert_allclose(tip[:3, 2], chord / np.linalg.norm(chord), atol=2e-4)  # 1e-4 mm rounding / 2 mm
        time.sleep(0.3)
    s = runner.summary
    assert (s.frames_in, s.processed, s.dropped) == (len(frames), len(frames), 0)
    assert s.ok + s.uncertain == sum(r["success"] for r in recs)
    assert len(s.latency_sent_s) == len(frames) and all(0 < x < WAIT_S for x in s.latency_sent_s)


def test_track_motion_streams_the_engines_motion_tracked_wires(setup, frames):
    """``live --track-motion``: the wires of ``live.Session(track_motion=True)`` on the same frames."""
    ref = list(live.Session(setup.tree, setup.frames_carm, setup.pose, registration_covariance=setup.covariance,
                            track_motion=True).run(frames))
    assert any(fr.motion is not None for fr in ref)  # the pose was updated from the frames
    with serving(setup, track_motion=True) as (server, runner, _), igtl.IGTLClient(HOST, server.port) as client:
        for k, (frame, fr) in enumerate(zip(frames, ref)):
            client.send(image_message(frame, 7000.0 + k))
            msg, st = next_status(client)
            assert st["verdict"] == fr.verdict.value and ("motion" in st) == (fr.motion is not None)
            if fr.motion is not None:
                assert st["motion"]["verdict"] == fr.motion.verdict.value
            got = bundle_after(client, msg)
            if fr:
                np.testing.assert_allclose(got[igtl.DEVICE_WIRE].points, fr.wire3d.points_lps_mm, atol=FLOAT32_MM)
    assert runner.summary.dropped == 0


def test_ras_space_flips_points_and_tip():
    """``--space ras``: what 3D Slicer reads as RAS is the LPS wire with x and y negated."""
    from guidewire3d import reconstruction
    from guidewire3d.xray.orderedwire import OrderedWire

    pts = np.array([[10.0, -20.0, 30.0], [11.0, -20.0, 31.0], [12.0, -19.0, 33.0], [12.5, -18.0, 35.0]])
    w3 = _wire3d(pts, np.full(4, 0.5))
    fr = live.FrameResult(7, OrderedWire(points_uv_px=np.zeros((4, 2)), success=True, message="ok"), w3, Verdict.OK,
                          "ok", None, 0.01, 1234.5)
    lps = {m.device_name: m for m in igtl.frame_messages(fr)}
    ras = {m.device_name: m for m in igtl.frame_messages(fr, space=igtl.Space.RAS)}
    assert igtl.status_of(ras[igtl.DEVICE_STATUS])["space"] == "RAS"
    np.testing.assert_allclose(ras[igtl.DEVICE_WIRE].points, pts * [-1, -1, 1])
    np.testing.assert_allclose(lps[igtl.DEVICE_WIRE].points, pts)
    f = np.diag([-1.0, -1.0, 1.0, 1.0])
    np.testing.assert_allclose(ras[igtl.DEVICE_TIP].matrix, f @ lps[igtl.DEVICE_TIP].matrix @ f, atol=1e-6)
    assert np.isclose(np.linalg.det(ras[igtl.DEVICE_TIP].matrix[:3, :3]), 1.0)
    for m in ras.values():
        assert m.timestamp == 1234.5
    # --points: the same wire as a POINT message, diameter twice the 1-sigma uncertainty
    [pm] = [m for m in igtl.frame_messages(fr, space=igtl.Space.RAS, points=True)
            if m.device_name == igtl.DEVICE_POINTS]
    packed = pm.pack()
    back = pyigtl.PointMessage()
    back.unpack(pyigtl.MessageBase.parse_header(packed[:58]), packed[58:])
    np.testing.assert_allclose(back.positions, pts * [-1, -1, 1], atol=1e-5)
    np.testing.assert_allclose(back.diameters, 1.0, atol=1e-6)
    # a frame without a wire sends its status only
    failed = live.FrameResult(8, OrderedWire(points_uv_px=np.zeros((0, 2)), success=False, message="no"),
                              reconstruction.Wire3D.failed("no wire"), Verdict.FAILED, "no wire", None, 0.0, 99.0)
    [only] = igtl.frame_messages(failed)
    assert only.device_name == igtl.DEVICE_STATUS and igtl.status_of(only)["verdict"] == "failed"


def test_guidewire_polydata_bytes_follow_the_openigtlink_spec():
    """What Slicer's OpenIGTLinkIF unpacks (igtl_polydata): read here with struct alone, not pyigtl."""
    import struct

    from guidewire3d.xray.orderedwire import OrderedWire

    pts = np.array([[1.5, -2.0, 3.25], [2.0, -2.5, 4.0], [2.5, -2.0, 5.5]])
    fr = live.FrameResult(0, OrderedWire(points_uv_px=np.zeros((3, 2)), success=True, message="ok"),
                          _wire3d(pts, [0.1, 0.2, 0.3]), Verdict.OK, "ok", None, 0.0, 1700000000.25)
    [wire] = [m for m in igtl.frame_messages(fr) if m.device_name == igtl.DEVICE_WIRE]
    raw = wire.pack()
    version, mtype, device, sec, frac, size, crc = struct.unpack(">H12s20sIIQQ", raw[:58])
    body = raw[58:]
    assert (version, mtype.rstrip(b"\0"), device.rstrip(b"\0")) == (1, b"POLYDATA", b"Guidewire")
    assert sec == 1700000000 and abs(frac / 2**32 - 0.25) < 1e-6 and size == len(body)
    assert crc == pyigtl.messages.CRC64(body)  # CRC-64/ECMA-182, as OpenIGTLink checks it
    head = struct.unpack(">10I", body[:40])
    n = len(pts)
    assert head == (n, 0, 0, 1, 4 * (n + 1), 0, 0, 0, 0, 0)  # points; one line cell; no attributes
    xyz = np.frombuffer(body[40:40 + 12 * n], ">f4").reshape(n, 3)
    np.testing.assert_allclose(xyz, pts, atol=1e-6)
    cell = np.frombuffer(body[40 + 12 * n:], ">u4")
    np.testing.assert_array_equal(cell, [n, 0, 1, 2])


# --------------------------------------------------------------------------------------
# bad frames, bad clients, disconnects
# --------------------------------------------------------------------------------------
def test_bad_frames_give_a_status_and_the_server_goes_on(setup, frames):
    nan_frame = np.array(frames[0], copy=True)
    nan_frame[100, 200] = np.nan
    with serving(setup) as (server, runner, thread), igtl.IGTLClient(HOST, server.port) as client:
        # not OpenIGTLink at all: that connection is closed, the server goes on
        with __import__("socket").create_connection((HOST, server.port), timeout=5) as raw:
            raw.sendall(b"GET / HTTP/1.1\r\n" + b"x" * 200)
        client.send(pyigtl.StringMessage("hello", device_name="Chat"))  # not a frame: ignored
        cases = [(np.zeros((100, 80), np.float32), "frame size (100, 80) differs"),
                 (nan_frame, "1 non-finite pixels"),
                 (np.zeros((3, 20, 30), np.float32), "expected a 2D frame")]  # a volume
        for k, (bad, why) in enumerate(cases):
            client.send(image_message(bad, 1000.0 + k))
            msg, st = next_status(client)
            assert st["verdict"] == "failed" and why in st["message"], st
            assert msg.timestamp == pytest.approx(1000.0 + k, abs=1e-6)
        client.send(image_message(frames[0], 2000.0))
        msg, st = next_status(client)
        assert st["verdict"] in ("ok", "uncertain") and st["failed"] == len(cases), st
        assert igtl.DEVICE_WIRE in bundle_after(client, msg)
        assert thread.is_alive()
    assert runner.summary.failed == len(cases) and runner.summary.processed == len(cases) + 1


def test_a_client_disconnect_and_reconnect_keeps_the_server_running(setup, frames):
    with serving(setup) as (server, runner, thread):
        for k in range(2):  # the first client goes away mid-stream, the second one connects afresh
            client = igtl.IGTLClient(HOST, server.port, reconnect=False)
            try:
                client.send(image_message(frames[k], 3000.0 + k))
                msg, st = next_status(client)
                assert st["frame"] == k and igtl.DEVICE_WIRE in bundle_after(client, msg)
            finally:
                client.close()
            end = time.monotonic() + 10
            while server.n_clients and time.monotonic() < end:
                time.sleep(0.02)
            assert server.n_clients == 0
        # a frame with no client connected is processed, and its bundle goes nowhere
        runner.process(sources.Frame(frames[2], time.time(), "direct"))
        assert thread.is_alive() and server.n_connections == 2
    assert runner.summary.processed == 3


def test_a_busy_server_keeps_its_clients():
    """Frames in and results out on the same connection while the processing holds the GIL: the
    client stays connected (sends must not change the socket timeout under the reader's recv)."""
    box, stop = sources.LatestFrame(), threading.Event()
    server = igtl.IGTLServer(HOST, 0, on_message=lambda m: box.put(sources.Frame(m.image, m.timestamp)))

    def busy_loop():
        k = 0
        while not stop.is_set():
            if box.take(0.05) is None:
                continue
            x = 0
            for i in range(1_000_000):  # pure Python: holds the GIL as parts of the 2D and 3D steps do
                x += i
            server.broadcast(igtl.pack([pyigtl.StringMessage(f"result {k}", device_name="Result")]))
            k += 1

    worker = threading.Thread(target=busy_loop, daemon=True)
    worker.start()
    try:
        with igtl.IGTLClient(HOST, server.port) as client:
            frame = np.zeros((1, 512, 512), np.uint16)
            end = time.monotonic() + 4.0
            while time.monotonic() < end:
                client.send(pyigtl.ImageMessage(frame, device_name="Image", timestamp=time.time()))
                time.sleep(1 / 30)
            assert client.wait_for(lambda m: m.device_name == "Result", timeout_s=5) is not None
            assert client.n_connects == 1 and server.n_connections == 1
    finally:
        stop.set()
        worker.join(5)
        server.close()
    assert box.n_in >= 30


def test_frames_faster_than_processing_are_dropped_and_counted(setup, frames):
    n = 12
    with serving(setup) as (server, runner, _), igtl.IGTLClient(HOST, server.port) as client:
        stamps = [5000.0 + k for k in range(n)]
        for k, ts in enumerate(stamps):  # a burst: each frame arrives well before the previous one is done
            client.send(image_message(frames[k % len(frames)], ts))
        last = None
        end = time.monotonic() + WAIT_S
        while time.monotonic() < end:  # until the newest frame's status arrives
            m = client.wait_for(lambda m: m.device_name == igtl.DEVICE_STATUS, timeout_s=1.0)
            if m is not None:
                last = m
                if m.timestamp == stamps[-1]:
                    break
        assert last is not None and last.timestamp == stamps[-1], "the newest frame was not processed"
        st = igtl.status_of(last)
    s = runner.summary
    assert s.frames_in == n and s.dropped >= 1
    assert s.processed + s.dropped == s.frames_in  # every frame is either processed or counted as dropped
    assert st["frames_in"] == n and st["dropped"] == s.dropped and st["processed"] == s.processed


# --------------------------------------------------------------------------------------
# the mailbox and the other sources
# --------------------------------------------------------------------------------------
def test_latest_frame_mailbox_keeps_one_frame_and_counts_the_rest():
    box = sources.LatestFrame()
    assert box.take(0.01) is None
    for k in range(5):
        box.put(sources.Frame(k, float(k)))
    assert (box.n_in, box.n_dropped) == (5, 4)
    assert box.take(0.01).image == 4 and box.take(0.01) is None
    box.skipped(3)
    assert (box.n_in, box.n_dropped) == (8, 7)


@pytest.mark.parametrize("shape", [(1, 6, 5), (6, 5, 1), (6, 5, 3), (1, 6, 5, 4)])
def test_check_frame_accepts_the_openigtlink_layouts(shape):
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 255, shape).astype(np.uint8)
    f, why = sources.check_frame(img, (6, 5))
    assert why == "" and f.shape == (6, 5) and f.dtype == np.float32
    if shape[-1] in (3, 4) and len(shape) >= 3:
        rgb = img.reshape(6, 5, -1)[..., :3].astype(float)
        np.testing.assert_allclose(f, rgb @ [0.299, 0.587, 0.114], atol=1e-3)
    else:
        np.testing.assert_array_equal(f, img.reshape(6, 5))


def test_folder_source_delivers_the_newest_new_file(tmp_path):
    cv2 = pytest.importorskip("cv2")

    watched, staging = tmp_path / "frames", tmp_path / "staging"
    watched.mkdir()
    staging.mkdir()

    def write(name, value):  # written elsewhere, then renamed: a complete file appears
        cv2.imwrite(str(staging / f"{name}.png"), np.full((6, 5), value, np.uint8))
        os.replace(staging / f"{name}.png", watched / f"{name}.png")

    write("f000", 1)  # already there: the past, not the live stream
    box, stop = sources.LatestFrame(), threading.Event()
    src = sources.FolderSource(watched, carm=None)
    src.start(box, stop)
    try:
        time.sleep(0.1)
        assert box.take(0.05) is None
        write("f001", 2)
        f = box.take(5.0)
        assert f is not None and f.source == "f001.png" and float(f.image[0, 0]) == 2.0
        taken = 1
        for k in range(2, 8):
            write(f"f{k:03d}", k + 1)
        newest = None
        end = time.monotonic() + 5
        while time.monotonic() < end and (newest is None or newest.source != "f007.png"):
            g = box.take(0.2)
            if g is not None:
                newest, taken = g, taken + 1
        assert newest is not None and newest.source == "f007.png" and float(newest.image[0, 0]) == 8.0
        assert box.n_in == 7 and box.n_in == taken + box.n_dropped
    finally:
        stop.set()
        assert src.done.wait(5)


def test_video_source_paces_a_file_at_its_frame_rate(tmp_path):
    cv2 = pytest.importorskip("cv2")
    path = tmp_path / "run.avi"
    fps, n = 25.0, 6
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (40, 30), False)
    if not w.isOpened():
        pytest.skip("no MJPG writer in this OpenCV build")
    for k in range(n):
        w.write(np.full((30, 40), 30 * k + 20, np.uint8))
    w.release()
    box, stop = sources.LatestFrame(), threading.Event()
    src = sources.VideoSource(path, carm=None)
    assert src.fps == pytest.approx(fps)
    got = []
    src.start(box, stop)
    try:
        end = time.monotonic() + 10
        while time.monotonic() < end and not (src.done.is_set() and box.n_in == len(got) + box.n_dropped):
            f = box.take(0.2)
            if f is not None:
                got.append(f)
    finally:
        stop.set()
        assert src.done.wait(5)
    assert box.n_in == n and len(got) + box.n_dropped == n
    levels = [float(np.median(f.image)) for f in got]
    assert levels == sorted(levels) and abs(levels[-1] - (30 * (n - 1) + 20)) <= 3  # in order, the last one last
    stamps = [f.timestamp for f in got]
    assert all(b - a >= 0.5 / fps for a, b in zip(stamps, stamps[1:]))  # paced, not as fast as it decodes
    with pytest.raises(InputError, match="cannot open"):
        sources.VideoSource(tmp_path / "missing.avi", carm=None)


def test_setup_from_the_inputs_is_the_one_reconstruct_made(setup, small_case_dir):
    """``live --cta --roadmap`` runs the same stages as ``reconstruct``: the same tree and pose."""
    d = small_case_dir
    fresh = stream.setup_from_inputs(d / "ct", d / "roadmap.dcm")
    np.testing.assert_allclose(fresh.tree.points_lps_mm, setup.tree.points_lps_mm, atol=1e-9)
    np.testing.assert_allclose(fresh.pose.matrix, setup.pose.matrix, atol=1e-9)
    np.testing.assert_allclose(fresh.covariance, setup.covariance, rtol=1e-6, atol=1e-12)
    assert fresh.frames_carm.to_dict() == setup.frames_carm.to_dict()


# --------------------------------------------------------------------------------------
# the command line
# --------------------------------------------------------------------------------------
def test_cli_live_replay_stops_by_itself_at_max_frames(live_out, small_case_dir, capsys):
    from guidewire3d.app.cli import main

    out, _ = live_out
    before = signal.getsignal(signal.SIGINT)
    rc = main(["live", "--from", str(out), "--replay", str(small_case_dir / "frames.dcm"), "--fps", "50",
               "--loop", "--max-frames", "5", "--port", "0", "--segmenter", "ridge"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "listening on 127.0.0.1:" in text and "5 processed" in text, text
    assert signal.getsignal(signal.SIGINT) is before  # the handler is given back


def test_cli_live_bad_setup_is_one_line_exit_2(tmp_path, capsys):
    from guidewire3d.app.cli import main

    assert main(["live", "--from", str(tmp_path / "nowhere")]) == 2
    assert "no such output folder" in capsys.readouterr().err
    assert main(["live"]) == 2
    assert "--from OUT" in capsys.readouterr().err
    assert main(["view", "--live", "localhost:notaport"]) == 2
    assert "HOST:PORT" in capsys.readouterr().err


def test_ctrl_c_stops_cleanly_and_prints_the_summary(live_out, small_case_dir):
    out, _ = live_out
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "guidewire3d.app.cli", "live", "--from", str(out), "--replay",
           str(small_case_dir / "frames.dcm"), "--fps", "10", "--loop", "--port", "0", "--duration", "300"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        port = None
        end = time.monotonic() + WAIT_S
        while port is None and time.monotonic() < end:
            line = proc.stdout.readline()
            if not line:
                break
            if "listening on" in line:
                port = int(line.split("listening on ")[1].split()[0].rsplit(":", 1)[1])
        assert port is not None, proc.stderr.read() if proc.poll() is not None else "no 'listening on' line"
        with igtl.IGTLClient(HOST, port) as client:  # a viewer: receives, sends nothing
            n = 0
            while n < 2:
                m = client.wait_for(lambda m: m.device_name == igtl.DEVICE_WIRE, timeout_s=WAIT_S)
                assert m is not None
                n += 1
        proc.send_signal(signal.SIGINT)
        rest, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    summary = [ln for ln in rest.splitlines() if "frames in" in ln]
    assert summary and "processed" in summary[0] and "dropped" in summary[0] and "failed" in summary[0], rest
    assert "latency" in summary[0] and "median" in summary[0], rest
    assert "Traceback" not in err, err


# --------------------------------------------------------------------------------------
# the viewer follows a live session (headless)
# --------------------------------------------------------------------------------------
def _broadcast_until(server, payload, done: threading.Event, period_s=0.05, limit_s=60.0):
    end = time.monotonic() + limit_s
    while not done.is_set() and time.monotonic() < end:
        server.broadcast(payload)
        time.sleep(period_s)


def test_viewer_follows_the_live_wire_offscreen(live_out, tmp_path):
    pytest.importorskip("pyvista")
    from guidewire3d.xray.orderedwire import OrderedWire
    from guidewire3d.viewer import app

    out, report = live_out
    rec = [r for r in report["frames"] if r["success"]][-1]  # not frame 0, which the viewer opens with
    pts, unc = np.asarray(rec["points_lps_mm"]), np.asarray(rec["uncertainty_mm"])
    w3 = _wire3d(pts, unc)
    fr = live.FrameResult(3, OrderedWire(points_uv_px=np.zeros((2, 2)), success=True, message="ok"), w3, Verdict.OK,
                          "ok", None, 0.01, time.time())
    payload = igtl.pack(igtl.frame_messages(fr, space=igtl.Space.RAS))  # the viewer converts back to LPS

    with igtl.IGTLServer(HOST, 0) as server:
        ctl, handles = app.open_viewer(out, size_px=(400, 300), off_screen=True, persist=False)
        try:
            with igtl.IGTLClient(HOST, server.port) as client:
                follower = app.LiveFollower(handles.wire, client, status_text=handles.status_text)
                before = np.array(handles.wire.polyline.points, copy=True)
                done = threading.Event()
                t = threading.Thread(target=_broadcast_until, args=(server, payload, done), daemon=True)
                t.start()
                end = time.monotonic() + 30
                while follower.n_updates == 0 and time.monotonic() < end:
                    follower.poll()
                    time.sleep(0.02)
                done.set()
                t.join(5)
            assert follower.n_updates >= 1 and follower.status["frame"] == 3
            shown = np.asarray(handles.wire.polyline.points)
            assert shown.shape == pts.shape and not np.allclose(before[:1], shown[:1])
            np.testing.assert_allclose(shown, pts, atol=FLOAT32_MM)
            np.testing.assert_allclose(handles.wire.polyline.point_data["uncertainty_mm"], unc, atol=UNC_DECIMALS_MM)
            assert handles.wire.actor.GetVisibility()
            handles.plotter.render()
            b = handles.wire.actor.GetBounds()  # the tube is drawn around the streamed wire
            assert b[0] <= pts[:, 0].min() and pts[:, 0].max() <= b[1]
            assert b[4] <= pts[:, 2].min() and pts[:, 2].max() <= b[5]
        finally:
            handles.plotter.close()

        # `guidewire3d view OUT --live HOST:PORT --screenshot PNG`: the first streamed wire, offscreen
        done = threading.Event()
        t = threading.Thread(target=_broadcast_until, args=(server, payload, done), daemon=True)
        t.start()
        try:
            shot = tmp_path / "live.png"
            assert app.run_live(f"{HOST}:{server.port}", out_dir=out, size_px=(400, 300), screenshot=shot,
                                wait_s=30) == 0
        finally:
            done.set()
            t.join(5)
        assert shot.is_file() and shot.stat().st_size > 1000
