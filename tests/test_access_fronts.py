"""`--access-lps` on the other front ends: `batch` (global and per manifest row), `listen` and `view`
on inputs, against `reconstruct --access-lps` on the same tiny simulated study.

One study (seed 11, 2 live frames) and two access points from its ground truth: ``far``, the far end of
the wire's path (the tree is re-rooted there, about 95 mm from the automatic root) and ``entry``, where
the wire enters (the automatic root). Every front end must write the report ``reconstruct`` writes:
the same ``access`` record and ``inputs.access_lps_mm``, the same rooted tree in
``registration_inputs.npz`` and the same pose. Bad values are refused with one line, exit 2, nothing
written.
"""
from __future__ import annotations

import csv
import json
import re
import tempfile
import time

import numpy as np
import pydicom
import pytest

from guidewire3d.app import batch
from guidewire3d.app.cli import main
from guidewire3d.phantom import load_truth
from guidewire3d.vesseltree import VesselTree

SEED = 11  # a tiny study of conftest.TINY_SEEDS (registration ok)
JSON_MM = 1e-3  # mm: points rounded to 3 decimals in report.json
DISTANCE_MM = 0.01  # report.json rounds distance_mm to 0.01 mm
MOVED_MM = 50.0  # the far end's root is at least this far from the entry's (95 mm on this study)
WAIT_S = 300.0  # bound on the wait for the listener's reconstruction (a loaded 2-core host)


def _xyz(p) -> str:
    return ",".join(f"{v:.3f}" for v in p)


def _report(out) -> dict:
    return json.loads((out / "report.json").read_text())


def _tree(out) -> VesselTree:
    z = np.load(out / "registration_inputs.npz")
    return VesselTree(z["tree_points_lps_mm"], z["tree_radius_mm"], z["tree_parent"])


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("guidewire3d: error: "), err
    return err


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """The tiny study, its truth, and the two access points."""
    from guidewire3d.phantom import PhantomOptions, simulate, write_case

    case = write_case(simulate(PhantomOptions(seed=SEED, n_frames=2)), tmp_path_factory.mktemp("fronts") / "case")
    truth = load_truth(case)
    ids = truth.wire_path_point_ids

    def as_typed(p):  # the point as the command lines get it (3 decimals), so that every front end gets the same
        return np.array([float(v) for v in _xyz(p).split(",")])

    return case, as_typed(truth.tree.points_lps_mm[ids[-1]]), as_typed(truth.tree.points_lps_mm[ids[0]])


@pytest.fixture(scope="module")
def reference(study, tmp_path_factory):
    """`reconstruct --access-lps FAR` (ridge: the segmenter changes neither the tree nor the pose)."""
    case, far, _ = study
    out = tmp_path_factory.mktemp("reference") / "out"
    assert main(["reconstruct", "--cta", str(case / "ct"), "--roadmap", str(case / "roadmap.dcm"), "--frames",
                 str(case / "frames.dcm"), "--out", str(out), "--segmenter", "ridge", "--no-images",
                 f"--access-lps={_xyz(far)}"]) == 0
    rep = _report(out)
    tree = _tree(out)
    # the reference itself: the tree rooted at the point nearest FAR, recorded as such
    d = np.linalg.norm(tree.points_lps_mm - far, axis=1)
    assert rep["access"]["root_index"] == tree.root == int(np.argmin(d))
    assert rep["access"]["distance_mm"] == pytest.approx(d.min(), abs=DISTANCE_MM)
    np.testing.assert_allclose(rep["inputs"]["access_lps_mm"], far, atol=JSON_MM)
    return out


def _same_as_reference(out, reference) -> None:
    """``out`` records the access, and holds the rooted tree and pose, exactly as ``reconstruct`` did."""
    rep, ref = _report(out), _report(reference)
    assert rep["access"] == ref["access"]
    assert rep["inputs"]["access_lps_mm"] == ref["inputs"]["access_lps_mm"]
    a, b = _tree(out), _tree(reference)
    assert a.root == b.root == rep["access"]["root_index"]
    np.testing.assert_array_equal(a.parent, b.parent)
    np.testing.assert_array_equal(a.points_lps_mm, b.points_lps_mm)
    np.testing.assert_array_equal(rep["pose"], ref["pose"])
    assert rep["registration"]["verdict"] == ref["registration"]["verdict"] == "ok"


# ------------------------------------------------------------------------------------------
# batch
# ------------------------------------------------------------------------------------------
def _manifest(path, header, rows):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)  # quotes the cells with commas, as a spreadsheet writes them
        w.writerow(header)
        w.writerows(rows)
    return path


