"""``guidewire3d live`` with two planes (issues 19 and 23): two OpenIGTLink streams, one per device
name, paired by source time stamp, each pair through ``biplane.BiplaneSession``.

Every socket is on 127.0.0.1 and every wait is bounded in time. The reference is the biplane
``reconstruct`` (``biplane.run_to_outdir``) on the same frame pairs of a ``phantom --biplane`` case,
and the simulator's true wire where the two cannot be the same (a plane left out).
"""
from __future__ import annotations

import contextlib
import json
import threading
import time

import numpy as np
import pytest

from guidewire3d import io, metrics
from guidewire3d.app import biplane, igtl, sources, stream
from guidewire3d.errors import InputError
from test_live_server import assert_bundle_matches, bundle_after, next_status

pyigtl = pytest.importorskip("pyigtl")

ONE_VIEW_MEAN_MM = 2.0  # a single-view wire (vessel prior for the depth) against the true wire, as test_biplane
WAIT_S = 120.0  # per pair on a loaded 2-core machine
HOST = "127.0.0.1"
DEV_A, DEV_B = stream.DEFAULT_DEVICES


# --------------------------------------------------------------------------------------
# fixtures
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def bcase_dir(tmp_path_factory):
    """``phantom --biplane``: seed 3, 3 frame pairs, plane B 90 deg from plane A."""
    from guidewire3d.app.cli import main

    out = tmp_path_factory.mktemp("live_biplane") / "case"
    assert main(["phantom", "--out", str(out), "--seed", "3", "--frames", "3", "--biplane"]) == 0
    return out


@pytest.fixture(scope="module")
def bout(bcase_dir, tmp_path_factory):
    """The biplane ``reconstruct`` of that case: the output folder and its report."""
    d = bcase_dir
    out = tmp_path_factory.mktemp("live_biplane_out") / "out"
    biplane.run_to_outdir(d / "ct", [d / "roadmap.dcm", d / "roadmap_b.dcm"], [d / "frames.dcm", d / "frames_b.dcm"],
                          out, images=False, progress=False)
    return out, json.loads((out / "report.json").read_text())


@pytest.fixture(scope="module")
def bframes(bcase_dir):
    """Both planes' live frames exactly as ``reconstruct`` read them."""
    return io.read_xa(bcase_dir / "frames.dcm").frames, io.read_xa(bcase_dir / "frames_b.dcm").frames


@pytest.fixture(scope="module")
def bsetup(bout):
    return stream.setup_from_outdir(bout[0])


@contextlib.contextmanager
def serving(setup, *, devices=stream.DEFAULT_DEVICES, timeout_s=sources.DEFAULT_PLANE_TIMEOUT_S, **runner_kw):
    """A biplane live server on a free port, its processing loop in a thread (as ``cli_live`` wires it)."""
    session = biplane.BiplaneSession(setup.tree, setup.frames_carms, setup.pose,
                                     registration_covariance=setup.covariance)
    stream.warm_up_biplane(session)
    mailbox = sources.PairedFrames(timeout_s=timeout_s)
    ignored = []

    def on_message(msg):
        if msg.message_type != "IMAGE":
            return
        plane = dict(zip(devices, sources.PLANES)).get(msg.device_name)
        if plane is None:
            ignored.append(msg.device_name)
            return
        mailbox.put(plane, sources.Frame(msg.image, float(msg.timestamp), f"igtl:{msg.device_name}"))

    server = igtl.IGTLServer(HOST, 0, on_message=on_message)
    runner = stream.BiplaneRunner(session, server, mailbox, devices=devices, ignored=lambda: len(ignored),
                                  duration_s=600.0, **runner_kw)
    stop = threading.Event()
    thread = threading.Thread(target=runner.run, args=(stop,), daemon=True)
    thread.start()
    try:
        yield server, runner, thread
    finally:
        stop.set()
        thread.join(timeout=30)
        server.close()
        session.close()


