"""The package as a user installs it: a wheel with its weights, run outside the checkout (issue 21)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ("guidewire_unet.safetensors", "vessel_unet.safetensors", "phantom_default.json")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    out = tmp_path_factory.mktemp("wheel")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(out),
                        str(ROOT)], capture_output=True, text=True, errors="replace")
    assert r.returncode == 0, r.stderr[-2000:]
    (whl,) = out.glob("guidewire3d-*.whl")
    return whl


def test_the_wheel_carries_the_weights_and_defaults(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    for name in SHIPPED:
        assert f"guidewire3d/resources/{name}" in names


def test_the_installed_wheel_reconstructs_from_another_folder(wheel, small_case_dir, tmp_path):
    # installed without its dependencies (the environment's are reused) into a scratch folder
    # outside the checkout, and run from a third folder: only the wheel's files can serve
    site = tmp_path / "site"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site), str(wheel)],
                       capture_output=True, text=True, errors="replace")
    assert r.returncode == 0, r.stderr[-2000:]
    work = tmp_path / "work"
    work.mkdir()
    env = dict(os.environ, PYTHONPATH=str(site))
    probe = subprocess.run([sys.executable, "-c", "import guidewire3d, guidewire3d.xray.segmentation as s, "
                            "guidewire3d.xray.vessels2d_learned as v; print(guidewire3d.__file__); "
                            "print(s.DEFAULT_WEIGHTS_PATH); print(v.DEFAULT_WEIGHTS_PATH)"],
                           cwd=work, env=env, capture_output=True, text=True, errors="replace")
    assert probe.returncode == 0, probe.stderr[-2000:]
    for line in probe.stdout.split():
        assert Path(line).resolve().is_relative_to(site.resolve()), line
        assert Path(line).exists(), line
    out = work / "out"
    d = small_case_dir
    run = subprocess.run([sys.executable, "-m", "guidewire3d.app.cli", "reconstruct", "--cta", str(d / "ct"),
                          "--roadmap", str(d / "roadmap.dcm"), "--frames", str(d / "frames.dcm"), "--out", str(out),
                          "--force", "--no-images"], cwd=work, env=env, capture_output=True, text=True, errors="replace", timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    report = json.loads((out / "report.json").read_text())
    assert sum(f["success"] for f in report["frames"]) >= len(report["frames"]) - 1
    assert report["inputs"]["segmenter"] == "unet"