@pytest.fixture(scope="module")
def batch_run(study, tmp_path_factory):
    """`batch --access-lps FAR` on two rows of the same study: ``glob`` (empty access_lps: the batch's
    point) and ``entry`` (its own point, which overrides it); one local worker."""
    case, far, entry = study
    tmp = tmp_path_factory.mktemp("batch")
    files = [case / "ct", case / "roadmap.dcm", case / "frames.dcm"]
    m = _manifest(tmp / "m.csv", ["study", "cta", "roadmap", "frames", "segmenter", "access_lps"],
                  [["glob", *files, "ridge", ""], ["entry", *files, "ridge", _xyz(entry)]])
    out = tmp / "out"
    rc = main(["batch", str(m), "--out", str(out), "--workers", "1", "--no-images", f"--access-lps={_xyz(far)}"])
    return rc, out


def test_batch_global_access_is_recorded_as_reconstruct_records_it(batch_run, reference):
    rc, out = batch_run
    assert rc == 0
    with open(out / batch.SUMMARY_NAME, newline="") as f:
        rows = {r["study"]: r for r in csv.DictReader(f)}
    assert [rows[s]["status"] for s in ("glob", "entry")] == [batch.DONE, batch.DONE]
    _same_as_reference(out / "glob", reference)


def test_batch_manifest_access_overrides_the_global_one(batch_run, study):
    _, out = batch_run
    _, far, entry = study
    rep, tree = _report(out / "entry"), _tree(out / "entry")
    np.testing.assert_allclose(rep["inputs"]["access_lps_mm"], entry, atol=JSON_MM)
    np.testing.assert_allclose(rep["access"]["access_lps_mm"], entry, atol=JSON_MM)
    d = np.linalg.norm(tree.points_lps_mm - entry, axis=1)
    assert rep["access"]["root_index"] == tree.root == int(np.argmin(d))
    np.testing.assert_allclose(rep["access"]["root_lps_mm"], tree.points_lps_mm[tree.root], atol=JSON_MM)
    assert rep["access"]["distance_mm"] == pytest.approx(d.min(), abs=DISTANCE_MM)
    # not the batch's point: the root is the entry's, far from where FAR roots the same tree
    glob = _report(out / "glob")["access"]
    assert np.linalg.norm(np.subtract(rep["access"]["root_lps_mm"], glob["root_lps_mm"])) > MOVED_MM


def test_a_rerun_never_reuses_a_study_made_at_another_access(batch_run, study, tmp_path):
    """A finished study is skipped only when its report was made at the access point this run asks for; made at
    another one (or with none), it is ``failed`` with a one-line reason, its folder untouched."""
    import shutil

    _, out0 = batch_run
    case, far, entry = study
    out = tmp_path / "out"
    shutil.copytree(out0, out)
    files = [case / "ct", case / "roadmap.dcm", case / "frames.dcm"]
    m = _manifest(tmp_path / "m.csv", ["study", "cta", "roadmap", "frames", "segmenter", "access_lps"],
                  [["glob", *files, "ridge", ""], ["entry", *files, "ridge", _xyz(entry)]])
    before = (out / "glob" / "report.json").read_bytes()

    def rerun(*extra):
        main(["batch", str(m), "--out", str(out), "--workers", "1", "--no-images", *extra])
        with open(out / batch.SUMMARY_NAME, newline="") as f:
            return {r["study"]: r for r in csv.DictReader(f)}

    rows = rerun(f"--access-lps={_xyz(far)}")  # the same points: both skipped
    assert [rows[s]["status"] for s in ("glob", "entry")] == [batch.SKIPPED, batch.SKIPPED]
    rows = rerun(f"--access-lps={_xyz(entry)}")  # glob now asks for the entry: not the study on disk
    assert rows["glob"]["status"] == batch.FAILED and rows["entry"]["status"] == batch.SKIPPED
    assert "made with --access-lps=" in rows["glob"]["error"] and "remove the folder" in rows["glob"]["error"]
    rows = rerun()  # no access point at all
    assert rows["glob"]["status"] == batch.FAILED and "this run asks for none" in rows["glob"]["error"]
    # another segmenter: not the study on disk either (the access points as made)
    m = _manifest(tmp_path / "m.csv", ["study", "cta", "roadmap", "frames", "segmenter", "access_lps"],
                  [["glob", *files, "unet", ""], ["entry", *files, "ridge", _xyz(entry)]])
    rows = rerun(f"--access-lps={_xyz(far)}")
    assert rows["glob"]["status"] == batch.FAILED and rows["entry"]["status"] == batch.SKIPPED
    assert "segmenter ridge, this run asks for segmenter unet" in rows["glob"]["error"]
    assert (out / "glob" / "report.json").read_bytes() == before