def image_message(frame, ts, device):
    return pyigtl.ImageMessage(np.asarray(frame)[None], device_name=device, timestamp=ts)


def _true_wire(bcase_dir, t):
    from guidewire3d.phantom import load_truth

    truth = load_truth(bcase_dir)
    return np.asarray(truth.wire_lps_mm[t])[truth.wire_visible[t]]


# --------------------------------------------------------------------------------------
# the stream of pairs matches the biplane reconstruct
# --------------------------------------------------------------------------------------
def test_streamed_pairs_match_biplane_reconstruct(bsetup, bout, bframes):
    _, report = bout
    recs = report["frames"]
    fa, fb = bframes
    assert bsetup.biplane and len(recs) == len(fa) == len(fb)
    assert sum(r["biplane"]["views"] == "AB" for r in recs) >= 2, [r["biplane"] for r in recs]
    with serving(bsetup) as (server, runner, _), igtl.IGTLClient(HOST, server.port) as client:
        client.send(image_message(fa[0], 50.0, "Image"))  # another device name: ignored, counted
        t0 = time.time() - 100.0
        for k, rec in enumerate(recs):
            ts = t0 + 0.1 * k + 0.012345
            ts_b = ts + 0.004  # plane B's grabber stamps a little later: within half the frame period
            client.send(image_message(fb[k], ts_b, DEV_B))  # plane B first: the order of arrival does not matter
            client.send(image_message(fa[k], ts, DEV_A))
            msg, st = next_status(client)
            assert st["frame"] == k and abs(msg.timestamp - ts) < 1e-6  # the pair's time stamp is plane A's
            assert abs(st["timestamp_b"] - ts_b) < 1e-6
            assert st["views"] == rec["biplane"]["views"] and st["fallback"] == rec["biplane"]["fallback"]
            assert st["verdict"] == rec["verdict"], (st, rec["verdict_message"])
            assert st["planes"]["A"] == {"device": DEV_A, "frames_in": k + 1, "dropped": 0}
            assert st["planes"]["B"] == {"device": DEV_B, "frames_in": k + 1, "dropped": 0}
            assert st["ignored"] == 1 and st["dropped"] == 0
            for plane in "ab":
                ref = rec["biplane"][f"projection_error_px_{plane}"]
                got = st["projection_error_px"][plane]
                assert (got is None) == (ref is None) and (ref is None or abs(got - ref) < 1e-3)
            got = bundle_after(client, msg)
            matched = assert_bundle_matches(got, rec, ts)
            if matched is None:
                continue
            _, ref = matched
            np.testing.assert_allclose(np.asarray(got[igtl.DEVICE_TIP].matrix)[:3, 3], ref[-1], atol=1e-3)
        time.sleep(0.3)
    s = runner.summary
    assert s.processed == len(recs) and s.two_view == sum(r["biplane"]["views"] == "AB" for r in recs)
    assert s.planes_in == {"A": len(recs), "B": len(recs)} and s.planes_dropped == {"A": 0, "B": 0}
    assert s.alone == {"A": 0, "B": 0} and s.ignored == 1
    assert "pairs processed" in s.line() and "plane B: 3 frames in, 0 dropped" in s.line()


