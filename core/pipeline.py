"""The stages chained: used by the CLI, the viewer and the Slicer plugin."""
from __future__ import annotations

from pathlib import Path

from guidewire3d import io
from guidewire3d.errors import Guidewire3DError, InputError


def load_inputs(cta, roadmap, frames, *, series_uid=None, overrides=None, log=None):
    """Read and validate every input before anything is written."""
    vol = io.read_volume(cta, series_uid=series_uid, log=log)
    road = io.read_xa(roadmap, overrides=overrides)
    live = road if Path(frames) == Path(roadmap) else io.read_xa(frames, overrides=overrides)
    return vol, road, live


def cli_reconstruct(args):
    from guidewire3d.cli import geometry_overrides

    out = Path(args.out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(f"{out}: output folder exists and is not empty")
    load_inputs(args.cta, args.roadmap, args.frames, series_uid=args.series_uid, overrides=geometry_overrides(args))
    raise Guidewire3DError("reconstruct: the reconstruction stages are not built yet")


def cli_demo(args):
    raise Guidewire3DError("demo: the simulator and reconstruction stages are not built yet")


def cli_bench(args):
    raise Guidewire3DError("bench: the benchmarks are not built yet")
