import subprocess
import sys


from guidewire3d.app import cli
from guidewire3d.methods import ReconMethod
from guidewire3d.xray.segmentation import SegMethod


def test_cli_choices_match_the_enums():
    assert set(cli.RECON_METHODS) == {m.value for m in ReconMethod}
    assert set(cli.SEGMENTERS) == {m.value for m in SegMethod}


def test_help_lists_every_subcommand():
    out = subprocess.run([sys.executable, "-m", "guidewire3d.app.cli", "--help"], capture_output=True, text=True, check=True).stdout
    for sub in ("demo", "phantom", "reconstruct", "segment", "view", "bench", "batch", "listen"):
        assert sub in out


def test_bad_choice_is_refused_before_any_work(tmp_path, capsys):
    rc = cli.main(["reconstruct", "--cta", "x", "--roadmap", "y", "--frames", "y", "--out", str(tmp_path / "o"),
                   "--method", "bogus"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1  # one line, not argparse's usage block
    assert err.startswith("guidewire3d: error: argument --method: invalid choice: 'bogus'")
    assert not (tmp_path / "o").exists()


def test_verbose_shows_traceback(tmp_path, capsys):
    rc = cli.main(["--verbose", "reconstruct", "--cta", str(tmp_path / "missing"), "--roadmap", "y", "--frames", "y",
                   "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" in err and "no such file" in err


def test_help_imports_no_stage():
    """`guidewire3d --help` lists the commands without importing a stage: each command's options are built
    (and its modules imported) only when that command is named."""
    code = ("import sys\nfrom guidewire3d.app import cli\n"
            "try:\n    cli.main(['--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in sys.modules if m.startswith('guidewire3d.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    loaded = eval(out.strip().splitlines()[-1])
    assert "phantom" in out and "listen" in out                     # the commands are listed
    assert loaded == ["guidewire3d.app", "guidewire3d.app.cli", "guidewire3d.errors", "guidewire3d.methods"]