def test_manifest_access_cells_and_the_dicom_tree(study, tmp_path):
    """Empty: the batch's point; ``none``: the automatic root; a point (``,`` quoted, ``;`` or spaces):
    its own, named by its cell in the errors. A DICOM tree: every study gets the batch's point."""
    case, far, entry = study
    files = [case / "ct", case / "roadmap.dcm", case / "frames.dcm"]
    m = _manifest(tmp_path / "m.csv", ["study", "cta", "roadmap", "frames", "access_lps"],
                  [["a", *files, ""], ["b", *files, "None"], ["c", *files, "1.5,-2,3"], ["d", *files, "4; 5 ;6"],
                   ["e", *files, "-7 8 9"]])
    glob = tuple(float(v) for v in far)
    specs = {s.study: s for s in batch.read_manifest(m, access_lps_mm=far)}
    assert {k: s.access_lps_mm for k, s in specs.items()} == {
        "a": glob, "b": None, "c": (1.5, -2.0, 3.0), "d": (4.0, 5.0, 6.0), "e": (-7.0, 8.0, 9.0)}
    assert specs["a"].access_option == "--access-lps"
    assert specs["c"].access_option == f"{m} line 4 (study c): access_lps"
    # without a batch point, an empty cell is no access point
    assert [s.access_lps_mm for s in batch.read_manifest(m)][:2] == [None, None]
    import pydicom

    uid = str(pydicom.dcmread(case / "frames.dcm", stop_before_pixels=True).StudyInstanceUID)
    (s,) = batch.load_studies(case, access_lps_mm=far)
    assert (s.study, s.access_lps_mm, s.access_option) == (uid, glob, "--access-lps")


@pytest.mark.parametrize("cell, match", [
    ("abc", r"line 3 \(study b\): access_lps: expected x,y,z in LPS mm \(quoted: \"x,y,z\"\), or none, got 'abc'"),
    ("1,2", r"line 3 \(study b\): access_lps: expected x,y,z in LPS mm .* got '1,2'"),
    ("1,2,3,4", r"line 3 \(study b\): access_lps: expected x,y,z"),
    ("nan,0,0", r"line 3 \(study b\): access_lps=nan,0,0: not a finite point"),
    (None, r"line 3: 7 fields, the header has 5 \(quote the access_lps cell: \"x,y,z\"\)"),  # 1,2,3 unquoted
])
def test_batch_refuses_a_bad_access_cell_naming_its_row(study, tmp_path, capsys, cell, match):
    case, _, _ = study
    files = [case / "ct", case / "roadmap.dcm", case / "frames.dcm"]
    rows = [["a", *files, ""], ["b", *files, cell]] if cell is not None else [["a", *files, ""], ["b", *files, 1, 2, 3]]
    m = _manifest(tmp_path / "m.csv", ["study", "cta", "roadmap", "frames", "access_lps"], rows)
    out = tmp_path / "out"
    assert main(["batch", str(m), "--out", str(out), "--workers", "1"]) == 2
    err = _one_line_error(capsys)
    assert re.search("^guidewire3d: error: " + re.escape(str(m)) + " " + match, err), err
    assert not out.exists()


@pytest.mark.parametrize("value, match", [
    ("--access-lps=nan,0,0", "--access-lps=nan,0,0: not a finite point"),
    ("--access-lps=1,2", "argument --access-lps: expected x,y,z in mm, got '1,2'"),
])
def test_batch_refuses_a_bad_global_access(study, tmp_path, capsys, value, match):
    case, _, _ = study
    files = [case / "ct", case / "roadmap.dcm", case / "frames.dcm"]
    m = _manifest(tmp_path / "m.csv", ["study", "cta", "roadmap", "frames"], [["a", *files]])
    out = tmp_path / "out"
    assert main(["batch", str(m), "--out", str(out), "--workers", "1", value]) == 2
    assert _one_line_error(capsys).startswith("guidewire3d: error: " + match)
    assert not out.exists()


@pytest.mark.parametrize("where", ["cell", "global"])
def test_a_study_whose_access_is_outside_its_cta_fails_naming_where_it_came_from(study, tmp_path, where):
    """Far outside the CTA (known once the study's CTA is read, on its worker): the study fails with
    ``reconstruct``'s one line, the point named as the manifest cell or ``--access-lps``; no folder."""
    case, _, _ = study
    files = [case / "ct", case / "roadmap.dcm", case / "frames.dcm"]
    m = _manifest(tmp_path / "m.csv", ["study", "cta", "roadmap", "frames", "access_lps"],
                  [["far", *files, "1000,0,0" if where == "cell" else ""]])
    (spec,) = batch.read_manifest(m, access_lps_mm=None if where == "cell" else (1000.0, 0.0, 0.0))
    row = batch.run_study(spec, tmp_path / "out", images=False)
    named = f"{m} line 2 (study far): access_lps" if where == "cell" else "--access-lps"
    assert row["status"] == batch.FAILED
    assert re.match(re.escape(named) + r"=1000,0,0: [0-9]+ mm outside the CTA's field of view", row["error"]), row
    assert not (tmp_path / "out" / "far").exists()


