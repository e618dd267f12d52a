"""Learned 2D vessel segmentation for real (non-subtracted) angiograms: a small UNet.

The classical :func:`guidewire3d.xray.roadmap.vessel_mask` (top-hat x Hessian vesselness) is tuned
for clean subtracted roadmaps; on real coronary angiograms (catheter, ribs, diaphragm, low
contrast of small branches) a UNet trained on manually labelled frames does better (5-fold
cross-validated Dice 0.778 vs 0.694 on the 40 real images of ``shared/data/coronary-angiograms``).
This module holds that network, its input normalisation, training helpers (random crops with
augmentation, Dice + BCE loss) and inference. ``vessel_mask(image, method="learned")`` calls
:func:`learned_vessel_mask`.

- Input (:func:`normalize_angiogram`): the image is resampled so that its longer side is
  ``REFERENCE_SIZE_PX`` (the training images' size; vessel widths in px scale with the
  image size, as in the classical method), then mapped to ``[0, 1]`` between its 1 and 99
  percentiles (clipped to ``NORM_CLIP``), with vessels dark (a bright-vessel image is
  inverted). The network sees ``2 x (x - 0.5)``.
- Network (:class:`VesselUNetConfig`): a UNet of four levels (shipped: 8-16-32-64 channels,
  120 k parameters, 0.5 MB), two 3x3 conv + BatchNorm + ReLU per level, max-pool down,
  transposed-conv up, skip connections, a 1x1 head giving logits.
- Weights: ``resources/vessel_unet.safetensors`` (safetensors, never pickle), written by
  ``scripts/train_vessels2d.py`` (trained on the 40 real coronary angiograms; its metadata
  records the recipe, the probability threshold and the cross-validated Dice per image).
  Reproduce: ``nice -n 10 .venv/bin/python scripts/train_vessels2d.py --workers 2`` (4400 steps).
- Inference (:func:`vessel_probability`, :func:`learned_vessel_mask`): the whole image at
  once (reflect-padded to a multiple of 16), averaged over the eight flips / transposes
  (test-time augmentation, two batches of 4; deterministic), probability set to 0 outside the classical
  detector's field of view (the dark collimator edge looks like a vessel to the network),
  probability >= the threshold recorded in the weights (picked on the training images;
  ``THRESHOLD`` if none), components below ``MIN_COMPONENT_PX`` dropped, resampled back to
  the input size. ~350 ms CPU for a 300x300 or 512x512 image on one torch thread (~50 ms
  without the test-time augmentation; once per roadmap).

torch is imported only inside functions.
"""
from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from guidewire3d.assets import resource_path
from guidewire3d.errors import InputError
from guidewire3d.xray import imaging
from guidewire3d.xray.unet import load_weights_into, read_weights, unet_class

__all__ = [
    "DEFAULT_WEIGHTS_PATH",
    "VesselUNetConfig",
    "normalize_angiogram",
    "build_vessel_unet",
    "build_vessel_ensemble",
    "save_vessel_unet",
    "load_vessel_unet",
    "vessel_probability",
    "learned_vessel_mask",
    "model_threshold",
    "model_tta",
    "mask_from_probability",
    "TrainOptions",
    "train_vessel_unet",
    "dice_bce_loss",
]

DEFAULT_WEIGHTS_PATH = resource_path("vessel_unet.safetensors")
FORMAT_TAG = "guidewire3d-vessel-unet-v1"

REFERENCE_SIZE_PX = 300        # longer image side the network works at (the training images' size)
NORM_PERCENTILES = (1.0, 99.0)  # intensity range mapped to [0, 1]
NORM_CLIP = (-0.25, 1.25)       # normalised values are clipped to this range
UNET_MULTIPLE = 16              # input padded to this multiple: up to 5 levels (4 poolings)
THRESHOLD = 0.5                 # vessel probability threshold when the weights record none
TTA = True                      # average the eight flips / transposes at inference
MIN_COMPONENT_PX = 20           # components smaller than this (at reference size) are dropped


