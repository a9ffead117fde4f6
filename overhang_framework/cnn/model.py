"""The stability network and its checkpoints.

A checkpoint is one ``torch.save`` file holding plain data only (it loads with
``weights_only=True``, so loading runs no code from the file and never touches
the network): the timm ``backbone`` name, the ``state_dict``, the ``renderer``
spec the model was trained with (see :mod:`overhang_framework.render`), and
what made it: the data settings, the training config, the metrics of the saved
epoch.

:data:`DEFAULT_CHECKPOINT` is the model shipped with the package; its model
card is ``default.md`` beside it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np

from overhang_framework.results import atomic_output

CHECKPOINT_FORMAT = 1
CHECKPOINT_DIR = Path(__file__).parent / "checkpoints"
DEFAULT_CHECKPOINT = CHECKPOINT_DIR / "default.pt"
#: Smallest input side some backbones accept (their stems downsample too much below it).
MIN_INPUT_SIDE = {"inception_v4": 75}


def check_backbone(backbone: str, size) -> None:
    """``ValueError`` when ``backbone`` is not a timm model or ``size`` (h, w) is too small for it."""
    import timm

    if not isinstance(backbone, str) or not timm.is_model(backbone):
        raise ValueError(f"unknown timm backbone {backbone!r}; e.g. mobilenetv3_small_100, regnetx_002, "
                         f"inception_v4 (timm.list_models() lists all)")
    need = MIN_INPUT_SIDE.get(backbone)
    if need is not None and min(size) < need:
        raise ValueError(f"backbone {backbone} needs inputs of at least {need}x{need}, got renderer size "
                         f"{list(size)}; set renderer.size")


def build_model(backbone: str, outputs: int = 1, channels: int = 3):
    """A timm ``backbone`` with random weights (``pretrained=False``) and ``outputs`` logits out, its
    weights in channels-last layout (about twice as fast on a CPU for these small inputs, measured for
    training and inference; feed it :func:`as_input`). The first logit is the stability verdict; any
    others are the training's auxiliary targets."""
    import timm
    import torch

    net = timm.create_model(backbone, pretrained=False, num_classes=outputs, in_chans=channels)
    return net.to(memory_format=torch.channels_last)


def as_input(images: np.ndarray, device):
    """``(n, channels, H, W)`` float32 images as the network's input tensor (channels-last, on ``device``)."""
    import torch

    return torch.from_numpy(images).to(device).contiguous(memory_format=torch.channels_last)


def pick_device(device: str = "auto"):
    """``auto``: the GPU when one is present, else the CPU; or any torch device name."""
    import torch

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        return torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise ValueError(f"device must be auto, cpu, cuda or cuda:N, got {device!r}") from err


def save_checkpoint(path: Path | str, model, renderer_spec: Mapping[str, Any], backbone: str,
                    **extra: Any) -> Path:
    """Write a checkpoint atomically (write, then rename); ``extra`` is plain data stored beside the weights."""
    import torch

    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    payload = {"format": CHECKPOINT_FORMAT, "backbone": backbone, "renderer": dict(renderer_spec),
               "state_dict": state, **extra}
    with atomic_output(path) as tmp:
        torch.save(payload, tmp)
    return Path(path)


def read_checkpoint(path: Path | str) -> dict:
    """The checkpoint's contents, on the CPU; ``ValueError`` naming the path when it is missing or unreadable."""
    import torch

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"no CNN checkpoint at {path}; use checkpoint=default or a .pt file written by "
                         f"python -m overhang_framework.cnn.train")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        raise ValueError(f"{path} is not a readable CNN checkpoint: {err}") from err
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not a CNN checkpoint of format {CHECKPOINT_FORMAT}")
    return payload


def resolve_checkpoint(checkpoint: Optional[str]) -> Path:
    """``default`` (or ``None``) is the shipped checkpoint; anything else is a path."""
    if checkpoint in (None, "default"):
        return DEFAULT_CHECKPOINT
    if not isinstance(checkpoint, (str, Path)):
        raise ValueError(f"checkpoint must be 'default' or a path to a .pt file, got {checkpoint!r}")
    return Path(checkpoint).expanduser()


