"""Small image networks distilled from the stability CNN (the teacher): the same question, one image, a
fraction of the cost.

The student reads a coarser picture than the teacher: one row per layer (8 x 160 pixels, the
raster renderer with ``size: [8, 160]``), in two channels, the blocks' coverage (``fill``) and the
coordinate channel (``x``). Every block of a layer covers the same rows of the teacher's image, so
its 32 x 160 image is a fixed linear map of this one: nothing the teacher sees of a tower's geometry
is lost, only the shading. Columns stay 5 cm wide and exactly anti-aliased, so a block moved by a
fraction of a column still changes the picture.

A tower's balance is a comparison along x of loads above against supports below, so the network
treats the layers of a column as channels and convolves along x only (:class:`LayerConv`): a strided
first convolution over 40 cm windows, two more that halve the width each, and a dense head over the
remaining positions, which compares places far apart. No batch norm: nothing to fold at inference.

Architectures are registered by name in :data:`ARCHITECTURES`, and a checkpoint names its
architecture in ``backbone`` as a teacher's names its timm model, so one loader
(:class:`~overhang_framework.cnn.model.StabilityModel`) runs both.
"""

from __future__ import annotations

from typing import Callable, Sequence

#: The student's picture: one row per layer, the blocks' coverage and the coordinate channel.
STUDENT_RENDERER = {"name": "raster", "size": [8, 160], "channels": ["fill", "x"]}


def _layer_conv(widths: Sequence[int], hidden: int):
    def build(outputs: int, channels: int, size: Sequence[int]):
        return LayerConv(outputs, channels, size, widths, hidden)
    return build


def _module():
    import torch
    from torch import nn

    class _LayerConv(nn.Module):
        """Convolutions along x over the layers of a column as channels, then a dense head."""

        def __init__(self, outputs: int, channels: int, size: Sequence[int], widths: Sequence[int], hidden: int):
            super().__init__()
            height, width = int(size[0]), int(size[1])
            if width % 16:
                raise ValueError(f"a layer-conv student needs an image width divisible by 16, got {width}")
            c1, c2, c3 = (int(w) for w in widths)
            self.inputs = channels * height
            self.features = nn.Sequential(
                nn.Conv1d(self.inputs, c1, 8, stride=4, padding=2), nn.ReLU(),
                nn.Conv1d(c1, c2, 3, stride=2, padding=1), nn.ReLU(),
                nn.Conv1d(c2, c3, 3, stride=2, padding=1), nn.ReLU())
            self.head = nn.Sequential(nn.Flatten(), nn.Linear(c3 * (width // 16), hidden), nn.ReLU(),
                                      nn.Linear(hidden, outputs))

        def forward(self, images: "torch.Tensor") -> "torch.Tensor":
            return self.head(self.features(images.flatten(1, 2)))

    return _LayerConv


def LayerConv(outputs: int, channels: int, size: Sequence[int], widths: Sequence[int], hidden: int):
    """A :class:`_LayerConv` network (built on first use, so that importing this module needs no torch)."""
    return _module()(outputs, channels, size, widths, hidden)


#: Student architectures by name: ``build(outputs, channels, (height, width))`` -> a torch module.
ARCHITECTURES: dict[str, Callable] = {
    "layerconv_s": _layer_conv((32, 48, 64), 64),
    "layerconv_m": _layer_conv((48, 64, 96), 96),
}


def is_student(name: object) -> bool:
    return isinstance(name, str) and name in ARCHITECTURES


def build_student(name: str, outputs: int, channels: int, size: Sequence[int]):
    """The architecture ``name`` with random weights."""
    if not is_student(name):
        raise ValueError(f"unknown student architecture {name!r}; known: {', '.join(ARCHITECTURES)}")
    return ARCHITECTURES[name](outputs, channels, size)