@dataclass(frozen=True)
class VesselUNetConfig:
    """Architecture of the vessel UNet.

    Attributes
    ----------
    channels : tuple of int
        Feature channels per level, finest first (one pooling between levels). The shipped
        model uses ``(8, 16, 32, 64)`` (recorded in its metadata).
    in_channels : int
        Input channels (1: the normalised image).
    """

    channels: tuple[int, ...] = (8, 16, 32, 64)
    in_channels: int = 1

    def to_metadata(self) -> dict[str, str]:
        return {"channels": json.dumps(list(self.channels)), "in_channels": str(self.in_channels)}

    @classmethod
    def from_metadata(cls, meta: dict[str, str]) -> VesselUNetConfig:
        try:
            return cls(channels=tuple(int(c) for c in json.loads(meta["channels"])),
                       in_channels=int(meta.get("in_channels", "1")))
        except (KeyError, ValueError, TypeError) as err:
            raise InputError(f"vessel UNet metadata: bad or missing architecture ({err})") from None


# --------------------------------------------------------------------------------------------------
# input normalisation
# --------------------------------------------------------------------------------------------------

def _as_image(image, name: str = "image") -> np.ndarray:
    """The checked 2D image as float32 (the checks of ``imaging.as_image``)."""
    return imaging.as_image(image, name).astype(np.float32)


def _reference_shape(shape: tuple[int, int]) -> tuple[int, int]:
    s = REFERENCE_SIZE_PX / max(shape)
    return max(8, int(round(shape[0] * s))), max(8, int(round(shape[1] * s)))


