"""A `batch` rerun reuses a finished study only when it was made with the options the run asks for.

One real study (tiny study s11 of conftest, 2 live frames, the ridge segmenter) made by `batch` with
``roadmap_frame`` 1 of a roadmap run of two identical frames, at an access point, without images. Each
rerun changes one thing: a study made otherwise is ``failed`` with a one-line reason naming what it was
made with and what the run asks for, and its folder is left as it was; a study made as asked is
``skipped``. ``summary.csv`` states the options every study was made with (the manifest's option
columns, appended after the first columns).
"""
from __future__ import annotations

import csv
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pydicom
import pytest

from guidewire3d import io
from guidewire3d.app import batch
from guidewire3d.app.cli import main
from guidewire3d.phantom import load_truth

STUDY = "s11"  # a tiny study of conftest.TINY_SEEDS (registration ok)
JSON_MM = 1e-3  # mm: report.json and summary.csv round a point to 3 decimals
HEADER = ["study", "cta", "roadmap", "frames", "segmenter", "roadmap_frame", "series_uid", "force", "access_lps"]
FIRST_COLUMNS = ("study", "status", "verdict", "residual_px", "frames_reconstructed", "frames_total", "seconds",
                 "peak_rss_mb", "worker", "error")  # summary.csv before the option columns: kept in place


def _xyz(p) -> str:
    return ",".join(f"{v:.3f}" for v in p)


def _summary(out) -> tuple[list[str], dict[str, dict]]:
    with open(out / batch.SUMMARY_NAME, newline="") as f:
        r = csv.DictReader(f)
        rows = {row["study"]: row for row in r}
        return list(r.fieldnames), rows