def test_plane_b_stops_and_plane_a_goes_on_alone(bsetup, bframes, bcase_dir):
    """Plane B switched off after the first pair: plane A's frames are reconstructed alone after the
    timeout (``views: A``, the reason in the status), and pairs come back with plane B."""
    fa, fb = bframes
    timeout = 0.4
    with serving(bsetup, timeout_s=timeout) as (server, runner, thread), \
            igtl.IGTLClient(HOST, server.port) as client:
        client.send(image_message(fa[0], 100.0, DEV_A))
        client.send(image_message(fb[0], 100.0, DEV_B))
        _, st = next_status(client)
        assert st["views"] == "AB"
        for k in (1, 2):  # plane B is silent now
            ts = 100.0 + 0.1 * k
            t_sent = time.monotonic()
            client.send(image_message(fa[k], ts, DEV_A))
            msg, st = next_status(client)
            waited = time.monotonic() - t_sent
            assert abs(msg.timestamp - ts) < 1e-6 and st["timestamp_b"] is None
            assert st["views"] == "A" and st["fallback"].startswith("one view (plane A only): plane B: no frame from "
                                                                     "plane B for"), st
            assert st["message"].startswith("one view (plane A only)") and st["verdict"] in ("ok", "uncertain")
            assert st["projection_error_px"]["b"] is None and st["projection_error_px"]["a"] < 3.0
            assert waited < timeout + WAIT_S  # bounded: never stalled waiting for plane B
            got = bundle_after(client, msg)
            e = metrics.wire_errors_mm(got[igtl.DEVICE_WIRE].points, _true_wire(bcase_dir, k))
            assert e["mean_error_mm"] < ONE_VIEW_MEAN_MM, e
        # plane B is back: pairs again
        client.send(image_message(fb[2], 101.0, DEV_B))
        client.send(image_message(fa[2], 101.0, DEV_A))
        msg, st = next_status(client)
        assert st["views"] == "AB" and st["fallback"] == "" and abs(msg.timestamp - 101.0) < 1e-6
        e = metrics.wire_errors_mm(bundle_after(client, msg)[igtl.DEVICE_WIRE].points, _true_wire(bcase_dir, 2))
        assert e["mean_error_mm"] < 1.0, e
        assert thread.is_alive()
    s = runner.summary
    assert s.processed == 4 and s.alone == {"A": 2, "B": 0} and s.one_view["A"] == 2
    assert s.planes_in == {"A": 4, "B": 2} and s.planes_dropped == {"A": 0, "B": 0}
    assert "2 processed without the other plane" in s.line()


def test_a_bad_frame_in_one_plane_leaves_that_plane_out(bsetup, bframes):
    fa = bframes[0]
    with serving(bsetup) as (server, runner, _), igtl.IGTLClient(HOST, server.port) as client:
        client.send(image_message(fa[1], 200.0, DEV_A))
        client.send(image_message(np.zeros((100, 80), np.float32), 200.0, DEV_B))
        msg, st = next_status(client)
        assert st["views"] == "A" and "plane B: bad frame: frame size (100, 80) differs" in st["fallback"], st
        assert igtl.DEVICE_WIRE in bundle_after(client, msg)
        both_bad = np.zeros((100, 80), np.float32)
        client.send(image_message(both_bad, 201.0, DEV_A))
        client.send(image_message(both_bad, 201.0, DEV_B))
        _, st = next_status(client)
        assert st["verdict"] == "failed" and st["views"] == "" and "plane A: bad frame" in st["message"], st
    assert runner.summary.failed == 1


# --------------------------------------------------------------------------------------
# the pairing mailbox
# --------------------------------------------------------------------------------------
class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def _f(ts, name=""):
    return sources.Frame(None, ts, name)


def _conserved(m: sources.PairedFrames):
    for p in sources.PLANES:
        assert m.n_in[p] == m.n_used[p] + m.n_dropped[p] + m.waiting(p), p


