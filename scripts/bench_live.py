"""Live-path speed: marginal time per frame after the one-off CTA and registration work.

Per frame: guidewire segmentation, ordered 2D wire, 3D reconstruction (tracking) and the
report entry. Measured over a long simulated sequence, per segmenter mode, and printed as a
table of medians: the whole frame, each stage (``live.FrameResult.stage_seconds``), and the
accuracy of what was measured (Dice of the live masks and median 3D error against the
simulator's truth), so that a faster path is seen to give the same answers.

    .venv/bin/python scripts/bench_live.py --frames 120
    .venv/bin/python scripts/bench_live.py --frames 120 --background-load 2   # a busy host

``--background-load N`` starts N busy processes (pure Python loops, one core each) before the
measurement and stops them at exit (each also stops by itself after ``--background-max-seconds``).
``--modes`` picks modes (default: all three). The host's CPU model and load average (before the
background load starts, and at the end) are printed beside the table.

``--igtl`` measures ``guidewire3d live`` instead (``bench_igtl``): source time stamp -> messages
received by a client, over OpenIGTLink on 127.0.0.1, at 15 and 30 fps input, then a bounded soak
at 30 fps with client reconnects and the server's RSS sampled:

    nice -n 5 .venv/bin/python scripts/bench_live.py --igtl --rate-seconds 40 --soak-seconds 300

``--igtl --biplane`` does the same with two planes (issues 19/23): a ``phantom --biplane`` sequence,
the biplane ``reconstruct`` as the setup, each pair sent as two IMAGE messages (device names
``PlaneA``, ``PlaneB``, one time stamp), latency from the pair's time stamp to its Guidewire
POLYDATA; the drops are counted per plane (``--rates 15`` for the 15 fps pairs only):

    nice -n 5 .venv/bin/python scripts/bench_live.py --igtl --biplane --rates 15 --rate-seconds 40 --soak-seconds 0
"""
from __future__ import annotations

import argparse
import atexit
import os
import subprocess
import sys
import time

import numpy as np

MODES = {"default": ("UNet, ROI tracking (default)", "unet", True),
         "full": ("UNet, full frame", "unet", False),
         "ridge": ("Ridge, ROI tracking", "ridge", True)}
STAGES = ("segmentation", "ordered_wire", "reconstruction")


def start_background_load(n: int, max_seconds: float) -> list:
    """``n`` busy processes (one core each), stopped at exit and by themselves after ``max_seconds``."""
    code = f"import time\nend = time.monotonic() + {float(max_seconds)}\nwhile time.monotonic() < end:\n    pass\n"
    procs = [subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL) for _ in range(max(0, int(n)))]

    def stop():
        for p in procs:
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()

    atexit.register(stop)
    return procs


