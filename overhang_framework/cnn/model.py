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

import contextlib
import functools
import re
import threading
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np

from overhang_framework.errors import ConfigError, first_line
from overhang_framework.results import atomic_output

CHECKPOINT_FORMAT = 1
CHECKPOINT_DIR = Path(__file__).parent / "checkpoints"
DEFAULT_CHECKPOINT = CHECKPOINT_DIR / "default.pt"
#: The shipped networks by name: ``teacher`` (also ``default``) was trained on the reference physics'
#: verdicts; ``student`` was distilled from it (:mod:`overhang_framework.cnn.distill`). Model cards beside them.
SHIPPED = {"default": DEFAULT_CHECKPOINT, "teacher": DEFAULT_CHECKPOINT, "student": CHECKPOINT_DIR / "student.pt"}
#: Smallest input side some backbones accept (their stems downsample too much below it).
MIN_INPUT_SIDE = {"inception_v4": 75}


#: Where a matching pair comes from: the wheel index PyTorch's install page gives for a compute platform.
TORCH_INDEX = "the --index-url that PyTorch's install page gives for {platform}"


def check_torch() -> None:
    """:class:`ConfigError` in one line saying what to install when torch and torchvision do not load
    together (a CPU torch beside a CUDA torchvision, say: timm imports torchvision). Checked once a process."""
    problem = _torch_problem()
    if problem:
        raise ConfigError(problem)


@functools.cache
def _torch_problem() -> Optional[str]:
    import importlib
    from importlib import metadata

    try:
        torch = importlib.import_module("torch")
    except Exception as err:
        return (f"PyTorch does not load ({first_line(err)}); install torch and torchvision from one index, "
                f"e.g. without a GPU: pip install torch torchvision, with {TORCH_INDEX.format(platform='cpu')}")
    try:
        importlib.import_module("torchvision")
    except Exception as err:
        try:
            found = f"torchvision {metadata.version('torchvision')}"
        except metadata.PackageNotFoundError:
            found = "torchvision"
        return (f"{found} does not work with torch {torch.__version__} ({first_line(err)}); install the pair "
                f"that matches: {matching_torchvision(torch.__version__, torch.version.cuda)}")
    return None


def matching_torchvision(torch_version: str, cuda: Optional[str]) -> str:
    """The pip command that installs the torchvision built for ``torch_version`` (``2.14.1+cpu``) and its
    compute platform (``cuda``: torch.version.cuda, None for a CPU build). The versions carry the platform
    (``0.29.1+cpu``) so that pip replaces a torchvision of the same number built for another platform."""
    platform = "cpu" if not cuda else "cu" + cuda.replace(".", "")
    index = TORCH_INDEX.format(platform=platform)
    release = re.match(r"2\.(\d+)\.(\d+)", torch_version)
    if release is None or int(release.group(1)) < 1:  # torchvision 0.(minor + 15) since torch 2.1
        return f"pip install --force-reinstall torch torchvision, with {index}"
    minor, patch = int(release.group(1)), int(release.group(2))
    return (f"pip install torch=={release.group(0)}+{platform} torchvision==0.{minor + 15}.{patch}+{platform}, "
            f"with {index}")


def check_backbone(backbone: str, size) -> None:
    """``ValueError`` when ``backbone`` is not a timm model or a student architecture
    (:mod:`overhang_framework.cnn.student`), or ``size`` (h, w) is too small for it."""
    check_torch()
    import timm

    from overhang_framework.cnn.student import is_student

    if is_student(backbone):
        return

    if not isinstance(backbone, str) or not timm.is_model(backbone):
        raise ValueError(f"unknown timm backbone {backbone!r}; e.g. mobilenetv3_small_100, regnetx_002, "
                         f"inception_v4 (timm.list_models() lists all)")
    need = MIN_INPUT_SIDE.get(backbone)
    if need is not None and min(size) < need:
        raise ValueError(f"backbone {backbone} needs inputs of at least {need}x{need}, got renderer size "
                         f"{list(size)}; set renderer.size")


def build_model(backbone: str, outputs: int = 1, channels: int = 3, size=None):
    """A timm ``backbone`` with random weights (``pretrained=False``) and ``outputs`` logits out, its
    weights in channels-last layout (about twice as fast on a CPU for these small inputs, measured for
    training and inference; feed it :func:`as_input`). The first logit is the stability verdict; any
    others are the training's auxiliary targets. A student architecture's name
    (:mod:`overhang_framework.cnn.student`) builds that network for images of ``size`` (h, w)."""
    import timm
    import torch

    from overhang_framework.cnn.student import build_student, is_student

    if is_student(backbone):
        return build_student(backbone, outputs, channels, size)

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
        raise ValueError(f"no CNN checkpoint at {path}; use checkpoint=teacher, student or a .pt file written "
                         f"by python -m overhang_framework.cnn.train or .distill")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        raise ValueError(f"{path} is not a readable CNN checkpoint: {err}") from err
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not a CNN checkpoint of format {CHECKPOINT_FORMAT}")
    return payload