def test_pairs_are_the_newest_within_the_tolerance_and_stale_frames_are_counted_per_plane():
    clock = _Clock()
    m = sources.PairedFrames(clock=clock)
    period = 1 / 15
    for k in range(4):  # plane A at 15 fps; plane B 10 ms later, its frame 3 not arrived yet
        m.put("A", _f(10.0 + k * period, f"a{k}"))
        if k < 3:
            m.put("B", _f(10.0 + k * period + 0.010, f"b{k}"))
    assert m.tolerance_s == pytest.approx(period / 2)  # half the measured frame period
    pair = m.take(0)
    assert (pair.a.source, pair.b.source, pair.reason) == ("a2", "b2", "") and pair.complete
    assert pair.timestamp == pair.a.timestamp
    assert m.n_dropped == {"A": 2, "B": 2} and m.waiting("A") == 1 and m.waiting("B") == 0  # a3 waits for b3
    _conserved(m)
    assert m.take(0) is None  # a3 alone is not a pair, and plane B is not late yet
    m.put("B", _f(10.0 + 3 * period + 0.040, "b3-late"))  # 40 ms > 33 ms: not a3's partner
    assert m.take(0) is None
    m.put("B", _f(10.0 + 4 * period, "b4"))
    m.put("A", _f(10.0 + 4 * period + 0.002, "a4"))
    pair = m.take(0)
    assert (pair.a.source, pair.b.source) == ("a4", "b4")
    assert m.n_dropped == {"A": 3, "B": 3} and m.n_pairs == 2
    _conserved(m)
    # an explicit tolerance
    t = sources.PairedFrames(tolerance_s=0.050, clock=clock)
    t.put("A", _f(1.0))
    t.put("B", _f(1.045))
    assert t.take(0).complete


def test_senders_without_time_stamps_still_pair_the_newest_frames():
    """Every frame stamped 0 (a sender that does not stamp): the newest frame of each plane pair."""
    m = sources.PairedFrames(clock=_Clock())
    for k in range(3):
        m.put("A", _f(0.0, f"a{k}"))
        m.put("B", _f(0.0, f"b{k}"))
    pair = m.take(0)
    assert (pair.a.source, pair.b.source) == ("a2", "b2") and m.n_dropped == {"A": 2, "B": 2}
    _conserved(m)


def test_a_silent_plane_does_not_stall_the_other_and_nothing_queues():
    clock = _Clock()
    m = sources.PairedFrames(timeout_s=0.5, keep=4, clock=clock)
    m.put("A", _f(1.0, "a0"))
    m.put("B", _f(1.0, "b0"))
    assert m.take(0).complete
    for k in range(1, 11):  # plane B switched off; plane A goes on
        clock.t += 0.05
        m.put("A", _f(1.0 + 0.05 * k, f"a{k}"))
    assert m.waiting("A") == 4  # bounded: the oldest were dropped and counted
    assert m.n_dropped["A"] == 6
    clock.t = 0.45
    assert m.take(0) is None  # not yet: plane B has been silent for 0.45 s
    clock.t = 0.55
    lone = m.take(0)
    assert lone.a.source == "a10" and lone.b is None and lone.reason == "no frame from plane B for 0.6 s"
    assert m.n_alone == {"A": 1, "B": 0} and m.waiting("A") == 0
    _conserved(m)
    clock.t = 0.6
    m.put("A", _f(1.6, "a11"))
    assert m.take(0).a.source == "a11"  # plane B still left out: at once, no new wait
    # plane A silent too long: plane B goes on alone
    m.put("B", _f(2.0, "b-back"))
    clock.t = 1.2
    lone = m.take(0)
    assert lone.a is None and lone.b.source == "b-back" and "no frame from plane A" in lone.reason
    assert lone.timestamp == 2.0
    _conserved(m)


def test_after_a_busy_loop_a_frame_waits_for_its_partner():
    """The loop was busy for longer than the timeout (nothing came from either plane meanwhile): the
    next frame of one plane is not taken for a silent other plane; its partner gets the tolerance."""
    clock = _Clock()
    m = sources.PairedFrames(timeout_s=0.5, clock=clock)
    m.put("A", _f(1.0, "a0"))
    m.put("B", _f(1.0, "b0"))
    assert m.take(0).complete
    clock.t = 2.0  # two seconds of processing
    m.put("B", _f(1.1, "b1"))
    assert m.take(0) is None  # plane A "silent" for 2 s, but b1 has just come: it waits for a1
    clock.t = 2.01
    m.put("A", _f(1.1, "a1"))
    pair = m.take(0)
    assert pair.complete and (pair.a.source, pair.b.source) == ("a1", "b1")
    m.put("B", _f(1.2, "b2"))  # a2 never comes: once plane A was silent for the timeout, b2 goes alone
    clock.t = 2.01 + 0.5 - 1e-6
    assert m.take(0) is None
    clock.t = 2.01 + 0.5 + 1e-6
    lone = m.take(0)
    assert lone.b.source == "b2" and "no frame from plane A" in lone.reason


