"""`guidewire3d batch`: many studies on a local Dask cluster, against sequential `reconstruct`."""
import csv
import json
import os
import signal
import threading
import time

import numpy as np
import pytest

from guidewire3d.app import batch
from guidewire3d.app.cli import main
from guidewire3d.io import STAGING_OWNER

KILL_WAIT_S = 240.0  # the killer gives up if no study started within this time (it asserts below)


def _manifest(path, rows, header="study,cta,roadmap,frames"):
    path.write_text(header + "\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))
    return path


def _summary(out):
    with open(out / "summary.csv", newline="") as f:
        return {r["study"]: r for r in csv.DictReader(f)}


def _rows(studies):
    return [(name, d / "ct", d / "roadmap.dcm", d / "frames.dcm") for name, d in studies.items()]


@pytest.fixture(scope="module")
def batch_run(tiny_studies, tmp_path_factory):
    """The four tiny studies and one broken one (a CT slice as roadmap) on 2 local workers; the
    worker that starts the first study is killed (SIGKILL) as soon as it holds a staging folder."""
    tmp = tmp_path_factory.mktemp("batch")
    any_case = next(iter(tiny_studies.values()))
    ct_slice = sorted((any_case / "ct").iterdir())[0]
    manifest = _manifest(tmp / "manifest.csv",
                         _rows(tiny_studies) + [("broken", any_case / "ct", ct_slice, any_case / "frames.dcm")])
    out = tmp / "out"
    killed, stop = [], threading.Event()

    def killer():
        deadline = time.monotonic() + KILL_WAIT_S
        while not stop.is_set() and time.monotonic() < deadline:
            for st in sorted(out.glob(".*.staging")) if out.is_dir() else ():
                try:
                    owner = json.loads((st / STAGING_OWNER).read_text())
                except (OSError, ValueError):
                    continue  # being created
                pid = int(owner["pid"])
                assert pid != os.getpid()  # a worker process, never this one
                os.kill(pid, signal.SIGKILL)
                killed.append((st.name[1:-len(".staging")], pid))
                return
            time.sleep(0.02)

    t = threading.Thread(target=killer, daemon=True)
    t.start()
    rc = main(["batch", str(manifest), "--out", str(out), "--workers", "2", "--no-images"])
    stop.set()
    t.join(5)
    return rc, manifest, out, killed, ct_slice


@pytest.fixture(scope="module")
def sequential(tiny_studies, tmp_path_factory):
    """`guidewire3d reconstruct` on each study, one after the other, in this process."""
    tmp = tmp_path_factory.mktemp("sequential")
    for name, d in tiny_studies.items():
        rc = main(["reconstruct", "--cta", str(d / "ct"), "--roadmap", str(d / "roadmap.dcm"),
                   "--frames", str(d / "frames.dcm"), "--out", str(tmp / name), "--no-images"])
        assert rc == 0
    return tmp


def test_batch_equals_sequential_reconstruct(batch_run, sequential, tiny_studies):
    rc, _, out, _, _ = batch_run
    assert rc == 1  # the broken study failed; the others went on
    summary = _summary(out)
    for name in tiny_studies:
        a = json.loads((out / name / "report.json").read_text())
        b = json.loads((sequential / name / "report.json").read_text())
        np.testing.assert_array_equal(a["pose"], b["pose"])
        np.testing.assert_array_equal(a["projection_matrix"], b["projection_matrix"])
        assert a["registration"]["verdict"] == b["registration"]["verdict"] == "ok"
        assert len(a["frames"]) == len(b["frames"]) == 2
        for fa, fb in zip(a["frames"], b["frames"]):
            assert fa["success"] == fb["success"] and fa["verdict"] == fb["verdict"]
            np.testing.assert_array_equal(fa["points_lps_mm"], fb["points_lps_mm"])
            np.testing.assert_array_equal(fa["uncertainty_mm"], fb["uncertainty_mm"])
        # the same files as `reconstruct` writes
        assert sorted(p.name for p in (out / name).iterdir()) == sorted(p.name for p in (sequential / name).iterdir())
        row = summary[name]
        assert row["status"] == batch.DONE and row["verdict"] == "ok" and row["error"] == ""
        assert float(row["residual_px"]) == pytest.approx(a["registration"]["mean_residual_px"], abs=1e-4)
        n_ok = sum(f["success"] for f in a["frames"])
        assert (int(row["frames_reconstructed"]), int(row["frames_total"])) == (n_ok, 2)
        assert float(row["seconds"]) > 0 and float(row["peak_rss_mb"]) > 100  # a worker with numpy and torch loaded
    assert list(summary) == [*tiny_studies, "broken"]  # the manifest's order


def test_bad_study_is_recorded_and_the_batch_goes_on(batch_run):
    _, _, out, _, ct_slice = batch_run
    row = _summary(out)["broken"]
    assert row["status"] == batch.FAILED and row["verdict"] == ""
    assert row["error"].startswith(f"{ct_slice}: ") and "\n" not in row["error"]  # names the file
    assert not (out / "broken").exists()


def test_killed_worker_still_completes_the_batch(batch_run):
    _, _, out, killed, _ = batch_run
    assert len(killed) == 1, "no study started on a worker within the wait"
    study, pid = killed[0]
    row = _summary(out)[study]
    assert row["status"] == batch.DONE  # rescheduled on a live worker
    assert not row["worker"].endswith(f":{pid}")  # finished by another process than the killed one
    assert (out / study / "report.json").is_file()
    assert not list(out.glob(".*.staging"))  # the killed run's staging folder was cleaned up


def test_rerun_skips_finished_studies(batch_run, tiny_studies, capsys):
    _, manifest, out, _, _ = batch_run
    before = {n: (out / n / "report.json").stat().st_mtime_ns for n in tiny_studies}
    first = _summary(out)
    rc = main(["batch", str(manifest), "--out", str(out), "--workers", "1", "--no-images"])
    assert rc == 1  # the broken study is tried again, and fails again
    summary = _summary(out)
    for n in tiny_studies:
        assert summary[n]["status"] == batch.SKIPPED
        assert (out / n / "report.json").stat().st_mtime_ns == before[n]
        # what the first run measured is kept
        for k in ("verdict", "residual_px", "frames_reconstructed", "seconds", "peak_rss_mb"):
            assert summary[n][k] == first[n][k], k
    assert summary["broken"]["status"] == batch.FAILED
    assert "5 studies (1 failed, 4 skipped)" in capsys.readouterr().out


# --------------------------------------------------------------------------------------
# manifests and DICOM trees (no cluster)
# --------------------------------------------------------------------------------------
def _one_line_error(capsys):
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("guidewire3d: error: ")
    return err


def test_manifest_missing_column(tmp_path, tiny_studies, capsys):
    m = _manifest(tmp_path / "m.csv", [r[:3] for r in _rows(tiny_studies)], header="study,cta,roadmap")
    assert main(["batch", str(m), "--out", str(tmp_path / "out")]) == 2
    err = _one_line_error(capsys)
    assert str(m) in err and "missing column 'frames'" in err
    assert not (tmp_path / "out").exists()


def test_manifest_missing_file(tmp_path, tiny_studies, capsys):
    rows = _rows(tiny_studies)
    rows[2] = (rows[2][0], rows[2][1], tmp_path / "nope.dcm", rows[2][3])
    m = _manifest(tmp_path / "m.csv", rows)
    assert main(["batch", str(m), "--out", str(tmp_path / "out")]) == 2
    err = _one_line_error(capsys)
    assert f"{m} line 4 (study {rows[2][0]}): roadmap: {tmp_path / 'nope.dcm'}: no such file" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("rows, expected", [
    ([("a", "x", "x", "x"), ("a", "x", "x", "x")], "line 3: study 'a' already on line 2"),
    ([("../a", "x", "x", "x")], "line 2: study '../a' cannot be a folder name"),
    ([("", "x", "x", "x")], "line 2: empty 'study'"),
    ([("a", "", "x", "x")], "line 2 (study a): empty 'cta'"),
    ([("a", "x", "x", "x", "7", "many")], "line 2: 6 fields, the header has 5"),
    ([], "no studies"),
])
def test_malformed_manifests(tmp_path, rows, expected, capsys):
    (tmp_path / "x").write_text("")
    m = _manifest(tmp_path / "m.csv", rows, header="study,cta,roadmap,frames,roadmap_frame")
    assert main(["batch", str(m), "--out", str(tmp_path / "out")]) == 2
    assert expected in _one_line_error(capsys)


def test_manifest_options_and_relative_paths(tmp_path):
    (tmp_path / "d").mkdir()
    for f in ("ct", "r.dcm", "f.dcm"):
        (tmp_path / "d" / f).write_text("")
    m = _manifest(tmp_path / "m.csv", [("a", "d/ct", "d/r.dcm", "d/f.dcm", "3", "ridge", "yes", "ignored")],
                  header="study,cta,roadmap,frames,roadmap_frame,segmenter,force,notes")
    (s,) = batch.read_manifest(m)
    assert (s.cta, s.roadmap, s.frames) == tuple(str(tmp_path / "d" / f) for f in ("ct", "r.dcm", "f.dcm"))
    assert (s.roadmap_frame, s.segmenter, s.force, s.method) == (3, "ridge", True, "vessel")
    m2 = _manifest(tmp_path / "m2.csv", [("a", "d/ct", "d/r.dcm", "d/f.dcm", "unet3")],
                   header="study,cta,roadmap,frames,segmenter")
    with pytest.raises(batch.InputError, match=r"m2.csv line 2 \(study a\): segmenter: expected one of unet, ridge"):
        batch.read_manifest(m2)


def test_dicom_tree_is_grouped_by_study(tiny_studies, tmp_path):
    specs = {s.study: s for s in batch.group_dicom_tree(next(iter(tiny_studies.values())).parent)}
    assert len(specs) == len(tiny_studies)
    import pydicom

    for d in tiny_studies.values():
        uid = str(pydicom.dcmread(d / "frames.dcm", stop_before_pixels=True).StudyInstanceUID)
        s = specs[uid]
        # the roadmap by its description, the live frames: the longest run in the roadmap's view
        # (heldout.dcm, the second view, is not chosen)
        assert (s.cta, s.roadmap, s.frames, s.error) == (str(d / "ct"), str(d / "roadmap.dcm"),
                                                         str(d / "frames.dcm"), None)
        assert s.series_uid == str(pydicom.dcmread(sorted((d / "ct").iterdir())[0]).SeriesInstanceUID)
    # a study without XA runs is returned as failed-to-assemble, not dropped
    only_ct = tmp_path / "tree"
    (only_ct / "ct").mkdir(parents=True)
    for f in sorted((d / "ct").iterdir())[:3]:
        (only_ct / "ct" / f.name).write_bytes(f.read_bytes())
    (only_ct / "notes.txt").write_text("not DICOM")
    (s,) = batch.group_dicom_tree(only_ct)
    assert s.error.endswith("no XA run (expected a roadmap and live frames)")
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("not DICOM")
    with pytest.raises(batch.InputError, match="no DICOM CT or XA files found"):
        batch.group_dicom_tree(tmp_path / "empty")


def _run(path, n, desc="", when="", angles=(0.0, 0.0), order=0):
    return batch._XARun(path, n, desc, when, (order, 0, path), angles)


@pytest.mark.parametrize("runs, expected", [
    # the SeriesDescription names the roadmap
    ([_run("a", 1), _run("b", 12, "Roadmap DSA"), _run("c", 30)], ("b", "c")),
    # no name: the shortest run is the roadmap; the longest in its view the frames
    ([_run("a", 20), _run("b", 1), _run("c", 40, angles=(30.0, 0.0)), _run("d", 10)], ("b", "a")),
    # nothing in the roadmap's view: the longest of any view
    ([_run("a", 1), _run("b", 9, angles=(30.0, 0.0)), _run("c", 5, angles=(-20.0, 10.0))], ("a", "b")),
    # ties: the earliest roadmap, the latest frames
    ([_run("a", 1, when="2"), _run("b", 1, when="1"), _run("c", 8, when="3"), _run("d", 8, when="4")], ("b", "d")),
    # one run: both
    ([_run("a", 10)], ("a", "a")),
])
def test_choose_xa_runs(runs, expected):
    assert batch.choose_xa_runs(runs) == expected


def test_a_multi_frame_ct_counts_its_frames(tiny_studies, tmp_path):
    """A study whose CTA is one multi-frame (enhanced) CT file beside a 3-slice classic series: the multi-frame file,
    many slices in one file, is the CTA."""
    hd = pytest.importorskip("highdicom")
    import pydicom
    from pydicom.uid import generate_uid

    d = next(iter(tiny_studies.values()))
    dss = [pydicom.dcmread(f) for f in sorted((d / "ct").iterdir())]
    for ds in dss:
        ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL"]
    enh = hd.legacy.LegacyConvertedEnhancedCTImage(legacy_datasets=dss, series_instance_uid=generate_uid(),
                                                   series_number=9, sop_instance_uid=generate_uid(), instance_number=1)
    tree = tmp_path / "tree"
    for sub in ("enh", "loc"):
        (tree / sub).mkdir(parents=True)
    enh.save_as(tree / "enh" / "e.dcm", enforce_file_format=True)
    for f in sorted((d / "ct").iterdir())[:3]:
        (tree / "loc" / f.name).write_bytes(f.read_bytes())
    for f in ("roadmap.dcm", "frames.dcm"):
        (tree / f).write_bytes((d / f).read_bytes())
    said = []
    (s,) = batch.group_dicom_tree(tree, log=said.append)
    assert (s.cta, s.series_uid, s.error) == (str(tree / "enh"), str(enh.SeriesInstanceUID), None)
    assert f"({len(dss)} slices)" in said[0]
