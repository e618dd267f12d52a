"""`guidewire3d listen`: a phantom study sent over loopback with a pynetdicom client is filed and
reconstructed, and the reconstruction matches the simulator's ground truth."""
import csv
import json
import time

import numpy as np
import pydicom
import pytest

from guidewire3d import metrics
from guidewire3d.app import batch
from guidewire3d.app.dicomnet import StudyReceiver
from guidewire3d.geometry import Pose
from guidewire3d.phantom import load_truth

QUIET_S = 1.0           # the receiver's quiet period in this test
WAIT_S = 300.0          # bound on the wait for the reconstruction (a loaded 2-core host)
MTRE_MM = 2.0           # as tests/test_pipeline.py
MEAN_3D_ERROR_MM = 1.5


def _send(files, port):
    """C-STORE ``files`` to 127.0.0.1:port in one association; the statuses."""
    from pynetdicom import AE
    from pynetdicom.sop_class import CTImageStorage, XRayAngiographicImageStorage

    ae = AE(ae_title="TESTSCU")
    ae.add_requested_context(CTImageStorage)
    ae.add_requested_context(XRayAngiographicImageStorage)
    assoc = ae.associate("127.0.0.1", port, ae_title="GUIDEWIRE3D")
    assert assoc.is_established
    try:
        return [int(assoc.send_c_store(pydicom.dcmread(f)).Status) for f in files]
    finally:
        assoc.release()


def test_study_sent_over_dicom_is_reconstructed(tiny_studies, tmp_path):
    case = tiny_studies["s11"]
    truth = load_truth(case)
    store, out = tmp_path / "store", tmp_path / "out"
    logs = []
    rx = StudyReceiver(store, out, port=0, quiet_s=QUIET_S, images=False, log=logs.append).start()
    try:
        assert rx.port > 0
        # the CT series first: not complete without XA runs, even on demand
        ct = sorted((case / "ct").iterdir())
        assert _send(ct, rx.port) == [0] * len(ct)
        uid = str(pydicom.dcmread(ct[0], stop_before_pixels=True).StudyInstanceUID)
        assert rx.reconstruct_now() == []
        assert any(f"study {uid} is not complete yet" in m and "no XA run" in m for m in logs)
        # then the XA runs (the roadmap, the live frames and the second view)
        xa = [case / "roadmap.dcm", case / "frames.dcm", case / "heldout.dcm"]
        assert _send(xa, rx.port) == [0, 0, 0]
        report = out / uid / "report.json"
        deadline = time.monotonic() + WAIT_S
        while not report.is_file() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert report.is_file(), f"no reconstruction within {WAIT_S} s: {logs}"
    finally:
        rx.stop(timeout=WAIT_S)
    # filed by study and series, one file per instance
    filed = sorted(store.glob(f"{uid}/*/*.dcm"))
    assert len(filed) == len(ct) + len(xa) and not list(store.rglob(".*"))
    assert len({p.parent for p in filed}) == 4  # the CT series and three XA runs
    rep = json.loads(report.read_text())
    # the live frames were chosen (two frames, the roadmap's view), not the second view
    assert pydicom.dcmread(rep["inputs"]["frames"], stop_before_pixels=True).SeriesDescription \
        == pydicom.dcmread(case / "frames.dcm", stop_before_pixels=True).SeriesDescription
    assert rep["registration"]["verdict"] == "ok"
    pose = Pose.from_matrix(np.asarray(rep["pose"]))
    assert metrics.mtre_mm(pose, truth.pose, truth.tree.points_lps_mm) < MTRE_MM
    errs = [metrics.wire_errors_mm(f["points_lps_mm"], truth.wire_lps_mm[f["index"]][truth.wire_visible[f["index"]]])
            ["mean_error_mm"] for f in rep["frames"] if f["success"]]
    assert len(errs) == 2 and np.median(errs) < MEAN_3D_ERROR_MM
    with open(out / batch.SUMMARY_NAME, newline="") as f:
        (row,) = list(csv.DictReader(f))
    assert (row["study"], row["status"], row["frames_reconstructed"]) == (uid, batch.DONE, "2")
    assert rx.pending() == []
    # a later session at another access point leaves the study's output as it is, and says so
    before = {p: p.stat().st_mtime_ns for p in (out / uid).iterdir()}
    access = truth.tree.points_lps_mm[truth.tree.root]
    logs2 = []
    rx2 = StudyReceiver(store, out, port=0, quiet_s=QUIET_S, images=False, access_lps_mm=access,
                        log=logs2.append).start()
    try:
        assert rx2.pending() == []
    finally:
        rx2.stop(timeout=WAIT_S)
    assert any(f"study {uid} is left as it is" in m and "remove the folder" in m for m in logs2), logs2
    assert {p: p.stat().st_mtime_ns for p in (out / uid).iterdir()} == before
    # ... and records it as batch does: failed, why, and the options the folder was made with
    row = batch.read_summary(out / batch.SUMMARY_NAME)[uid]
    assert (row["status"], row["access_lps"], row["frames_reconstructed"]) == (batch.FAILED, "", "2")
    assert row["error"] == (f"{out / uid}: it was made with no access point, this run asks for --access-lps="
                            f"{batch._xyz(access)}: remove the folder to reconstruct it again")
    # a session with the options it was made with reuses it (no longer refused)
    assert _session(store, out, []) == []
    assert batch.read_summary(out / batch.SUMMARY_NAME)[uid]["status"] == batch.SKIPPED
    assert {p: p.stat().st_mtime_ns for p in (out / uid).iterdir()} == before
    # a CT instance filed again with other bytes while no session ran: the study is made again, as
    # when more instances arrive, its folder replaced
    ct_filed = next(p for p in filed if pydicom.dcmread(p, stop_before_pixels=True).Modality == "CT")
    ds = pydicom.dcmread(ct_filed)
    ds.ImageComments = "sent again"
    ds.save_as(ct_filed)
    logs3 = []
    assert _session(store, out, logs3, wait_for=report, after_ns=report.stat().st_mtime_ns) == []
    assert any(f"study {uid}: its files in the store changed since {out / uid} was made" in m
               and "reconstructing it again" in m for m in logs3), logs3
    row = batch.read_summary(out / batch.SUMMARY_NAME)[uid]
    assert (row["status"], row["frames_reconstructed"]) == (batch.DONE, "2")
    rep = json.loads(report.read_text())
    assert rep["registration"]["verdict"] == "ok"
    assert batch.input_changes(batch.group_dicom_tree(store / uid)[0], rep) == []  # made from the files now


