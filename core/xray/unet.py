"""The UNet architecture shared by the guidewire segmenter (:mod:`guidewire3d.xray.segmentation`) and the
vessel segmenter (:mod:`guidewire3d.xray.vessels2d_learned`): an encoder-decoder with skip connections.

torch is imported on first use (importing it costs ~1 s; the live path runs the exported ONNX model
through onnxruntime and never needs it).
"""
from __future__ import annotations

from pathlib import Path

from guidewire3d.errors import InputError

__all__ = ["unet_class"]

_CLASS = None


def unet_class():
    """The torch module class (defined lazily so that importing this module does not import torch)."""
    global _CLASS
    if _CLASS is not None:
        return _CLASS
    import torch
    from torch import nn

    def cbr(i, o):
        return [nn.Conv2d(i, o, 3, padding=1, bias=False), nn.BatchNorm2d(o), nn.ReLU(inplace=True)]

    class Block(nn.Sequential):
        def __init__(self, c_in, c_out, n_convs):
            layers = cbr(c_in, c_out)
            for _ in range(n_convs - 1):
                layers += cbr(c_out, c_out)
            super().__init__(*layers)

    class UNet(nn.Module):
        """UNet: encoder-decoder with skip connections; input (B, C, H, W) normalised, output logits.

        ``config.channels`` per level; ``config.in_channels`` (default 1) and
        ``config.level0_convs`` (default 2) if the config has them. Shared by the guidewire UNet
        (:class:`UNetConfig`) and the vessel UNet (``vessels2d_learned.VesselUNetConfig``).
        """

        def __init__(self, config):
            super().__init__()
            ch = tuple(int(c) for c in config.channels)
            n0 = int(getattr(config, "level0_convs", 2))
            c_in = int(getattr(config, "in_channels", 1))
            self.config = config
            self.enc = nn.ModuleList(
                [Block(c_in if k == 0 else ch[k - 1], ch[k], n0 if k == 0 else 2) for k in range(len(ch))])
            self.up = nn.ModuleList(
                [nn.ConvTranspose2d(ch[k + 1], ch[k], 2, stride=2) for k in range(len(ch) - 1)])
            self.dec = nn.ModuleList(
                [Block(2 * ch[k], ch[k], n0 if k == 0 else 2) for k in range(len(ch) - 1)])
            self.head = nn.Conv2d(ch[0], 1, 1)
            self.pool = nn.MaxPool2d(2)

        def forward(self, x):
            skips = []
            for k, block in enumerate(self.enc):
                x = block(x if k == 0 else self.pool(x))
                skips.append(x)
            for k in reversed(range(len(self.dec))):
                x = self.dec[k](torch.cat([self.up[k](x), skips[k]], 1))
            return self.head(x)

    _CLASS = UNet
    return UNet


def read_weights(path, what: str = "UNet") -> tuple[dict, dict]:
    """The tensors and metadata of a safetensors weights file (no pickle); ``what`` names the network
    in the errors. Raises InputError for a missing or unreadable file."""
    from safetensors import safe_open

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} weights file not found")
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = dict(f.metadata() or {})
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as err:  # safetensors raises its own error types
        raise InputError(f"{path}: not a readable safetensors file ({err})") from None
    return tensors, meta


def load_weights_into(model, tensors: dict, meta: dict, path, arch) -> object:
    """Load ``tensors`` into ``model`` (the running statistics' counters may be absent), set eval
    mode and ``model.metadata``; InputError naming ``path`` when they do not match ``arch``."""
    missing, unexpected = model.load_state_dict(tensors, strict=False)
    missing = [k for k in missing if not k.endswith("num_batches_tracked")]
    if missing or unexpected:
        raise InputError(f"{path}: weights do not match the architecture {arch} "
                         f"(missing {missing[:3]}, unexpected {list(unexpected)[:3]})")
    model.eval()
    model.metadata = dict(meta)
    return model
