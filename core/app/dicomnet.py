"""Studies received over the DICOM network: ``guidewire3d listen --port 11112 --store DIR``.

:class:`StudyReceiver` is a C-STORE SCP (pynetdicom) bound to 127.0.0.1 by default. Every
instance received is written to ``STORE/<StudyInstanceUID>/<SeriesInstanceUID>/<SOPInstanceUID>.dcm``
(through a temporary file renamed into place). A study is reconstructed into ``OUT/<study>/``
(``batch.run_study``: the same call, the same output rules as ``reconstruct``) once it has a CT
series and an XA run and no instance arrived for ``quiet_s`` seconds, or at once on
:meth:`StudyReceiver.reconstruct_now` (``SIGUSR1`` from the command line). A study that receives
more instances after its reconstruction is reconstructed again (its output folder replaced), and
so is a study of the store whose files changed while no session ran; one whose output was made
with other options than this session's is refused as ``batch`` refuses it (:meth:`_needs_redo`).
Reconstructions run one at a time in a background thread, so receiving goes on meanwhile; each
adds its row to ``OUT/summary.csv`` (the format of ``batch``). ``access_lps_mm`` (``--access-lps``)
is every study's access point, as ``reconstruct --access-lps`` takes it.
"""
from __future__ import annotations

import os
import queue
import re
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from guidewire3d.app import batch
from guidewire3d.app.batch import writable_folder
from guidewire3d.errors import InputError
from guidewire3d.vesseltree import check_access

__all__ = ["StudyReceiver", "add_cli_options", "cli_listen"]

DEFAULT_AE_TITLE = "GUIDEWIRE3D"
DEFAULT_QUIET_S = 30.0
_UID = re.compile(r"^[0-9][0-9.]{0,63}$")  # a DICOM UID: digits and dots, at most 64 characters

# C-STORE statuses (PS3.4 B.2.3)
STATUS_SUCCESS = 0x0000
STATUS_OUT_OF_RESOURCES = 0xA700
STATUS_CANNOT_UNDERSTAND = 0xC000


@dataclass
class _StudyState:
    instances: int = 0
    last_arrival: float = 0.0          # time.monotonic() of the newest instance
    reconstructed_at: int = -1         # ``instances`` when the last reconstruction started
    queued: bool = False
    waiting_reported: str = ""         # the last "not complete" message logged
    checked_at: int = -1               # ``instances`` when it was last found not complete