def _session(store, out, logs, *, access=None, wait_for=None, after_ns=0):
    """A receiver session on ``store``; with ``wait_for``, until that file is newer than ``after_ns``
    (bounded by WAIT_S). The studies left pending."""
    rx = StudyReceiver(store, out, port=0, quiet_s=0.0, images=False, access_lps_mm=access, log=logs.append).start()
    try:
        deadline = time.monotonic() + WAIT_S
        while wait_for is not None and time.monotonic() < deadline and not (
                wait_for.is_file() and wait_for.stat().st_mtime_ns > after_ns and rx.pending() == []):
            time.sleep(0.2)
    finally:
        rx.stop(timeout=WAIT_S)
    return rx.pending()


def test_bad_options_are_refused(tmp_path):
    with pytest.raises(batch.InputError, match="--ae-title"):
        StudyReceiver(tmp_path / "s", tmp_path / "o", ae_title="A" * 17)
    (tmp_path / "file").write_text("")
    with pytest.raises(batch.InputError, match="file: --store folder exists and is not a folder"):
        StudyReceiver(tmp_path / "file", tmp_path / "o")
    with pytest.raises(batch.InputError, match="--quiet-seconds"):
        StudyReceiver(tmp_path / "s", tmp_path / "o", quiet_s=-1)


@pytest.mark.parametrize("uids", [("1.2.3", "1.2.4", ""), ("../../etc", "1.2.4", "1.2.5"),
                                  ("1.2", "1." + "2" * 70, "1.3")])
def test_instance_without_valid_uids_is_refused(tmp_path, uids):
    from types import SimpleNamespace

    from guidewire3d.app.dicomnet import STATUS_CANNOT_UNDERSTAND

    import warnings

    ds = pydicom.Dataset()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pydicom warns about the invalid UIDs as they are set
        ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.SOPInstanceUID = uids
    logs = []
    rx = StudyReceiver(tmp_path / "store", tmp_path / "out", port=0, log=logs.append)  # not started: the handler alone
    assert rx._on_store(SimpleNamespace(dataset=ds)) == STATUS_CANNOT_UNDERSTAND
    assert list((tmp_path / "store").iterdir()) == [] and rx.pending() == []
    assert len(logs) == 1 and "is not a DICOM UID" in logs[0]
