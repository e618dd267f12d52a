"""Export the shipped guidewire UNet (safetensors) to ONNX.

    .venv/bin/python scripts/export_onnx.py [--weights resources/guidewire_unet.safetensors] [--out unet.onnx]

Without ``--out`` the file goes to the run-time cache (``$GUIDEWIRE3D_CACHE`` or
``~/.cache/guidewire3d``), keyed by the weights' SHA-256, which is where
``guidewire3d.xray.segmentation`` looks for it; inference exports it there on first use anyway.
"""
from __future__ import annotations

import argparse

from guidewire3d.xray.segmentation import DEFAULT_WEIGHTS_PATH, export_onnx


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--weights", default=str(DEFAULT_WEIGHTS_PATH))
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    print(export_onnx(args.weights, args.out))


if __name__ == "__main__":
    main()