def test_planes_that_never_pair_fall_back_after_the_timeout():
    """Both planes send but their time stamps are 1 s apart (clocks not synchronised): plane A goes
    on alone after the timeout, and says why."""
    clock = _Clock()
    m = sources.PairedFrames(timeout_s=0.5, clock=clock)
    got = []
    for k in range(20):
        clock.t = 0.05 * k
        m.put("A", _f(100.0 + 0.05 * k, f"a{k}"))
        m.put("B", _f(101.0 + 0.05 * k, f"b{k}"))
        p = m.take(0)
        if p is not None:
            got.append(p)
    assert got and all(not p.complete for p in got)
    assert got[0].a is not None and "too far apart" in got[0].reason
    _conserved(m)


def test_take_waits_for_the_timeout_in_real_time():
    m = sources.PairedFrames(timeout_s=0.2)
    m.put("A", _f(5.0, "a"))
    t0 = time.monotonic()
    lone = m.take(5.0)
    waited = time.monotonic() - t0
    assert lone is not None and lone.a.source == "a" and 0.15 < waited < 2.0
    m.close()
    assert m.take(5.0) is None


def test_pair_replay_source_puts_pairs_with_one_time_stamp(bcase_dir):
    runs = [io.read_xa(bcase_dir / "frames.dcm"), io.read_xa(bcase_dir / "frames_b.dcm")]
    src = sources.PairReplaySource(runs, [(0, 0), (1, 1), (2, 2)], fps=200.0)
    m = sources.PairedFrames(tolerance_s=0.001)
    stop = threading.Event()
    src.start(m, stop)
    assert src.done.wait(10.0)
    assert m.n_in == {"A": 3, "B": 3}
    pair = m.take(0)
    assert pair.complete and pair.a.timestamp == pair.b.timestamp and pair.a.source.endswith("#2")
    np.testing.assert_array_equal(pair.b.image, runs[1].frames[2])


# --------------------------------------------------------------------------------------
# setup and command line
# --------------------------------------------------------------------------------------
def test_setup_from_two_roadmaps_is_the_one_reconstruct_made(bsetup, bcase_dir):
    """``live --cta --roadmap A --roadmap B``: the joint registration of ``reconstruct``: same tree,
    pose and both planes' views."""
    d = bcase_dir
    fresh = stream.setup_from_inputs(d / "ct", [d / "roadmap.dcm", d / "roadmap_b.dcm"])
    assert fresh.biplane and bsetup.biplane
    np.testing.assert_allclose(fresh.tree.points_lps_mm, bsetup.tree.points_lps_mm, atol=1e-9)
    np.testing.assert_allclose(fresh.pose.matrix, bsetup.pose.matrix, atol=1e-9)
    np.testing.assert_allclose(fresh.covariance, bsetup.covariance, rtol=1e-6, atol=1e-12)
    assert [c.to_dict() for c in fresh.frames_carms] == [c.to_dict() for c in bsetup.frames_carms]