class _Recording:
    """The session's segmenter, keeping each frame's mask (for the Dice against the truth); it passes on the
    tracked segmenter's look point and second pass (``live.Session.wire2d_of``), so the live path is measured as
    it runs."""

    def __init__(self, seg):
        self.seg, self.masks = seg, []
        self.method = getattr(seg, "method", "custom")

    @property
    def last_mode(self) -> str:
        return getattr(self.seg, "last_mode", "")

    def segment(self, frame, **kw):
        m = self.seg.segment(frame, **kw)
        self.masks.append(m)
        return m

    def segment_again(self, frame, **kw):
        m = self.seg.segment_again(frame, **kw)
        self.masks[-1] = m
        return m

    def reset(self):
        self.seg.reset()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--threads", type=int, default=None, help="inference threads (default: the segmenter's)")
    ap.add_argument("--modes", default="default,full,ridge", help=f"comma-separated, of {', '.join(MODES)}")
    ap.add_argument("--background-load", type=int, default=0, metavar="N",
                    help="run N busy processes during the measurement (a busy host)")
    ap.add_argument("--background-max-seconds", type=float, default=1800.0,
                    help="the busy processes stop by themselves after this long")
    ap.add_argument("--igtl", action="store_true", help="measure `guidewire3d live` over OpenIGTLink (bench_igtl)")
    ap.add_argument("--rate-seconds", type=float, default=40.0, help="--igtl: seconds per input rate (15, 30 fps)")
    ap.add_argument("--soak-seconds", type=float, default=300.0, help="--igtl: soak at 30 fps (0: none)")
    ap.add_argument("--reconnect-seconds", type=float, default=30.0, help="--igtl soak: the client reconnects this often")
    ap.add_argument("--biplane", action="store_true", help="--igtl: two planes (pairs of IMAGE messages, PlaneA/PlaneB)")
    ap.add_argument("--rates", default="15,30", help="--igtl: input rates in frames (pairs) per second, comma-separated")
    args = ap.parse_args()
    if args.igtl:
        return bench_igtl(args)
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    bad = [m for m in modes if m not in MODES]
    if bad or not modes:
        ap.error(f"--modes: expected some of {', '.join(MODES)}, got {args.modes!r}")
    if not 0 <= args.background_load <= 64:
        ap.error("--background-load: expected 0..64 processes")

    from guidewire3d import metrics
    from guidewire3d.app import bench
    from guidewire3d.app import export
    from guidewire3d.xray.roadmap import roadmap_centerline
    from guidewire3d.live import session as live
    from guidewire3d import phantom
    from guidewire3d import registration
    from guidewire3d.cta import vessels3d
    from guidewire3d.xray.segmentation import GuidewireSegmenter, guidewire_mask

    case = phantom.simulate(phantom.PhantomOptions(seed=args.seed, n_frames=args.frames))
    t0 = time.perf_counter()
    ves = vessels3d.extract_vessels(case.volume)
    t_cta = time.perf_counter() - t0
    t0 = time.perf_counter()
    cl = roadmap_centerline(case.roadmap, max_radius_px=float(ves.tree.radius_mm.max()) / case.carm.pixel_at_iso_mm * 1.5)
    reg = registration.register(ves.tree, cl.points_uv_px, case.carm, centerline_radius_px=cl.radius_px)
    t_reg = time.perf_counter() - t0

    load_before = os.getloadavg()
    if args.background_load:
        start_background_load(args.background_load, args.background_max_seconds)
        time.sleep(2.0)  # let them take the cores

    rows = []
    for key in modes:
        name, method, tracking = MODES[key]
        seg = GuidewireSegmenter(method=method, num_threads=args.threads)
        if not tracking:
            seg.segment = lambda frame, _m=method, **_: guidewire_mask(frame, method=_m)  # noqa: E731
        rec = _Recording(seg)
        session = live.Session(ves.tree, case.carm, reg.pose, registration_covariance=reg.covariance_6x6,
                               segmenter=rec)
        session.warm_up(case.frames[0])  # session creation, first-call compilation
        rec.masks.clear()
        lat, ok, stages, results = [], 0, {s: [] for s in STAGES}, []
        t_all = time.perf_counter()
        for fr in session.run(case.frames):
            export.frame_record(fr.index, fr.wire2d, fr.wire3d, fr.seconds, fr)  # the report entry is part of the live path
            lat.append(fr.seconds)
            ok += bool(fr)
            for s in STAGES:
                if s in getattr(fr, "stage_seconds", {}):  # (older versions of the package: none)
                    stages[s].append(fr.stage_seconds[s])
            results.append(fr)
        marginal = (time.perf_counter() - t_all) / len(case.frames)
        # accuracy of what was timed (after the clock): the live masks and 3D wires against the truth
        dice = [metrics.dice(m, case.wire_mask[k]) for k, m in enumerate(rec.masks[:len(case.frames)])]
        err = []
        for fr in results:
            vis = np.asarray(case.wire_visible[fr.index], bool)
            tru = np.asarray(case.wire_lps_mm[fr.index])[vis]
            if fr and len(tru) >= 2:
                err.append(metrics.wire_errors_mm(fr.wire3d.points_lps_mm, tru)["mean_error_mm"])

        def med_ms(v):
            return f"{1000 * float(np.median(v)):.1f}" if v else "n/a"

        rows.append([name, f"{1000 * marginal:.1f}", f"{1.0 / marginal:.1f}", med_ms(lat),
                     f"{1000 * float(np.percentile(lat, 90)):.1f}", *(med_ms(stages[s]) for s in STAGES),
                     f"{100 * float(np.mean(dice)):.2f}", f"{float(np.median(err)):.3f}" if err else "n/a",
                     f"{ok}/{len(case.frames)}", str(getattr(session, "n_segmented_again", "n/a"))])
    load_after = os.getloadavg()
    print(f"live path, {args.frames} frames {case.frames.shape[2]}x{case.frames.shape[1]}, seed {args.seed}; one-off: "
          f"CTA vessels {t_cta:.1f} s, roadmap + registration {t_reg * 1000:.0f} ms")
    print(f"machine: {bench.machine_line()}; load average (1/5/15 min) before "
          f"{' / '.join(f'{x:.2f}' for x in load_before)}, at the end {' / '.join(f'{x:.2f}' for x in load_after)}; "
          f"background load: {args.background_load} busy process(es)")
    print(bench._table(["mode", "marginal ms/frame", "FPS", "median latency ms", "p90 latency ms",
                        "segmentation ms", "ordered wire ms", "3D ms", "mask Dice %", "3D err mm", "frames ok",
                        "segmented again"], rows))
    print("stage columns: medians over frames (live.FrameResult.stage_seconds); the report entry is in the latency, "
          "not in a stage. Dice: the live masks against the simulator's; 3D err: median over frames of the mean "
          "distance to the true wire. Segmented again: frames whose tracked mask was doubted (live.Session.wire2d_of).")
    return 0


# --------------------------------------------------------------------------------------------
# --igtl: guidewire3d live, end to end over OpenIGTLink
# --------------------------------------------------------------------------------------------
def _rss_mb(pid: int) -> float:
    try:
        for line in open(f"/proc/{pid}/status"):
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _igtl_run(out_dir, frames, *, fps: float, seconds: float, reconnect_s: float | None = None,
              rss_every_s: float = 5.0, planes=None) -> dict:
    """Start `guidewire3d live --from OUT` in a process, send ``frames`` (cycled) as OpenIGTLink
    IMAGE messages at ``fps`` for ``seconds``, receive its messages; stop it with SIGINT.

    ``planes``: a biplane OUT's two planes: ``frames`` is then a pair of arrays (plane A's, plane
    B's), each pair sent as two messages of the device names ``planes`` with one time stamp."""
    import signal
    import subprocess
    import sys
    import threading

    import pyigtl

    from guidewire3d.app import igtl

    cmd = [sys.executable, "-m", "guidewire3d.app.cli", "live", "--from", str(out_dir), "--port", "0",
           "--duration", str(seconds + 120)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    lines: list[str] = []
    port_ready = threading.Event()

    def read_stdout():
        for line in proc.stdout:
            lines.append(line.rstrip())
            if "listening on" in line:
                port_ready.set()

    threading.Thread(target=read_stdout, daemon=True).start()
    try:
        if not port_ready.wait(300):
            raise RuntimeError(f"the live server did not start: {lines}")
        port = int([ln for ln in lines if "listening on" in ln][0].split("listening on ")[1].split()[0].rsplit(":", 1)[1])
        client = igtl.IGTLClient("127.0.0.1", port, keep=1 << 14)
        lat_wire, t_wire, statuses, rss = [], [], [], []
        n_sent, n_reconnects = 0, 0
        period = 1.0 / fps
        t_start = time.monotonic()
        t_next, t_rss, t_reconnect = t_start, t_start, t_start + (reconnect_s or 1e18)

        def drain():
            for m in client.messages():
                if m.device_name == igtl.DEVICE_WIRE:
                    lat_wire.append(m.received_at - m.timestamp)
                    t_wire.append(m.received_at)
                elif m.device_name == igtl.DEVICE_STATUS:
                    st = igtl.status_of(m)
                    statuses.append({k: st.get(k) for k in ("frames_in", "processed", "dropped", "failed",
                                                            "processing_ms", "planes", "views")})

        while time.monotonic() - t_start < seconds:
            now = time.monotonic()
            if now >= t_rss:
                rss.append((now - t_start, _rss_mb(proc.pid)))
                t_rss += rss_every_s
            if now >= t_reconnect:  # a client that goes away and comes back
                drain()
                client.close()
                client = igtl.IGTLClient("127.0.0.1", port, keep=1 << 14)
                n_reconnects += 1
                t_reconnect += reconnect_s
            time.sleep(max(0.0, t_next - time.monotonic()))
            t_next += period
            t_grab = time.time()
            if planes is None:
                msgs = [pyigtl.ImageMessage(frames[n_sent % len(frames)][None], device_name="Image", timestamp=t_grab)]
            else:
                msgs = [pyigtl.ImageMessage(f[n_sent % len(f)][None], device_name=name, timestamp=t_grab)
                        for f, name in zip(frames, planes)]
            try:
                for msg in msgs:
                    client.send(msg)
                n_sent += 1
            except ConnectionError:
                pass
            drain()
        time.sleep(1.0)
        drain()
        client.close()
        rss.append((time.monotonic() - t_start, _rss_mb(proc.pid)))
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    summary = next((ln for ln in lines if "frames in" in ln), "")
    last = statuses[-1] if statuses else {}
    lat = np.asarray(lat_wire) * 1000.0
    engine = np.asarray([st["processing_ms"] for st in statuses if st.get("processing_ms") is not None], float)
    thirds = np.array_split(lat, 3) if len(lat) >= 3 else [lat, lat, lat]
    views = [st.get("views") for st in statuses]
    return {"fps": fps, "seconds": seconds, "sent": n_sent, "wires": len(lat), "statuses": len(statuses),
            "planes": last.get("planes"), "two_view": sum(v == "AB" for v in views),
            "frames_in": last.get("frames_in"), "processed": last.get("processed"), "dropped": last.get("dropped"),
            "failed": last.get("failed"), "p50": float(np.percentile(lat, 50)) if len(lat) else float("nan"),
            "p99": float(np.percentile(lat, 99)) if len(lat) else float("nan"),
            "p50_first_third": float(np.median(thirds[0])) if len(lat) else float("nan"),
            "p50_last_third": float(np.median(thirds[-1])) if len(lat) else float("nan"),
            "engine_p50": float(np.median(engine)) if len(engine) else float("nan"),
            "rss": rss, "reconnects": n_reconnects, "server_summary": summary}


class _Precomputed:
    """A stand-in engine that answers every frame with one precomputed result at once: what is
    left of the latency is the streaming (receive, mailbox, messages, send)."""

    def __init__(self, session, frame):
        self.carm = session.carm
        self.result = session.process(frame)

    def process(self, frame, *, index=0, timestamp=float("nan")):
        from dataclasses import replace

        return replace(self.result, index=index, timestamp=timestamp)


def _igtl_transport_only(out_dir, frames, *, fps: float, seconds: float) -> dict:
    """The server in this process with the engine replaced by ``_Precomputed``; a client sends
    ``frames`` at ``fps`` and receives the messages."""
    import threading

    import pyigtl

    from guidewire3d.app import igtl, sources, stream
    from guidewire3d.live import session as live

    st = stream.setup_from_outdir(out_dir)
    session = live.Session(st.tree, st.frames_carm, st.pose, registration_covariance=st.covariance)
    engine = _Precomputed(session, frames[0].astype(np.float32))
    box = sources.LatestFrame()
    server = igtl.IGTLServer("127.0.0.1", 0, on_message=lambda m: box.put(sources.Frame(m.image, m.timestamp)))
    runner = stream.LiveRunner(engine, server, box, duration_s=seconds + 30)
    stop = threading.Event()
    worker = threading.Thread(target=runner.run, args=(stop,), daemon=True)
    worker.start()
    lat = []
    try:
        with igtl.IGTLClient("127.0.0.1", server.port, keep=1 << 14) as client:
            t_next = t0 = time.monotonic()
            k = 0
            while time.monotonic() - t0 < seconds:
                time.sleep(max(0.0, t_next - time.monotonic()))
                t_next += 1.0 / fps
                client.send(pyigtl.ImageMessage(frames[k % len(frames)][None], device_name="Image",
                                                timestamp=time.time()))
                k += 1
                lat += [m.received_at - m.timestamp for m in client.messages() if m.device_name == igtl.DEVICE_WIRE]
            time.sleep(0.5)
            lat += [m.received_at - m.timestamp for m in client.messages() if m.device_name == igtl.DEVICE_WIRE]
    finally:
        stop.set()
        worker.join(10)
        server.close()
    lat = np.asarray(lat) * 1000.0
    s = runner.summary
    return {"sent": k, "processed": s.processed, "dropped": s.dropped, "p50": float(np.median(lat)),
            "p99": float(np.percentile(lat, 99))}


def bench_igtl(args) -> int:
    """``--igtl``: ``guidewire3d live --from OUT`` in its own process, fed over OpenIGTLink."""
    import tempfile
    from pathlib import Path

    from guidewire3d import io
    from guidewire3d.app import bench
    from guidewire3d import phantom
    from guidewire3d.app import pipeline

    tmp = Path(tempfile.mkdtemp(prefix="bench-live-igtl-"))
    rates = [float(r) for r in str(args.rates).split(",") if r.strip()]
    case = phantom.simulate(phantom.PhantomOptions(seed=args.seed, n_frames=args.frames, biplane=args.biplane))
    d = phantom.write_case(case, tmp / "case")
    t0 = time.perf_counter()
    if args.biplane:
        from guidewire3d.app import biplane, stream

        biplane.run_to_outdir(d / "ct", [d / "roadmap.dcm", d / "roadmap_b.dcm"], [d / "frames.dcm", d / "frames_b.dcm"],
                              tmp / "out", images=False, progress=False)
        planes = stream.DEFAULT_DEVICES
        names = ("frames.dcm", "frames_b.dcm")
    else:
        pipeline.run_to_outdir(d / "ct", d / "roadmap.dcm", d / "frames.dcm", tmp / "out", images=False, progress=False)
        planes, names = None, ("frames.dcm",)
    t_setup = time.perf_counter() - t0
    runs = []
    for name in names:
        frames = io.read_xa(d / name).frames
        if np.all(frames == np.round(frames)) and frames.min() >= 0 and frames.max() < 65536:
            frames = frames.astype(np.uint16)  # as a frame grabber sends them (the DICOM's stored values)
        runs.append(frames)
    frames = tuple(runs) if args.biplane else runs[0]
    f0 = runs[0]
    what = "biplane pairs (PlaneA + PlaneB, one time stamp)" if args.biplane else "frames"
    print(f"live over OpenIGTLink, {args.frames}-frame sequence {f0.shape[1]}x{f0.shape[2]} {f0.dtype} (cycled), "
          f"{what}, seed {args.seed}; reconstruct --out for the setup {t_setup:.0f} s; machine: "
          f"{bench.machine_line()}; load average before {' / '.join(f'{x:.1f}' for x in os.getloadavg())}", flush=True)
    rows = []
    plan = [(fps, args.rate_seconds, None) for fps in rates]
    if args.soak_seconds > 0:
        plan.append((30.0, args.soak_seconds, args.reconnect_seconds))
    for fps, seconds, reconnect in plan:
        load0 = os.getloadavg()[0]
        r = _igtl_run(tmp / "out", frames, fps=fps, seconds=seconds, reconnect_s=reconnect, planes=planes)
        load1 = os.getloadavg()[0]
        rss = [m for _, m in r["rss"]]
        rss_first = rss[min(1, len(rss) - 1)] if rss else float("nan")  # after the network's first frames
        name = f"{fps:g} {'pairs/s' if planes else 'fps'}, {seconds:g} s" + (
            f", soak (reconnect every {reconnect:g} s: {r['reconnects']})" if reconnect else "")
        dropped = (" / ".join(str((r["planes"] or {}).get(p, {}).get("dropped")) for p in ("A", "B")) if planes
                   else f"{r['dropped']}")
        rows.append([name, str(r["sent"]), f"{r['processed']}" + (f" ({r['two_view']} AB)" if planes else ""),
                     dropped, f"{r['failed']}",
                     f"{r['p50']:.1f}", f"{r['p99']:.1f}", f"{r['engine_p50']:.1f}",
                     f"{r['p50_first_third']:.1f} -> {r['p50_last_third']:.1f}",
                     f"{rss_first:.0f} -> {rss[-1]:.0f}" if rss else "n/a", f"{load0:.1f} / {load1:.1f}"])
        print(f"  {name}: server: {r['server_summary']}", flush=True)
        print(f"  {name}: server RSS MB every 5 s: {' '.join(f'{m:.0f}' for m in rss)}", flush=True)
    if not planes:
        for fps in rates:
            load0 = os.getloadavg()[0]
            r = _igtl_transport_only(tmp / "out", frames, fps=fps, seconds=min(args.rate_seconds, 20.0))
            rows.append([f"{fps:g} fps, streaming only (engine answers at once)", str(r["sent"]), str(r["processed"]),
                         str(r["dropped"]), "0", f"{r['p50']:.1f}", f"{r['p99']:.1f}", "0", "", "",
                         f"{load0:.1f} / {os.getloadavg()[0]:.1f}"])
    print(bench._table(["input", "pairs sent" if planes else "frames sent", "processed",
                        "dropped A / B" if planes else "dropped", "failed", "latency p50 ms", "p99 ms",
                        "engine p50 ms", "p50 first -> last third", "server RSS MB start -> end",
                        "load avg start / end"], rows))
    print("latency: the frame's (pair's) OpenIGTLink time stamp (set when it is sent) -> its Guidewire POLYDATA "
          "received by the client, same host")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