# ------------------------------------------------------------------------------------------
# listen
# ------------------------------------------------------------------------------------------
def test_listen_reconstructs_each_study_at_the_access(study, reference, tmp_path):
    from test_listen import _send  # C-STORE over loopback with a pynetdicom client

    from guidewire3d.app.dicomnet import StudyReceiver

    case, far, _ = study
    files = sorted((case / "ct").iterdir()) + [case / "roadmap.dcm", case / "frames.dcm"]
    logs = []
    rx = StudyReceiver(tmp_path / "store", tmp_path / "out", port=0, auto=False, images=False, access_lps_mm=far,
                       log=logs.append).start()
    try:
        assert _send(files, rx.port) == [0] * len(files)
        uid = str(pydicom.dcmread(case / "frames.dcm", stop_before_pixels=True).StudyInstanceUID)
        assert rx.reconstruct_now() == [uid]
        deadline = time.monotonic() + WAIT_S
        while not rx.rows and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        rx.stop(timeout=WAIT_S)
    assert [r["status"] for r in rx.rows] == [batch.DONE], logs
    assert f"access point {','.join(f'{v:g}' for v in far)} LPS mm" in logs[0]
    _same_as_reference(tmp_path / "out" / uid, reference)


@pytest.mark.parametrize("value, match", [
    ("--access-lps=0,inf,0", "--access-lps=0,inf,0: not a finite point"),
    ("--access-lps=x,y,z", "argument --access-lps: expected x,y,z in mm, got 'x,y,z'"),
])
def test_listen_refuses_a_bad_access_before_listening(tmp_path, capsys, value, match):
    store = tmp_path / "store"
    assert main(["listen", "--store", str(store), "--port", "0", value]) == 2
    assert _one_line_error(capsys).startswith("guidewire3d: error: " + match)
    assert list(tmp_path.iterdir()) == []  # neither the store nor the output folder


# ------------------------------------------------------------------------------------------
# view
# ------------------------------------------------------------------------------------------
def _view_inputs(case):
    return ["--cta", str(case / "ct"), "--roadmap", str(case / "roadmap.dcm"), "--frames", str(case / "frames.dcm")]


def test_view_on_inputs_runs_reconstruct_at_the_access(study, reference, tmp_path, capsys):
    pytest.importorskip("pyvista")
    import cv2

    case, far, _ = study
    out, shot = tmp_path / "out", tmp_path / "shot.png"
    assert main(["view", str(out), *_view_inputs(case), f"--access-lps={_xyz(far)}", "--screenshot", str(shot),
                 "--size", "400x300"]) == 0
    _same_as_reference(out, reference)
    assert cv2.imread(str(shot)).shape == (300, 400, 3)
    assert f"screenshot written to {shot}" in capsys.readouterr().out


def test_view_refuses_the_access_on_a_finished_folder_and_on_live(reference, tmp_path, capsys):
    before = sorted(p.name for p in reference.iterdir())
    shot = tmp_path / "shot.png"
    assert main(["view", str(reference), "--access-lps=1,2,3", "--screenshot", str(shot)]) == 2
    far = ",".join(f"{v:g}" for v in _report(reference)["access"]["access_lps_mm"])
    err = _one_line_error(capsys)
    assert err.startswith(f"guidewire3d: error: --access-lps: {reference} is a finished reconstruction, its vessel "
                          f"tree rooted when it was written (at its access point {far}); give --access-lps with "
                          "--cta, --roadmap and --frames"), err
    assert sorted(p.name for p in reference.iterdir()) == before and not shot.exists()
    # the live viewer shows another process's wires: refused before it connects (nothing listens on port 9)
    assert main(["view", "--live", "127.0.0.1:9", "--access-lps=1,2,3", "--screenshot", str(shot)]) == 2
    assert "--access-lps: view --live shows the wires of a `guidewire3d live` server" in _one_line_error(capsys)
    assert not shot.exists()


def test_view_on_inputs_refuses_a_far_access_and_leaves_no_folder(study, tmp_path, monkeypatch, capsys):
    """Without OUT_DIR the run goes to a new temporary folder: refused, it is removed again."""
    case, _, _ = study
    (tmp_path / "tmp").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    assert main(["view", *_view_inputs(case), "--access-lps=0,0,5000", "--screenshot", str(tmp_path / "s.png")]) == 2
    assert re.match(r"guidewire3d: error: --access-lps=0,0,5000: [0-9]+ mm outside the CTA's field of view",
                    _one_line_error(capsys))
    assert list((tmp_path / "tmp").iterdir()) == [] and not (tmp_path / "s.png").exists()