def test_cli_live_biplane_replay(bout, bcase_dir, capsys):
    from guidewire3d.app.cli import main

    d = bcase_dir
    rc = main(["live", "--from", str(bout[0]), "--replay", str(d / "frames.dcm"), "--replay", str(d / "frames_b.dcm"),
               "--fps", "20", "--port", "0", "--segmenter", "ridge"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "biplane: plane A" in text and "(plane B), 3 pairs at 20 fps" in text, text
    import re

    [(n, n_ab)] = re.findall(r"(\d+) pairs processed \((\d+) from both planes", text)
    [(in_a, drop_a), (in_b, drop_b)] = re.findall(r"plane [AB]: (\d+) frames in, (\d+) dropped", text)
    assert (in_a, in_b) == ("3", "3") and int(n) + int(drop_a) == 3 and int(n) + int(drop_b) == 3, text
    assert int(n) >= 1 and int(n_ab) >= 1, text  # a pair that a newer one replaced while one was processed is dropped


def _near_plane_a_roadmap(bcase_dir, tmp_path, degrees=5.0):
    import pydicom

    a = pydicom.dcmread(bcase_dir / "roadmap.dcm")
    ds = pydicom.dcmread(bcase_dir / "roadmap_b.dcm")
    ds.PositionerPrimaryAngle = float(a.PositionerPrimaryAngle) + degrees
    ds.PositionerSecondaryAngle = float(a.PositionerSecondaryAngle)
    path = tmp_path / "roadmap_b_near.dcm"
    ds.save_as(path)
    return path


def test_cli_live_biplane_bad_input_is_one_line_exit_2(bout, bcase_dir, tmp_path, capsys):
    from guidewire3d.app.cli import main

    d, out = bcase_dir, str(bout[0])
    near = _near_plane_a_roadmap(d, tmp_path)
    cases = [
        (["--from", out, "--roadmap", str(d / "roadmap.dcm"), "--roadmap", str(d / "roadmap_b.dcm")],
         "give --from OUT, or two --roadmap, not both"),
        (["--from", out, "--device-a", "Cam", "--device-b", "Cam"], "both planes are named 'Cam'"),
        (["--from", out, "--device-b", DEV_A], f"both planes are named '{DEV_A}'"),
        (["--cta", str(d / "ct"), "--roadmap", str(d / "roadmap.dcm"), "--roadmap", str(near)],
         "a biplane needs at least 15 deg between the planes"),
        (["--from", out, "--replay", str(d / "frames_b.dcm"), "--replay", str(d / "frames.dcm")],
         "same plane order"),
        (["--from", out, "--replay", str(d / "frames.dcm")], "give --replay twice"),
        (["--from", out, "--video", str(d / "x.mp4")], "--video: not available with two planes"),
        (["--cta", str(d / "ct"), "--roadmap", str(d / "roadmap.dcm"), "--replay", str(d / "frames.dcm"),
          "--replay", str(d / "frames_b.dcm")], "two replays need a biplane setup"),
        (["--cta", str(d / "ct"), "--roadmap", str(d / "roadmap.dcm"), "--device-b", "B"], "--device-b: only with two"),
        (["--from", out, "--roadmap", "a", "--roadmap", "b", "--roadmap", "c"], "not both"),
        (["--cta", str(d / "ct"), "--roadmap", "a", "--roadmap", "b", "--roadmap", "c"], "got 3"),
        (["--from", out, "--pair-tolerance-ms", "0"], "--pair-tolerance-ms"),
    ]
    for argv, why in cases:
        assert main(["live", "--port", "0", *argv]) == 2, argv
        err = capsys.readouterr().err
        assert why in err and len(err.strip().splitlines()) == 1, (argv, err)
    # the near plane's message names its file
    assert main(["live", "--cta", str(d / "ct"), "--roadmap", str(d / "roadmap.dcm"), "--roadmap", str(near)]) == 2
    assert "roadmap_b_near.dcm" in capsys.readouterr().err


def test_pairing_options_are_checked():
    with pytest.raises(InputError, match="tolerance"):
        sources.PairedFrames(tolerance_s=0.0)
    with pytest.raises(InputError, match="timeout"):
        sources.PairedFrames(timeout_s=-1.0)
    with pytest.raises(ValueError, match="plane"):
        sources.PairedFrames().put("C", _f(0.0))