def _folder_state(folder) -> dict:
    """Every file of ``folder`` with its bytes and modification time: what "untouched" means."""
    return {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def made(tiny_studies, tmp_path_factory):
    """The study made once by `batch`: (case files, the CT's series UID, the access point, out folder,
    the first run's exit code)."""
    d = tiny_studies[STUDY]
    tmp = tmp_path_factory.mktemp("rerun")
    road = io.read_xa(d / "roadmap.dcm")
    # two identical roadmap frames: the automatic choice is frame 0, and frame 1 registers as well
    roadmap2 = io.write_xa(tmp / "roadmap2.dcm", np.concatenate([road.frames, road.frames]), road.carm)
    files = [d / "ct", roadmap2, d / "frames.dcm"]
    uid = str(pydicom.dcmread(sorted((d / "ct").iterdir())[0], stop_before_pixels=True).SeriesInstanceUID)
    truth = load_truth(d)
    far = np.array([float(v) for v in _xyz(truth.tree.points_lps_mm[truth.wire_path_point_ids[-1]]).split(",")])
    out = tmp / "out"
    m = _manifest(tmp / "m.csv", files, roadmap_frame="1", access_lps=_xyz(far))
    rc = main(["batch", str(m), "--out", str(out), "--workers", "1", "--no-images"])
    return files, uid, far, out, rc


def _manifest(path, files, **cells):
    row = {"study": STUDY, "segmenter": "ridge", "roadmap_frame": "", "series_uid": "", "force": "",
           "access_lps": "", **cells}
    with open(path, "w", newline="") as f:
        w = csv.writer(f)  # quotes the access point's commas, as a spreadsheet does
        w.writerow(HEADER)
        w.writerow([row[h] if h not in ("cta", "roadmap", "frames") else files[("cta", "roadmap", "frames").index(h)]
                    for h in HEADER])
    return path


def test_the_summary_states_the_options_the_study_was_made_with(made):
    files, uid, far, out, rc = made
    assert rc == 0
    columns, rows = _summary(out)
    assert tuple(columns) == batch.SUMMARY_COLUMNS == (*FIRST_COLUMNS, *batch.OPTION_COLUMNS)
    row = rows[STUDY]
    assert row["status"] == batch.DONE and row["verdict"] == "ok"
    np.testing.assert_allclose([float(v) for v in row["access_lps"].split(",")], far, atol=JSON_MM)
    assert {k: row[k] for k in ("series_uid", "roadmap_frame", "method", "segmenter", "force", "track_motion")} == {
        "series_uid": uid, "roadmap_frame": "1", "method": "vessel", "segmenter": "ridge", "force": "false",
        "track_motion": "false"}
    # the same values as the folder's report.json
    inputs = json.loads((out / STUDY / "report.json").read_text())["inputs"]
    assert (inputs["roadmap_frame"], inputs["series_uid"], inputs["forced"]) == (1, uid, False)
    np.testing.assert_allclose(inputs["access_lps_mm"], far, atol=JSON_MM)


@pytest.mark.parametrize("cells, images, reason", [
    ({}, False, None),                                       # as made: reused
    ({"series_uid": "UID"}, False, None),                    # the series it was made with, now named
    ({"force": "true"}, False, None),                        # the registration succeeded: force changes nothing
    ({"roadmap_frame": "0"}, False, "made with roadmap_frame 1, this run asks for roadmap_frame 0"),
    ({"roadmap_frame": ""}, False, "made with roadmap_frame 1, this run asks for the automatic roadmap_frame (0)"),
    ({"series_uid": "1.2.3.4"}, False, "made with series_uid UID, this run asks for series_uid 1.2.3.4"),
    ({}, True, "made with --no-images, this run asks for images"),
    ({"roadmap_frame": "0", "access_lps": "none"}, False,
     "made with --access-lps=FAR, roadmap_frame 1, this run asks for none, roadmap_frame 0"),
], ids=["same", "series-named", "force-ok", "frame", "frame-automatic", "series", "images", "two"])
def test_a_rerun_reuses_only_a_study_made_as_asked(made, tmp_path, cells, images, reason):
    files, uid, far, out, _ = made
    typed = _xyz(far)
    cells = {"roadmap_frame": "1", "access_lps": typed,
             **{k: v.replace("UID", uid) for k, v in cells.items()}}
    before = _folder_state(out / STUDY)
    m = _manifest(tmp_path / "m.csv", files, **cells)
    rc = main(["batch", str(m), "--out", str(out), "--workers", "1", *([] if images else ["--no-images"])])
    row = _summary(out)[1][STUDY]
    assert _folder_state(out / STUDY) == before  # reused or refused, never rewritten
    if reason is None:
        assert (rc, row["status"], row["error"]) == (0, batch.SKIPPED, "")
    else:
        made_with = ",".join(f"{v:.3f}".rstrip("0").rstrip(".") for v in far)  # to 1e-3 mm, no trailing zeros
        expected = reason.replace("UID", uid).replace("FAR", made_with)
        assert (rc, row["status"]) == (1, batch.FAILED)
        assert row["error"] == (f"{out / STUDY}: it was {expected}: remove the folder to reconstruct it again")
    # either way the row states what the folder holds
    assert (row["roadmap_frame"], row["series_uid"], row["verdict"]) == ("1", uid, "ok")


def test_force_is_compared_where_the_registration_failed(made, tmp_path):
    """A study whose registration failed is not reconstructed without ``force``, and is with it: each
    is not the study the other asks for. (The study's report is edited, on a copy, into a failed one.)"""
    files, uid, far, out0, _ = made
    out = tmp_path / "out"
    shutil.copytree(out0 / STUDY, out / STUDY)
    rep_path = out / STUDY / "report.json"
    rep = json.loads(rep_path.read_text())
    rep["registration"]["success"] = False
    for forced, ask, status in [(False, "true", batch.FAILED), (True, "", batch.FAILED), (True, "true", batch.SKIPPED),
                                (False, "", batch.SKIPPED)]:
        rep["inputs"]["forced"] = forced
        rep_path.write_text(json.dumps(rep))
        m = _manifest(tmp_path / "m.csv", files, roadmap_frame="1", access_lps=_xyz(far), force=ask)
        main(["batch", str(m), "--out", str(out), "--workers", "1", "--no-images"])
        row = _summary(out)[1][STUDY]
        assert row["status"] == status, (forced, ask, row)
        assert row["force"] == ("true" if forced else "false")
        if status == batch.FAILED:
            assert (f"it was made with force {forced} (the registration failed), this run asks for force "
                    f"{not forced}: remove the folder") in row["error"]


def test_a_study_that_failed_without_a_folder_states_the_options_asked_for(made, tmp_path):
    """No folder to read them from: the row states what the manifest asked for (empty roadmap_frame and
    series_uid: the automatic choice)."""
    files, _, far, _, _ = made
    ct_slice = sorted(files[0].iterdir())[0]  # a CT slice where the roadmap belongs: refused on reading
    m = _manifest(tmp_path / "m.csv", [files[0], ct_slice, files[2]], access_lps=_xyz(far), force="true")
    (spec,) = batch.read_manifest(m)
    row = batch.run_study(spec, tmp_path / "out", images=False)
    assert row["status"] == batch.FAILED and row["error"].startswith(f"{ct_slice}: ")
    assert not (tmp_path / "out" / STUDY).exists()
    assert {k: row[k] for k in ("series_uid", "roadmap_frame", "method", "segmenter", "force", "track_motion")} == {
        "series_uid": "", "roadmap_frame": "", "method": "vessel", "segmenter": "ridge", "force": "true",
        "track_motion": "false"}
    np.testing.assert_allclose([float(v) for v in row["access_lps"].split(",")], far, atol=JSON_MM)


# --------------------------------------------------------------------------------------
# the input files: compared by their bytes, wherever they lie
# --------------------------------------------------------------------------------------
def _copied(made, tmp_path):
    """The made study's inputs and folder copied under ``tmp_path`` (the same bytes at other paths):
    (the files: ct folder, roadmap, frames; the output folder)."""
    files, _, _, out0, _ = made
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    copies = [shutil.copytree(files[0], inputs / "ct"), shutil.copy2(files[1], inputs / files[1].name),
              shutil.copy2(files[2], inputs / "frames.dcm")]
    out = tmp_path / "out"
    shutil.copytree(out0 / STUDY, out / STUDY)
    return [Path(p) for p in copies], out


def _rerun(tmp_path, files, out, far, **cells):
    """A rerun of the made study with its options (and ``cells``) on ``files``: (exit code, row)."""
    m = _manifest(tmp_path / "m.csv", files, **{"roadmap_frame": "1", "access_lps": _xyz(far), **cells})
    rc = main(["batch", str(m), "--out", str(out), "--workers", "1", "--no-images"])
    return rc, _summary(out)[1][STUDY]


def _edited(path, **tags) -> None:
    """Rewrite the DICOM file ``path`` with ``tags`` set (another export of the same image, say)."""
    ds = pydicom.dcmread(path)
    for k, v in tags.items():
        setattr(ds, k, v)
    ds.save_as(path)


def test_the_report_records_the_bytes_of_every_input_file(made):
    files, uid, _, out, _ = made
    record = json.loads((out / STUDY / "report.json").read_text())["inputs"]["files"]
    slices = sorted(files[0].iterdir())
    assert [d["name"] for d in record["cta"]] == [p.name for p in slices]
    for role, paths in (("cta", slices), ("roadmap", [files[1]]), ("frames", [files[2]])):
        assert [(d["size"], d["sha256"]) for d in record[role]] == \
            [(p.stat().st_size, hashlib.sha256(p.read_bytes()).hexdigest()) for p in paths], role


def _change_roadmap(files, tmp_path):
    _edited(files[1], ImageComments="exported again")
    return "the roadmap file {roadmap} before it changed", "the roadmap file {roadmap} as it is now"


def _change_slice(files, tmp_path):
    _edited(sorted(files[0].iterdir())[3], ImageComments="exported again")
    return "the cta file {slice3} before it changed", "the cta file {slice3} as it is now"


def _add_slice(files, tmp_path):
    shutil.copy2(sorted(files[0].iterdir())[3], files[0] / "zz_extra.dcm")
    return "the cta {ct} without {ct}/zz_extra.dcm", "the cta {ct} with it (added)"


def _remove_slices(files, tmp_path):
    for p in sorted(files[0].iterdir())[-2:]:
        p.unlink()
    return "the cta {ct} with {last2} and 1 more gone", "the cta {ct} without it (gone)"


def _other_frames(files, tmp_path):
    files[2] = shutil.copy2(files[1], tmp_path / "other_frames.dcm")  # the manifest names another file
    return "the frames file {made_frames}", f"the frames file {tmp_path / 'other_frames.dcm'} (other bytes)"


@pytest.mark.parametrize("change", [None, _change_roadmap, _change_slice, _add_slice, _remove_slices, _other_frames],
                         ids=["same-bytes-elsewhere", "roadmap", "ct-slice", "ct-added", "ct-gone", "other-frames"])
def test_a_rerun_never_reuses_a_study_whose_input_files_changed(made, tmp_path, change, capsys):
    """The study's files copied elsewhere are the same inputs (skipped); one file of them changed,
    added, gone or another file named: ``failed``, the error naming the file, the folder untouched."""
    files, uid, far, out0, _ = made
    copies, out = _copied(made, tmp_path)
    slices = sorted(copies[0].iterdir())
    names = {"roadmap": copies[1], "slice3": slices[3], "ct": copies[0], "last2": slices[-2],
             "made_frames": json.loads((out0 / STUDY / "report.json").read_text())["inputs"]["frames"]}
    reason = None if change is None else change(copies, tmp_path)
    before = _folder_state(out / STUDY)
    rc, row = _rerun(tmp_path, copies, out, far)
    assert _folder_state(out / STUDY) == before
    if reason is None:
        assert (rc, row["status"], row["error"]) == (0, batch.SKIPPED, "")
        return
    said, asked = (r.format(**names) for r in reason)
    assert (rc, row["status"]) == (1, batch.FAILED)
    assert "0 studies already done (skipped), 1 made otherwise than asked (failed: see the error column of " \
        f"{out / batch.SUMMARY_NAME}), 0 to run" in capsys.readouterr().err
    assert row["error"] == f"{out / STUDY}: it was made with {said}, this run asks for {asked}: remove the folder " \
                           "to reconstruct it again"
    assert "\n" not in row["error"] and (row["roadmap_frame"], row["series_uid"]) == ("1", uid)  # what it holds


def test_a_study_without_a_record_of_its_files_is_not_reused(made, tmp_path):
    """A folder made before report.json kept its files cannot be compared: refused, not kept silently;
    a report that cannot be read neither."""
    files, _, far, _, _ = made
    copies, out = _copied(made, tmp_path)
    rep_path = out / STUDY / "report.json"
    rep = json.loads(rep_path.read_text())
    del rep["inputs"]["files"]
    rep_path.write_text(json.dumps(rep))
    rc, row = _rerun(tmp_path, copies, out, far)
    assert (rc, row["status"]) == (1, batch.FAILED)
    assert row["error"] == (f"{out / STUDY}: it was made with no record of its input files (made before report.json "
                            "kept them), this run asks for input files it can compare with the ones the study was "
                            "made from: remove the folder to reconstruct it again")
    rep_path.write_text("{not json")
    rc, row = _rerun(tmp_path, copies, out, far)
    assert (rc, row["status"]) == (1, batch.FAILED)
    assert row["error"].startswith(f"{rep_path}: unreadable (") and row["error"].endswith(
        ": remove the folder to reconstruct it again")
    assert rep_path.read_text() == "{not json"


def _second_series(ct, n_more: int) -> str:
    """Add to the folder ``ct`` another CT series: a copy of its slices, ``n_more`` slices more; its UID."""
    from pydicom.uid import generate_uid

    uid = generate_uid()
    slices = sorted(ct.iterdir())
    step = float(pydicom.dcmread(slices[1]).ImagePositionPatient[2]) - \
        float(pydicom.dcmread(slices[0]).ImagePositionPatient[2])
    for k, p in enumerate(slices + slices[-1:] * n_more):
        ds = pydicom.dcmread(p)
        ds.SeriesInstanceUID, ds.SOPInstanceUID = uid, generate_uid()
        ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
        if k >= len(slices):
            ds.ImagePositionPatient[2] = float(ds.ImagePositionPatient[2]) + step * (k - len(slices) + 1)
        ds.save_as(ct / f"b_{k:04d}.dcm")
    return uid


def test_an_empty_series_uid_is_compared_with_the_series_chosen_now(made, tmp_path):
    """Made from a named series, rerun with the cell emptied: the automatic choice (the largest CT
    series of the folder) is another series now, so the study is not the one asked for."""
    files, uid, far, _, _ = made
    copies, out = _copied(made, tmp_path)
    larger = _second_series(copies[0], 2)
    assert io.read_volume(copies[0]).series_uid == larger  # what reconstruct reads
    rc, row = _rerun(tmp_path, copies, out, far, series_uid=uid)  # named: the files of that series, unchanged
    assert (rc, row["status"]) == (0, batch.SKIPPED)
    before = _folder_state(out / STUDY)
    rc, row = _rerun(tmp_path, copies, out, far, series_uid="")
    assert (rc, row["status"]) == (1, batch.FAILED)
    assert row["error"] == (f"{out / STUDY}: it was made with series_uid {uid}, this run asks for the automatic "
                            f"series_uid ({larger}): remove the folder to reconstruct it again")
    assert _folder_state(out / STUDY) == before