class StabilityModel:
    """A loaded checkpoint: renders geometries and returns stability probabilities, batched.

    ``threads`` sets torch's CPU threads (``None``: leave torch's setting).
    ``batch_size`` caps the images of one forward pass (a pass holds at least
    one tower: two images with ``mirror``); the input buffer is
    reused between calls of the same or smaller size. ``mirror`` averages the
    network's logits for each tower and its mirror image (x -> -x, which keeps
    the verdict), both in the same forward pass: two images a tower.
    ``auto`` follows the checkpoint: its training records whether averaging
    scored higher on the validation set (older checkpoints: whether it trained
    on mirrored images).
    """

    def __init__(self, checkpoint: Optional[str] = "default", device: str = "auto",
                 threads: Optional[int] = None, batch_size: int = 512, mirror="auto"):
        import torch

        from overhang_framework.render import make_renderer

        if threads is not None:
            if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
                raise ValueError(f"threads must be a whole number >= 1 or null, got {threads!r}")
            torch.set_num_threads(threads)
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"batch_size must be a whole number >= 1, got {batch_size!r}")
        mirror = parse_mirror(mirror)
        self.path = resolve_checkpoint(checkpoint)
        payload = read_checkpoint(self.path)
        self.info = {k: v for k, v in payload.items() if k != "state_dict"}
        self.mirror = trained_mirrored(self.info) if mirror == "auto" else mirror
        self.backbone = payload["backbone"]
        self.renderer = make_renderer(payload["renderer"])
        self.device = pick_device(device)
        self.batch_size = batch_size
        self.net = build_model(self.backbone, int(payload.get("outputs", 1)), self.renderer.channels)
        self.net.load_state_dict(payload["state_dict"])
        self.net.eval().to(self.device)
        self._buffer = np.empty((0, *self.renderer.shape), dtype=np.float32)

    @property
    def images_per_tower(self) -> int:
        return 2 if self.mirror else 1

    def _images(self, n: int) -> np.ndarray:
        if self._buffer.shape[0] < n:
            self._buffer = np.empty((max(n, 2 * self._buffer.shape[0]), *self.renderer.shape), dtype=np.float32)
        return self._buffer[:n]

    def logits_of_arrays(self, widths, xs, layers, mask) -> np.ndarray:
        """Logits of padded block arrays (see :func:`overhang_framework.render.block_arrays`); with
        ``mirror``, the mean of each tower's and its mirror image's logits."""
        n = widths.shape[0]
        out = np.empty(n, dtype=np.float32)
        step = max(1, self.batch_size // self.images_per_tower)
        for start in range(0, n, step):
            stop = min(n, start + step)
            rows = (widths[start:stop], xs[start:stop], layers[start:stop], mask[start:stop])
            single, mirrored = tower_logits(self.net, self.renderer, *rows, self.device,
                                            self._images((stop - start) * self.images_per_tower), self.mirror)
            out[start:stop] = single if mirrored is None else (single + mirrored) / 2
        return out

    def probabilities(self, geometries) -> np.ndarray:
        """Stability probability of every geometry, rendered and scored in batches."""
        from overhang_framework.render import block_arrays

        if not len(geometries):
            return np.zeros(0)
        logits = self.logits_of_arrays(*block_arrays(geometries))
        return 1.0 / (1.0 + np.exp(-logits.astype(np.float64)))


def tower_logits(net, renderer, widths, xs, layers, mask, device, images: np.ndarray,
                 mirror: bool = False) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """The verdict logits of ``net`` (in eval mode) for the towers of padded block arrays, and with
    ``mirror`` those of their mirror images (x -> -x), from one forward pass. ``images`` is the buffer the
    towers are drawn into: at least one image a tower, two with ``mirror``. Returns ``(single, mirrored)``,
    ``mirrored`` being ``None`` without ``mirror``."""
    import torch

    k = widths.shape[0]
    images = images[:k * (2 if mirror else 1)]
    renderer.render_arrays(widths, xs, layers, mask, out=images[:k])
    if mirror:
        renderer.render_arrays(widths, -xs, layers, mask, out=images[k:])
    with torch.inference_mode():
        logits = net(as_input(images, device))[:, 0].float().cpu().numpy()
    return logits[:k], (logits[k:] if mirror else None)


def parse_mirror(value):
    """A ``mirror`` setting as ``"auto"``, ``True`` or ``False``: from those, or the words auto, true or
    false; ``ValueError`` naming what is allowed otherwise."""
    if value == "auto" or isinstance(value, bool):
        return value
    word = str(value).strip().lower()
    if word in ("auto", "true", "false"):
        return {"auto": "auto", "true": True, "false": False}[word]
    raise ValueError(f"mirror must be auto, true or false, got {value!r}")


def trained_mirrored(info: Mapping[str, Any]) -> bool:
    """Whether a checkpoint is best used with mirror averaging: its own record, from validation, or else
    whether its training showed it mirrored images (``augment.mirror > 0``)."""
    if isinstance(info.get("mirror"), bool):
        return info["mirror"]
    config = info.get("train_config") or {}
    return float((config.get("augment") or {}).get("mirror", 0) or 0) > 0