class StudyReceiver:
    """A DICOM C-STORE receiver that reconstructs the studies it receives.

    Parameters
    ----------
    store_dir : path
        Where instances are filed (``<study>/<series>/<sop>.dcm``).
    out_dir : path
        Where reconstructions go (``<study>/`` as ``reconstruct`` writes it, and ``summary.csv``).
    port : int
        TCP port (0: a free one, see :attr:`port`).
    host : str
        Address to bind (default 127.0.0.1: this machine only).
    quiet_s : float
        A study is complete when no instance of it arrived for this long.
    auto : bool
        Reconstruct complete studies by themselves (else only on :meth:`reconstruct_now`).
    access_lps_mm : (3,) array_like of float, optional
        Where the wire enters the vessels (LPS mm), for every study: its tree is rooted at its point
        nearest to it and ``report.json`` records it (``reconstruct --access-lps``).
    """

    def __init__(self, store_dir, out_dir, *, port: int = 11112, host: str = "127.0.0.1",
                 ae_title: str = DEFAULT_AE_TITLE, quiet_s: float = DEFAULT_QUIET_S, auto: bool = True,
                 images: bool = True, access_lps_mm=None, log=None):
        if not 0 <= int(port) <= 65535:
            raise InputError(f"--port {port}: expected 0..65535")
        if not (quiet_s >= 0):
            raise InputError(f"--quiet-seconds {quiet_s}: expected a non-negative number")
        title = str(ae_title).strip()
        if not 1 <= len(title) <= 16 or not title.isascii() or "\\" in title:
            raise InputError(f"--ae-title {ae_title!r}: expected 1-16 ASCII characters without '\\'")
        self.access_lps_mm = None if access_lps_mm is None else tuple(float(c) for c in check_access(access_lps_mm))
        self.store_dir = Path(os.path.abspath(store_dir))
        self.out_dir = Path(os.path.abspath(out_dir))
        writable_folder(self.store_dir, "--store folder")
        writable_folder(self.out_dir, "--out folder")
        self.host, self._port, self.ae_title = host, int(port), title
        self.quiet_s, self.auto, self.images = float(quiet_s), bool(auto), bool(images)
        self._log = log
        self._lock = threading.Lock()
        self._queue_lock = threading.Lock()  # one caller at a time decides what to queue
        self._studies: dict[str, _StudyState] = {}
        self._jobs: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self._server = None
        self._threads: list[threading.Thread] = []
        self.busy_with: str | None = None  # the study being reconstructed now
        self.rows: list[dict] = []         # summary rows of the reconstructions done, in order

    # ---- life cycle -----------------------------------------------------------------
    @property
    def port(self) -> int:
        """The port the server listens on (the actual one when started with port 0)."""
        return int(self._server.server_address[1]) if self._server is not None else self._port

    def start(self) -> "StudyReceiver":
        """Start the server (non-blocking) and the threads that watch and reconstruct studies."""
        from pynetdicom import AE, evt
        from pynetdicom.presentation import (
            StoragePresentationContexts,
            VerificationPresentationContexts,
        )

        ae = AE(ae_title=self.ae_title)
        ae.supported_contexts = list(StoragePresentationContexts) + list(VerificationPresentationContexts)
        ae.maximum_pdu_size = 0  # no limit
        try:
            self._server = ae.start_server((self.host, self._port), block=False,
                                           evt_handlers=[(evt.EVT_C_STORE, self._on_store)])
        except OSError as e:
            raise InputError(f"--port {self._port}: cannot listen on {self.host}:{self._port} ({e.strerror or e})") \
                from None
        self._ae = ae
        self._say(f"listening on {self.host}:{self.port} as {self.ae_title}; filing into {self.store_dir}, "
                  f"reconstructing into {self.out_dir}"
                  + ("" if self.access_lps_mm is None else
                     f"; access point {','.join(f'{v:g}' for v in self.access_lps_mm)} LPS mm"))
        self._scan_store()
        for target, name in ((self._watch, "gw3d-watch"), (self._work, "gw3d-reconstruct")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def stop(self, *, wait: bool = True, timeout: float | None = None) -> None:
        """Stop receiving; with ``wait``, let a running reconstruction finish (up to ``timeout`` s).
        Queued reconstructions that did not start are dropped (their instances stay in the store)."""
        self._stop.set()
        if self._server is not None:
            self._server.shutdown()
        self._jobs.put(None)
        if wait:
            for t in self._threads:
                t.join(timeout)

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # ---- receiving --------------------------------------------------------------------
    def _say(self, msg: str) -> None:
        if self._log is not None:
            self._log(msg)

    def _on_store(self, event) -> int:
        try:
            ds = event.dataset
            uids = [str(ds.get(kw, "") or "").strip() for kw in ("StudyInstanceUID", "SeriesInstanceUID",
                                                                   "SOPInstanceUID")]
        except Exception as e:  # noqa: BLE001 - a data set that cannot be decoded is refused, not fatal
            self._say(f"refused an instance from {_peer(event)}: cannot decode it ({e})")
            return STATUS_CANNOT_UNDERSTAND
        for kw, uid in zip(("StudyInstanceUID", "SeriesInstanceUID", "SOPInstanceUID"), uids):
            if not _UID.match(uid):
                self._say(f"refused an instance from {_peer(event)}: {kw} {uid!r} is not a DICOM UID")
                return STATUS_CANNOT_UNDERSTAND
        study, series, sop = uids
        folder = self.store_dir / study / series
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{sop}.", suffix=".part", dir=folder)
            try:
                with os.fdopen(fd, "wb") as f:
                    f.write(event.encoded_dataset(include_meta=True))
                os.replace(tmp, folder / f"{sop}.dcm")
            except BaseException:
                if os.path.exists(tmp):
                    os.unlink(tmp)
                raise
        except OSError as e:
            self._say(f"cannot file {sop} of study {study}: {e.strerror or e}")
            return STATUS_OUT_OF_RESOURCES
        with self._lock:
            st = self._studies.setdefault(study, _StudyState())
            st.instances += 1
            st.last_arrival = time.monotonic()
            if st.instances == 1:
                self._say(f"receiving study {study} from {_peer(event)}")
        return STATUS_SUCCESS

    def _scan_store(self) -> None:
        """Studies already in the store (an earlier session) are looked at as ``batch`` looks at a
        rerun's studies. One without an output, or whose store files differ from the ones its output
        was made from (instances filed after its reconstruction), is treated as received now: it is
        reconstructed after the quiet period like a new one, its folder replaced (as when more
        instances arrive). One made from the same files with other options than this session's
        (another access point, say: ``batch.finished_row``), or whose output cannot be compared, is
        left as it is: the log says why, and ``summary.csv`` records it ``failed`` as ``batch`` does."""
        now = time.monotonic()
        for d in sorted(self.store_dir.iterdir()):
            if not (d.is_dir() and _UID.match(d.name)):
                continue
            if (self.out_dir / d.name / batch.REPORT_NAME).is_file() and not self._needs_redo(d):
                continue
            n = sum(1 for p in d.rglob("*.dcm") if not p.name.startswith("."))
            if n:
                with self._lock:
                    self._studies[d.name] = _StudyState(instances=n, last_arrival=now)

    def _needs_redo(self, study_dir: Path) -> bool:
        """Whether the finished study of ``study_dir`` is reconstructed again: its store files changed
        since its output was made. If not, a study made otherwise than this session asks is refused as
        ``batch`` refuses it (logged, recorded ``failed`` in ``summary.csv``, its folder untouched)."""
        try:
            (spec,) = batch.group_dicom_tree(study_dir, access_lps_mm=self.access_lps_mm)
        except (InputError, ValueError):
            return False
        folder = self.out_dir / spec.study
        try:
            report = batch.read_report(folder)
        except InputError:
            report = None  # finished_row refuses it
        changes = batch.input_changes(spec, report) if report is not None and spec.error is None else None
        if changes:
            self._say(f"study {study_dir.name}: its files in the store changed since {folder} was made "
                      f"({changes[0][1]}): reconstructing it again")
            return True
        summary = batch.read_summary(self.out_dir / batch.SUMMARY_NAME)
        row = batch.finished_row(spec, self.out_dir, summary.get(spec.study), images=self.images,
                                 files=changes is None)
        if row is None:
            return True
        if row["status"] == batch.FAILED:
            self._say(f"study {study_dir.name} is left as it is: {row['error']}")
        if row["status"] == batch.FAILED or (summary.get(spec.study) or {}).get("status") == batch.FAILED:
            self._record(row)  # refused now, or no longer refused (made as this session asks)
        return False

    def _record(self, row: dict) -> None:
        """Put ``row`` into ``OUT/summary.csv`` (in place of the study's earlier row)."""
        with self._lock:
            summary = batch.read_summary(self.out_dir / batch.SUMMARY_NAME)
            summary[row["study"]] = row
            try:
                batch.write_summary(self.out_dir / batch.SUMMARY_NAME, list(summary.values()))
            except OSError as e:
                self._say(f"cannot write {self.out_dir / batch.SUMMARY_NAME}: {e.strerror or e}")

    # ---- deciding and reconstructing --------------------------------------------------
    def pending(self) -> list[str]:
        """Studies with instances not yet reconstructed."""
        with self._lock:
            return [s for s, st in self._studies.items() if st.instances != st.reconstructed_at]

    def reconstruct_now(self, study: str | None = None) -> list[str]:
        """Queue the pending studies (or ``study``) that are complete, without waiting for the quiet
        period; returns those queued."""
        return self._queue_complete(None if study is None else [study], force=True)

    def _watch(self) -> None:
        tick = min(1.0, max(0.05, self.quiet_s / 4))
        while not self._stop.wait(tick):
            if self.auto:
                self._queue_complete(None, force=False)

    def _queue_complete(self, studies, *, force: bool) -> list[str]:
        with self._queue_lock:
            return self._queue_complete_locked(studies, force=force)

    def _queue_complete_locked(self, studies, *, force: bool) -> list[str]:
        now = time.monotonic()
        queued = []
        with self._lock:
            cands = [(s, st) for s, st in self._studies.items() if studies is None or s in studies]
            cands = [(s, st, st.instances) for s, st in cands if not st.queued and st.instances != st.reconstructed_at
                     and (force or (now - st.last_arrival >= self.quiet_s and st.instances != st.checked_at))]
        for s, st, n in cands:  # n: the instances on disk before the folder is read (more may arrive meanwhile)
            try:
                (spec,) = batch.group_dicom_tree(self.store_dir / s, access_lps_mm=self.access_lps_mm)
            except (InputError, ValueError) as e:  # nothing readable yet, or more than one study inside
                spec, err = None, str(e)
            else:
                err = spec.error
            if err:
                st.checked_at = n  # looked at again when more arrive (or on demand)
                if st.waiting_reported != err:
                    self._say(f"study {s} is not complete yet: {err}")
                    st.waiting_reported = err
                continue
            with self._lock:
                st.queued = True
            self._jobs.put((s, spec, n))
            queued.append(s)
        return queued

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None or self._stop.is_set():
                return
            study, spec, n = job
            self.busy_with = study
            self._say(f"reconstructing study {study} ({n} instances)")
            try:
                row = batch.run_study(spec, self.out_dir, images=self.images, replace=True)
            except Exception as e:  # noqa: BLE001 - one study's crash must not stop the receiver
                row = {"study": study, "status": batch.FAILED,
                       "error": " ".join(f"{e.__class__.__name__}: {e}".split())}
            with self._lock:
                st = self._studies[study]
                st.reconstructed_at = n
                st.queued = False
                st.waiting_reported = ""
                self.rows.append(row)
            self._record(row)
            self.busy_with = None
            what = (f"registration {row.get('verdict')} ({row.get('residual_px')} px), "
                    f"{row.get('frames_reconstructed')}/{row.get('frames_total')} frames"
                    if row.get("status") in (batch.DONE, batch.NOT_RECONSTRUCTED) else row.get("error"))
            self._say(f"study {study}: {row.get('status')}: {what} -> {self.out_dir / study}")


def _peer(event) -> str:
    try:
        a = event.assoc.requestor
        return f"{a.ae_title} at {a.address}:{a.port}"
    except Exception:  # noqa: BLE001
        return "a peer"


# --------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------
def add_cli_options(p) -> None:
    p.add_argument("--port", type=int, default=11112, help="TCP port (default 11112; 0 picks a free one)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1, this machine only; 0.0.0.0 for a network)")
    p.add_argument("--store", required=True, metavar="DIR", help="where received instances are filed "
                   "(DIR/<StudyInstanceUID>/<SeriesInstanceUID>/<SOPInstanceUID>.dcm)")
    p.add_argument("--out", default=None, metavar="OUT",
                   help="where reconstructions go (OUT/<study>/, OUT/summary.csv; default: STORE/../<store>-out)")
    p.add_argument("--ae-title", default=DEFAULT_AE_TITLE,
                   help=f"this receiver's AE title (default {DEFAULT_AE_TITLE})")
    p.add_argument("--quiet-seconds", type=float, default=DEFAULT_QUIET_S, metavar="S",
                   help=f"a study is complete when nothing new arrived for S seconds (default {DEFAULT_QUIET_S:g})")
    p.add_argument("--on-demand", action="store_true",
                   help="reconstruct only when told (kill -USR1 <pid>), not after the quiet period")
    p.add_argument("--no-images", action="store_true", help="skip screenshot/overlay/metrics PNGs")


def cli_listen(args) -> int:
    import signal

    def say(msg):
        print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)

    store = Path(args.store)
    out = Path(args.out) if args.out else store.with_name(f"{store.name}-out")
    rx = StudyReceiver(store, out, port=args.port, host=args.host, ae_title=args.ae_title,
                       quiet_s=args.quiet_seconds, auto=not args.on_demand, images=not args.no_images,
                       access_lps_mm=getattr(args, "access_lps", None), log=say)
    rx.start()
    if hasattr(signal, "SIGUSR1"):
        def on_usr1(signum, frame):
            queued = rx.reconstruct_now()
            say(f"SIGUSR1: queued {', '.join(queued) if queued else 'nothing (no complete study pending)'}")

        signal.signal(signal.SIGUSR1, on_usr1)
    def stop_signal(signum, frame):
        raise KeyboardInterrupt

    # Ctrl-C, and SIGTERM from a service manager, stop cleanly (also when started in the background,
    # where a shell leaves SIGINT ignored)
    signal.signal(signal.SIGINT, stop_signal)
    signal.signal(signal.SIGTERM, stop_signal)
    say(f"pid {os.getpid()}: Ctrl-C stops" + ("; kill -USR1 reconstructs the complete studies now"
                                             if hasattr(signal, "SIGUSR1") else ""))
    try:
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    rx.stop(wait=False)
    if rx.busy_with:
        say(f"stopped receiving; waiting for the reconstruction of {rx.busy_with} to finish (Ctrl-C again abandons "
            "it: its output folder is not written)")
        try:
            for t in rx._threads:
                t.join()
        except KeyboardInterrupt:
            study = rx.busy_with
            if study:  # its staging folder goes (the next run would remove it anyway: its owner is dead)
                import shutil

                shutil.rmtree(rx.out_dir / f".{study}.staging", ignore_errors=True)
            say(f"abandoned the reconstruction of {study}")
            sys.stderr.flush()
            os._exit(130)  # the reconstruction thread cannot be stopped; the process ends without it
    left = rx.pending()
    say("stopped" + (f"; not reconstructed: {', '.join(left)} (they stay in the store; the next `listen` on it "
                     "reconstructs them)" if left else ""))
    return 0