def _resize(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    import cv2

    if a.shape == tuple(shape):
        return a.astype(np.float32, copy=True)
    interp = cv2.INTER_AREA if shape[0] < a.shape[0] else cv2.INTER_LINEAR
    return cv2.resize(a.astype(np.float32), (shape[1], shape[0]), interpolation=interp)


def normalize_angiogram(image, *, dark_vessels: bool | None = None) -> np.ndarray:
    """The network input: the image at reference size, robustly scaled to ~[0, 1], vessels dark.

    Parameters
    ----------
    image : (H, W) array_like of numbers
        Angiogram, any dtype and intensity scale.
    dark_vessels : bool or None
        ``False`` inverts the image (bright vessels); ``None`` detects the polarity with the
        classical detector of :mod:`guidewire3d.xray.roadmap`.

    Returns
    -------
    (h, w) ndarray of float32
        ``max(h, w) == REFERENCE_SIZE_PX``; 0 / 1 at the 1 / 99 intensity percentiles, clipped to
        ``NORM_CLIP``. All 0.5 for a flat image.

    Raises
    ------
    InputError
        If ``image`` is not a finite 2D numeric array of at least 8x8 pixels.
    """
    a = _as_image(image)
    if dark_vessels is None:
        dark_vessels = _detect_dark(a)
    r = _resize(a, _reference_shape(a.shape))
    if not dark_vessels:
        r = -r
    lo, hi = (float(x) for x in np.percentile(r, NORM_PERCENTILES))
    if hi - lo <= 1e-6 * max(abs(lo), abs(hi), 1e-12):
        return np.full(r.shape, 0.5, np.float32)
    return np.clip((r - lo) / (hi - lo), *NORM_CLIP).astype(np.float32)


def _detect_dark(a: np.ndarray) -> bool:
    im01, ok = imaging.normalise01(a.astype(np.float64))
    if not ok:
        return True
    return bool(imaging.dark_vessels_auto(im01, max(a.shape) / imaging.REFERENCE_SIZE_PX))


# --------------------------------------------------------------------------------------------------
# the network
# --------------------------------------------------------------------------------------------------


def build_vessel_unet(config: VesselUNetConfig | None = None):
    """A freshly initialised (untrained) torch vessel UNet."""
    config = config or VesselUNetConfig()
    if len(config.channels) < 2 or min(config.channels) < 1 or config.in_channels < 1:
        raise InputError(f"VesselUNetConfig: need >= 2 levels of >= 1 channel, got {config}")
    if 2 ** (len(config.channels) - 1) > UNET_MULTIPLE:
        raise InputError(f"VesselUNetConfig.channels: at most {UNET_MULTIPLE.bit_length()} levels "
                         f"(inputs are padded to a multiple of {UNET_MULTIPLE}), got {len(config.channels)}")
    return unet_class()(config)


_ENSEMBLE_CLASS = None


def build_vessel_ensemble(members):
    """An ensemble of vessel UNets of one architecture: its output is the logit of the members'
    mean probability (so everything downstream treats it as one network). Saved and loaded like a
    single network (:func:`save_vessel_unet`, :func:`load_vessel_unet`; metadata ``members``)."""
    global _ENSEMBLE_CLASS
    members = list(members)
    if len(members) < 2 or any(m.config != members[0].config for m in members):
        raise InputError(f"vessel UNet ensemble: need >= 2 members of one architecture, got {len(members)}")
    if _ENSEMBLE_CLASS is None:
        import torch
        from torch import nn

        class VesselUNetEnsemble(nn.Module):
            def __init__(self, nets):
                super().__init__()
                self.members = nn.ModuleList(nets)
                self.config = nets[0].config

            def forward(self, x):
                p = torch.stack([torch.sigmoid(m(x)) for m in self.members]).mean(dim=0)
                return torch.logit(p, eps=1e-7)

        _ENSEMBLE_CLASS = VesselUNetEnsemble
    return _ENSEMBLE_CLASS(members)


def save_vessel_unet(model, path, *, extra_metadata: dict | None = None) -> Path:
    """Write the weights (float32, BatchNorm running statistics included) and config to safetensors
    (an ensemble's members under ``members.<k>.``, their number in the metadata)."""
    from safetensors.torch import save_file

    state = {k: v.detach().to("cpu").float().contiguous().clone() for k, v in model.state_dict().items()
             if not k.endswith("num_batches_tracked")}
    meta = model.config.to_metadata()
    meta["format"] = FORMAT_TAG
    meta["members"] = str(len(model.members)) if hasattr(model, "members") else "1"
    for k, v in (extra_metadata or {}).items():
        meta[str(k)] = v if isinstance(v, str) else json.dumps(v)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_file(state, str(path), metadata=meta)
    return path


def load_vessel_unet(path=None):
    """Load the vessel UNet from a safetensors file (no pickle), in eval mode on the CPU.

    Parameters
    ----------
    path : str or Path, optional
        Defaults to ``resources/vessel_unet.safetensors``.

    Returns
    -------
    torch.nn.Module
        The network (or ensemble of networks, :func:`build_vessel_ensemble`); ``config`` is its
        :class:`VesselUNetConfig` and ``metadata`` the file's metadata (training recipe,
        cross-validated Dice).

    Raises
    ------
    InputError
        Missing or unreadable file, or weights that do not match the recorded architecture.
    """
    path = Path(DEFAULT_WEIGHTS_PATH if path is None else path)
    tensors, meta = read_weights(path, "vessel UNet")
    if meta.get("format") != FORMAT_TAG:
        raise InputError(f"{path}: not a vessel UNet file (format {meta.get('format')!r})")
    try:
        n_members = int(meta.get("members", "1"))
    except ValueError:
        n_members = 0
    if n_members < 1:
        raise InputError(f"{path}: bad 'members' in the metadata ({meta.get('members')!r})")
    config = VesselUNetConfig.from_metadata(meta)
    model = (build_vessel_unet(config) if n_members == 1
             else build_vessel_ensemble([build_vessel_unet(config) for _ in range(n_members)]))
    return load_weights_into(model, tensors, meta, path, model.config)


_MODELS: dict[str, object] = {}
_MODELS_LOCK = threading.Lock()


def _cached_model(weights_path):
    key = str(Path(DEFAULT_WEIGHTS_PATH if weights_path is None else weights_path).resolve())
    with _MODELS_LOCK:
        if key not in _MODELS:
            _MODELS[key] = load_vessel_unet(key)
        return _MODELS[key]


# --------------------------------------------------------------------------------------------------
# inference
# --------------------------------------------------------------------------------------------------

def _net_input(x01: np.ndarray) -> np.ndarray:
    return (2.0 * (x01 - 0.5)).astype(np.float32)


def _predict_probability(model, x01: np.ndarray, *, tta: bool) -> np.ndarray:
    """Vessel probability of the network on a normalised (h, w) image (reflect-padded to
    UNET_MULTIPLE); with ``tta`` the mean over the eight symmetries of the square (the four flips of
    the image and of its transpose; the training augmentation has all of them), run as two
    batches of four."""
    import torch

    h, w = x01.shape
    ph, pw = (-h) % UNET_MULTIPLE, (-w) % UNET_MULTIPLE
    z = np.pad(_net_input(x01), ((ph // 2, ph - ph // 2), (pw // 2, pw - pw // 2)), mode="reflect")
    flips = ((), (1,), (0,), (0, 1)) if tta else ((),)
    acc = np.zeros(z.shape, np.float64)
    for transpose in ((False, True) if tta else (False,)):
        base = z.T if transpose else z
        batch = np.stack([np.flip(base, f) if f else base for f in flips])[:, None]
        with torch.inference_mode():
            logits = model(torch.from_numpy(np.ascontiguousarray(batch, np.float32)))[:, 0].numpy()
        prob = 1.0 / (1.0 + np.exp(-np.clip(logits, -30.0, 30.0)))
        for p, f in zip(prob, flips):
            p = np.flip(p, f) if f else p
            acc += p.T if transpose else p
    prob = acc / (len(flips) * (2 if tta else 1))
    return prob[ph // 2: ph // 2 + h, pw // 2: pw // 2 + w].astype(np.float32)


def vessel_probability(image, *, dark_vessels: bool | None = None, weights_path=None, model=None,
                       tta: bool | None = None) -> np.ndarray:
    """Per-pixel vessel probability of an angiogram by the vessel UNet.

    Parameters
    ----------
    image : (H, W) array_like of numbers
        Angiogram (non-subtracted coronary XA is what the shipped model was trained on).
    dark_vessels : bool or None
        Polarity (see :func:`normalize_angiogram`).
    weights_path : str or Path, optional
        Safetensors weights; default ``resources/vessel_unet.safetensors`` (loaded once, cached).
    model : torch.nn.Module, optional
        A network to use instead of loading one (training / cross-validation).
    tta : bool or None
        Test-time augmentation: average the probabilities of the eight flipped / transposed
        copies; deterministic. ``None`` (default): as recorded in the weights (:func:`model_tta`).

    Returns
    -------
    (H, W) ndarray of float32 in [0, 1]
    """
    a = _as_image(image)
    if dark_vessels is None:
        dark_vessels = _detect_dark(a)
    x = normalize_angiogram(a, dark_vessels=dark_vessels)
    net = model if model is not None else _cached_model(weights_path)
    prob = _predict_probability(net, x, tta=model_tta(net) if tta is None else bool(tta))
    prob = prob * _field_of_view(a, x.shape, dark_vessels)
    return np.clip(_resize(prob, a.shape), 0.0, 1.0).astype(np.float32)


def model_threshold(model) -> float:
    """The probability threshold recorded in a model's metadata (picked on its training images by
    ``scripts/train_vessels2d.py``), else ``THRESHOLD``."""
    meta = getattr(model, "metadata", None) or {}
    try:
        t = float(meta["threshold"])
    except (KeyError, ValueError, TypeError):
        return THRESHOLD
    return t if 0.0 < t < 1.0 else THRESHOLD


def model_tta(model) -> bool:
    """Whether a model's metadata asks for test-time flips (as it was scored), else ``TTA``."""
    meta = getattr(model, "metadata", None) or {}
    return meta["tta"] == "true" if meta.get("tta") in ("true", "false") else TTA


def _field_of_view(a: np.ndarray, shape: tuple[int, int], dark_vessels: bool) -> np.ndarray:
    """The classical detector's field of view (inside the collimator, ``FOV_MARGIN_PX`` away from
    shutter edges) at the reference size: the dark shutter edge is a dark line to the network."""
    im01, ok = imaging.normalise01(_resize(a, shape).astype(np.float64))
    if not ok:
        return np.zeros(shape, np.float32)
    if not dark_vessels:
        im01 = 1.0 - im01
    margin = max(2, int(round(imaging.FOV_MARGIN_PX)))
    return imaging.field_of_view(im01, margin).astype(np.float32)


def learned_vessel_mask(image, *, dark_vessels: bool | None = None, weights_path=None, model=None,
                        threshold: float | None = None, tta: bool | None = None) -> np.ndarray:
    """Vessel mask of an angiogram by the vessel UNet: probability >= ``threshold``, tiny components
    (below ``MIN_COMPONENT_PX`` at reference size) removed.

    Parameters are those of :func:`vessel_probability`, plus ``threshold`` in (0, 1). ``None``
    (default) for ``threshold`` / ``tta`` takes the values recorded in the weights' metadata
    (:func:`model_threshold`, :func:`model_tta`; the rule the cross-validation scored).

    Returns
    -------
    (H, W) ndarray of bool
        All False for a flat (blank) image.

    Raises
    ------
    InputError
        Bad image, weights file or threshold.
    """
    if threshold is not None and not (0.0 < float(threshold) < 1.0):
        raise InputError(f"threshold: expected a probability in (0, 1), got {threshold!r}")
    a = _as_image(image)
    lo, hi = (float(v) for v in np.percentile(a, [0.5, 99.5]))
    if hi - lo <= 1e-3 * max(abs(lo), abs(hi), 1e-12):
        return np.zeros(a.shape, bool)
    net = model if model is not None else _cached_model(weights_path)
    if threshold is None:
        threshold = model_threshold(net)
    if tta is None:
        tta = model_tta(net)
    return mask_from_probability(vessel_probability(a, dark_vessels=dark_vessels, model=net, tta=tta),
                                 threshold=float(threshold))


def mask_from_probability(prob: np.ndarray, *, threshold: float) -> np.ndarray:
    """The vessel mask of a probability map: ``prob >= threshold``, components smaller than
    ``MIN_COMPONENT_PX`` (scaled from the reference size to the map's size) removed.

    Parameters
    ----------
    prob : (H, W) ndarray of float
        Output of :func:`vessel_probability`.
    threshold : float
        Probability threshold in (0, 1).

    Returns
    -------
    (H, W) ndarray of bool
    """
    from scipy import ndimage as ndi

    m = np.asarray(prob) >= threshold
    if m.any():
        lab, n = ndi.label(m, structure=np.ones((3, 3), bool))
        sizes = np.bincount(lab.ravel(), minlength=n + 1)
        min_px = MIN_COMPONENT_PX * (max(m.shape) / REFERENCE_SIZE_PX) ** 2
        keep = sizes >= min_px
        keep[0] = False
        m = keep[lab]
    return m


# --------------------------------------------------------------------------------------------------
# training
# --------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class TrainOptions:
    """Training recipe (random crops, augmentation, Dice + BCE, Adam with cosine decay).

    Attributes
    ----------
    steps : int
        Optimiser steps.
    batch : int
        Crops per step.
    crop_px : int
        Crop side at reference size, px (multiple of UNET_MULTIPLE).
    lr : float
        Adam's initial learning rate (cosine decay to 5 % of it).
    weight_decay : float
        Adam's L2 weight decay.
    scale_range : (float, float)
        Random zoom factors (small scale changes).
    rotate_deg : float
        Random rotation in ``[-rotate_deg, rotate_deg]`` degrees (besides rot90 and flips).
    seed : int
        Seeds numpy and torch.
    """

    steps: int = 600
    batch: int = 8
    crop_px: int = 160
    lr: float = 3e-3
    weight_decay: float = 1e-5
    scale_range: tuple[float, float] = (0.85, 1.18)
    rotate_deg: float = 0.0
    seed: int = 0


def dice_bce_loss(logits, target):
    """Binary cross-entropy plus (1 - soft Dice) over the batch (torch tensors, (B, 1, H, W))."""
    import torch.nn.functional as F

    bce = F.binary_cross_entropy_with_logits(logits, target)
    p = logits.sigmoid()
    inter = (p * target).sum()
    dice = (2.0 * inter + 1.0) / (p.sum() + target.sum() + 1.0)
    return bce + (1.0 - dice)


def _augment_crop(x01: np.ndarray, m: np.ndarray, crop: int, rng: np.random.Generator,
                  scale_range: tuple[float, float], rotate_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """One random crop of (normalised image, mask) with geometric and photometric augmentation.

    Geometric: a random zoom in ``scale_range`` and rotation in ``[-rotate_deg, rotate_deg]`` about
    a random centre (one affine resampling, reflected borders), then rot90 / flip. Photometric:
    gamma, gain / offset, blur, noise (vessels stay darker than the background).
    """
    import cv2

    zoom = float(np.exp(rng.uniform(np.log(scale_range[0]), np.log(scale_range[1]))))
    angle = float(rng.uniform(-rotate_deg, rotate_deg)) if rotate_deg > 0 else 0.0
    h, w = x01.shape
    half = 0.5 * crop / zoom
    cx = float(rng.uniform(half, w - half)) if w > 2 * half else 0.5 * w
    cy = float(rng.uniform(half, h - half)) if h > 2 * half else 0.5 * h
    mat = cv2.getRotationMatrix2D((cx, cy), angle, zoom)
    mat[:, 2] += (0.5 * crop - cx, 0.5 * crop - cy)
    warp = dict(dsize=(crop, crop), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    xi = cv2.warpAffine(np.ascontiguousarray(x01, np.float32), mat, **warp)
    mi = cv2.warpAffine(np.ascontiguousarray(m, np.float32), mat, **warp)
    k = int(rng.integers(0, 4))
    xi, mi = np.rot90(xi, k), np.rot90(mi, k)
    if rng.random() < 0.5:
        xi, mi = xi[:, ::-1], mi[:, ::-1]
    # Photometric: gamma, gain / offset (percentile jitter), blur, noise.
    xi = np.clip(xi, 0.0, None) ** float(np.exp(rng.normal(0.0, 0.25)))
    xi = xi * float(np.exp(rng.normal(0.0, 0.15))) + float(rng.normal(0.0, 0.06))
    if rng.random() < 0.3:
        xi = cv2.GaussianBlur(np.ascontiguousarray(xi, np.float32), (0, 0), float(rng.uniform(0.4, 1.0)))
    if rng.random() < 0.5:
        xi = xi + rng.normal(0.0, rng.uniform(0.005, 0.04), xi.shape)
    return np.ascontiguousarray(xi, np.float32), np.ascontiguousarray(mi > 0.5, np.float32)


def train_vessel_unet(images, masks, *, config: VesselUNetConfig | None = None,
                      options: TrainOptions | None = None, log=None):
    """Train a vessel UNet on labelled angiograms.

    Parameters
    ----------
    images : sequence of (H, W) arrays
        Angiograms (vessels dark).
    masks : sequence of (H, W) bool arrays
        Manual vessel masks, same shapes.
    config : VesselUNetConfig, optional
    options : TrainOptions, optional
    log : callable ``(step, loss) -> None``, optional
        Called every 50 steps.

    Returns
    -------
    torch.nn.Module
        The trained network in eval mode.
    """
    import torch

    options = options or TrainOptions()
    if len(images) != len(masks) or not len(images):
        raise InputError(f"images/masks: need equally many (>= 1), got {len(images)} and {len(masks)}")
    if options.crop_px % UNET_MULTIPLE:
        raise InputError(f"TrainOptions.crop_px: must be a multiple of {UNET_MULTIPLE}, got {options.crop_px}")
    rng = np.random.default_rng(options.seed)
    torch.manual_seed(options.seed)
    xs, ms = [], []
    for i, (im, mk) in enumerate(zip(images, masks)):
        mk = np.asarray(mk, bool)
        if mk.shape != np.shape(im):
            raise InputError(f"masks[{i}]: shape {mk.shape} differs from the image's {np.shape(im)}")
        x = normalize_angiogram(im, dark_vessels=True)
        xs.append(x)
        ms.append(_resize(mk.astype(np.float32), x.shape) > 0.5)
    model = build_vessel_unet(config)
    opt = torch.optim.Adam(model.parameters(), lr=options.lr, weight_decay=options.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.05 + 0.95 * 0.5 * (1.0 + np.cos(np.pi * min(s, options.steps) / options.steps)))
    model.train()
    running = None
    for step in range(options.steps):
        idx = rng.integers(0, len(xs), options.batch)
        pairs = [_augment_crop(xs[j], ms[j], options.crop_px, rng, options.scale_range, options.rotate_deg)
                 for j in idx]
        xb = torch.from_numpy(_net_input(np.stack([p[0] for p in pairs]))[:, None])
        yb = torch.from_numpy(np.stack([p[1] for p in pairs])[:, None])
        loss = dice_bce_loss(model(xb), yb)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        lv = float(loss.detach())
        running = lv if running is None else 0.95 * running + 0.05 * lv
        if log is not None and (step % 50 == 0 or step == options.steps - 1):
            log(step, running)
    model.eval()
    return model