def resolve_checkpoint(checkpoint: Optional[str]) -> Path:
    """A shipped network's name (:data:`SHIPPED`: ``teacher``, the same as ``default`` or ``None``, and
    ``student``) or a path to a ``.pt`` file."""
    if checkpoint is None:
        return DEFAULT_CHECKPOINT
    if isinstance(checkpoint, str) and checkpoint in SHIPPED:
        return SHIPPED[checkpoint]
    if not isinstance(checkpoint, (str, Path)):
        raise ValueError(f"checkpoint must be one of {', '.join(SHIPPED)} or a path to a .pt file, "
                         f"got {checkpoint!r}")
    return Path(checkpoint).expanduser()


RUNTIMES = ("onnxruntime", "torch")


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

    ``fused`` (default) is the network for inference: every batch norm folded
    into the convolution before it (:func:`fold_batch_norm`), run by
    ``runtime``: ``onnxruntime`` (the default, on the CPU, with as many
    threads as torch; the network is exported to ONNX once and kept, see
    :func:`onnx_network`) or ``torch``. A GPU device always runs torch. Its probabilities equal the trained
    network's up to float rounding. ``fused=False`` is the network as trained,
    run by torch, the reference the tests compare with (``runtime`` is then not
    used).
    """

    def __init__(self, checkpoint: Optional[str] = "default", device: str = "auto",
                 threads: Optional[int] = None, batch_size: int = 64, mirror="auto", fused: bool = True,
                 runtime: str = "onnxruntime"):
        check_torch()
        import torch

        from overhang_framework.render import make_renderer

        if threads is not None:
            if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
                raise ValueError(f"threads must be a whole number >= 1 or null, got {threads!r}")
            torch.set_num_threads(threads)
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"batch_size must be a whole number >= 1, got {batch_size!r}")
        if not isinstance(fused, bool):
            raise ValueError(f"fused must be true or false, got {fused!r}")
        if runtime not in RUNTIMES:
            raise ValueError(f"runtime must be one of {', '.join(RUNTIMES)}, got {runtime!r}")
        mirror = parse_mirror(mirror)
        self.path = resolve_checkpoint(checkpoint)
        payload = read_checkpoint(self.path)
        self.info = {k: v for k, v in payload.items() if k != "state_dict"}
        self.mirror = trained_mirrored(self.info) if mirror == "auto" else mirror
        self.backbone = payload["backbone"]
        self.renderer = make_renderer(payload["renderer"])
        self.device = pick_device(device)
        self.batch_size = batch_size
        self.fused = fused
        #: what runs the network: ``onnxruntime`` or ``torch``
        self.runtime = runtime if fused and self.device.type == "cpu" else "torch"
        # torch.fx (the folding) and torch.export patch torch's modules while they trace, so a network is built in
        # one thread at a time; an exported one is built once a process and shared (ONNX Runtime's sessions run
        # from any thread)
        n_threads = torch.get_num_threads()  # as this constructor set it, whatever another thread sets later
        with _EXPORTING:
            shared = None
            if self.runtime == "onnxruntime":
                import hashlib

                made = hashlib.sha256(self.path.read_bytes())
                made.update(repr((torch.__version__, self.renderer.shape, "folded")).encode())
                key = made.hexdigest()[:32]
                shared = _ONNX_SHARED.get((key, n_threads))
            if shared is not None:
                self.net, self.folded = shared
            else:
                self.net = build_model(self.backbone, int(payload.get("outputs", 1)), self.renderer.channels,
                                       (self.renderer.height, self.renderer.width))
                self.net.load_state_dict(payload["state_dict"])
                self.net.eval().to(self.device)
                #: batch norms folded into the convolution before them (0 unfused, or for a network torch.fx
                #: cannot trace)
                self.folded = fold_batch_norm(self.net) if fused else 0
                if self.folded:
                    self.net.to(memory_format=torch.channels_last)
                if self.runtime == "onnxruntime":
                    self.net = onnx_network(self.net, self.renderer.shape, n_threads, key=f"{key}-{self.folded}")
                    _ONNX_SHARED[(key, n_threads)] = (self.net, self.folded)
        self._buffer = self._new_buffer(0)

    @property
    def images_per_tower(self) -> int:
        return 2 if self.mirror else 1

    def _new_buffer(self, n: int) -> np.ndarray:
        """Images as the runtime takes them without a copy: ``(n, C, H, W)``, laid out channels last for
        the fused network in torch (the unfused one takes them as it always did)."""
        c, h, w = self.renderer.shape
        if self.runtime == "torch" and self.fused:
            return np.empty((n, h, w, c), dtype=np.float32).transpose(0, 3, 1, 2)
        return np.empty((n, c, h, w), dtype=np.float32)

    def _images(self, n: int) -> np.ndarray:
        if self._buffer.shape[0] < n:
            self._buffer = self._new_buffer(max(n, 2 * self._buffer.shape[0]))
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
                                            self._images((stop - start) * self.images_per_tower), self.mirror,
                                            flip=self.fused)
            out[start:stop] = single if mirrored is None else (single + mirrored) / 2
        return out

    def probabilities(self, geometries) -> np.ndarray:
        """Stability probability of every geometry, rendered and scored in batches."""
        from overhang_framework.render import block_arrays

        if not len(geometries):
            return np.zeros(0)
        logits = self.logits_of_arrays(*block_arrays(geometries))
        return 1.0 / (1.0 + np.exp(-logits.astype(np.float64)))


class OnnxNetwork:
    """A network exported to ONNX and run by ONNX Runtime on the CPU: ``net(images)`` takes
    ``(n, C, H, W)`` float32 NumPy images and returns the ``(n, outputs)`` logits as a NumPy array."""

    def __init__(self, model: bytes, threads: Optional[int] = None):
        import onnxruntime

        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = int(threads or 0)  # 0: ONNX Runtime's default, one per core
        options.inter_op_num_threads = 1
        options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
        self.session = onnxruntime.InferenceSession(model, options, providers=["CPUExecutionProvider"])
        self.input = self.session.get_inputs()[0].name

    def __call__(self, images: np.ndarray) -> np.ndarray:
        return self.session.run(None, {self.input: np.ascontiguousarray(images, dtype=np.float32)})[0]


_ONNX_MODELS: dict = {}
#: The exported networks of this process, with their folded batch norms, by checkpoint digest and threads.
_ONNX_SHARED: dict = {}
#: One network built and exported at a time in a process: ``torch.fx`` and ``torch.export`` are not thread-safe
#: (a pilot's concurrent participants, each building a CNN, crashed in them); the threads that wait then share
#: the network the first one built.
_EXPORTING = threading.RLock()


def onnx_cache_dir() -> Path:
    """Where exported networks are kept between processes: ``$XDG_CACHE_HOME/overhang_framework/onnx``
    (``~/.cache`` without it)."""
    import os

    return Path(os.environ.get("XDG_CACHE_HOME") or "~/.cache").expanduser() / "overhang_framework" / "onnx"


def onnx_network(net, shape, threads: Optional[int] = None, key: Optional[str] = None) -> OnnxNetwork:
    """``net`` (a torch network in eval mode, its batch norms folded) exported to ONNX with a free batch
    size (``torch.onnx.export``, the ``torch.export``-based exporter) and run by ONNX Runtime with
    ``threads`` threads. The export takes seconds, so with a ``key`` (a digest of everything that makes
    the network: the checkpoint's bytes, the torch version, the input shape) it is kept, in the process
    and as a file in :func:`onnx_cache_dir` (written atomically; a cache that cannot be written is
    skipped). Threads wait for each other's export (:data:`_EXPORTING`)."""
    with _EXPORTING:
        return _onnx_network(net, shape, threads, key)


def _onnx_network(net, shape, threads: Optional[int], key: Optional[str]) -> OnnxNetwork:
    model = _ONNX_MODELS.get(key) if key is not None else None
    path = onnx_cache_dir() / f"{key}.onnx" if key is not None else None
    if model is None and path is not None and path.is_file():
        model = path.read_bytes()
        try:
            network = OnnxNetwork(model, threads)
        except Exception:  # a damaged file: export again and replace it
            model = None
        else:
            _ONNX_MODELS[key] = model
            return network
    if model is None:
        model = export_onnx(net, shape)
        if key is not None:
            _ONNX_MODELS[key] = model
            try:
                with atomic_output(path) as tmp:
                    Path(tmp).write_bytes(model)
            except OSError:
                pass
    return OnnxNetwork(model, threads)


def export_onnx(net, shape) -> bytes:
    """The ONNX model of ``net`` for ``(batch, *shape)`` float32 inputs, the batch size left free."""
    import io
    import logging
    import warnings

    import torch

    quiet = [logging.getLogger(name) for name in ("torch.onnx", "torch.export", "onnxscript")]
    levels = [log.level for log in quiet]
    try:
        for log in quiet:
            log.setLevel(logging.ERROR)
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            program = torch.onnx.export(net, (torch.zeros(2, *shape),), dynamo=True, input_names=["images"],
                                        output_names=["logits"], optimize=True,
                                        dynamic_shapes=({0: torch.export.Dim("batch")},))
    finally:
        for log, level in zip(quiet, levels):
            log.setLevel(level)
    return program.model_proto.SerializeToString()


def fold_batch_norm(net) -> int:
    """Fold every batch norm that directly follows a convolution into that convolution, in place.

    For inference only (``net`` in eval mode): a batch norm then is a fixed affine map per channel, so
    ``bn(conv(x))`` is one convolution with scaled weights and a bias
    (``torch.nn.utils.fusion.fuse_conv_bn_eval``). The pairs are found on the network's ``torch.fx``
    graph (convolutions and batch norms kept whole): a batch norm (``nn.BatchNorm2d`` or timm's
    ``BatchNormAct2d``) whose input is a convolution's output that nothing else uses. Its place keeps
    what the module applied after normalising (``BatchNormAct2d``: its dropout and activation), or
    nothing. Returns the number of batch norms
    folded; a network that ``torch.fx`` cannot trace is left as it is (0).
    """
    import torch
    from torch import fx, nn
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    if net.training:
        raise ValueError("fold_batch_norm needs a network in eval mode (net.eval()): training updates batch norms")

    class Tracer(fx.Tracer):
        def is_leaf_module(self, module, name):
            return isinstance(module, (nn.Conv2d, nn.BatchNorm2d)) or super().is_leaf_module(module, name)

    from timm.layers import BatchNormAct2d

    foldable = (nn.BatchNorm2d, BatchNormAct2d)  # exactly these: a subclass may do more in its forward
    try:
        graph = Tracer().trace(net)
    except Exception:  # any model code fx cannot follow: keep the network unfused
        return 0
    modules = dict(net.named_modules())
    pairs = []
    for node in graph.nodes:
        if node.op != "call_module" or type(modules[node.target]) not in foldable:
            continue
        source = node.args[0] if node.args else None
        if isinstance(source, fx.Node) and source.op == "call_module" and len(source.users) == 1 \
                and isinstance(modules[source.target], nn.Conv2d) \
                and modules[node.target].track_running_stats:
            pairs.append((source.target, node.target))

    def put(name: str, module) -> None:
        parent, _, attr = name.rpartition(".")
        setattr(net.get_submodule(parent) if parent else net, attr, module)

    with torch.no_grad():
        for conv_name, bn_name in pairs:
            bn = modules[bn_name]
            put(conv_name, fuse_conv_bn_eval(modules[conv_name], bn))
            after = [m for m in (getattr(bn, "drop", None), getattr(bn, "act", None)) if isinstance(m, nn.Module)]
            put(bn_name, nn.Sequential(*after) if after else nn.Identity())
    return len(pairs)


def tower_logits(net, renderer, widths, xs, layers, mask, device, images: np.ndarray,
                 mirror: bool = False, flip: bool = False) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """The verdict logits of ``net`` (a torch network in eval mode, or an :class:`OnnxNetwork`) for the
    towers of padded block arrays, and with ``mirror`` those of their mirror images (x -> -x), from one
    forward pass. ``images`` is the buffer the towers are drawn into: at least one image a tower, two
    with ``mirror``. With ``flip`` and a renderer that can mirror its images
    (:meth:`RasterRenderer.mirror_images`), the mirror images are the towers' images flipped, equal to
    drawing them up to float rounding; otherwise they are drawn. Returns ``(single, mirrored)``,
    ``mirrored`` being ``None`` without ``mirror``."""
    import torch

    k = widths.shape[0]
    images = images[:k * (2 if mirror else 1)]
    renderer.render_arrays(widths, xs, layers, mask, out=images[:k])
    if mirror:
        mirror_images = getattr(renderer, "mirror_images", None) if flip else None
        if mirror_images is not None:
            mirror_images(images[:k], out=images[k:])
        else:
            renderer.render_arrays(widths, -xs, layers, mask, out=images[k:])
    if isinstance(net, OnnxNetwork):
        logits = net(images)[:, 0].astype(np.float32)
    else:
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
