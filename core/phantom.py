"""Simulator with ground truth (being built; see issue 3)."""
from guidewire3d.errors import Guidewire3DError


def add_cli_options(p):
    p.add_argument("--out", required=True)
    p.add_argument("--seed", type=int, default=0)


def cli_main(args):
    raise Guidewire3DError("phantom: the simulator is not built yet")
