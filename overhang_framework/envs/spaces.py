"""The environment's observation and action spaces, and the conversions between them and the task.

One :class:`TowerSpaces` describes what an agent sees and does; the environment
and the ``policy`` planner both use it, so a saved policy is shown the same
arrays in the main job as in training.

Observation (a ``Dict``):

* ``blocks`` -- ``(max_blocks, 3)`` float32 rows ``(width, x, layer)`` of the
  placed blocks in placement order; rows of absent blocks are zero (a real
  block's width is never 0).
* ``remaining`` -- ``(max_blocks,)`` float32 widths still to place, the next
  one first, zero-padded.
* ``image`` (with ``observation="image"``, instead of ``blocks``) --
  ``(3, height, width)`` uint8 image of the tower drawn by the project's
  raster renderer, the one the CNN sees.

Action (a ``Dict``): ``x``, a ``(1,)`` float32 in ``[-4, 4]`` (the x of the
block's centre), and ``layer``, a ``Discrete`` layer of the grid. x is taken
to the micrometre (so a float32 ``0.3`` places a block at 0.3), or, with a
``resolution``, rounded to that grid step.

:meth:`TowerSpaces.flat_action_space` is the same action as a ``Box`` in
``[-1, 1]^2`` for libraries that support only ``Box`` actions: the first value
scaled to x, the second split into equal bins, one per layer a block can reach
in the current state (layer 1 up to one above the highest block), so that
every layer the flat action names could hold the block.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from overhang_framework.geometry import (
    GRID_HALF_WIDTH,
    KEY_DECIMALS,
    MAX_LAYER,
    WIDTHS,
    Action,
)
from overhang_framework.interfaces import State

OBSERVATIONS = ("arrays", "image")


@dataclass(frozen=True)
class TowerSpaces:
    """What an agent sees and does in tasks of up to ``max_blocks`` blocks."""

    max_blocks: int = 6
    observation: str = "arrays"
    resolution: float | None = None
    image_size: tuple = field(default=(32, 160))

    def __post_init__(self):
        if isinstance(self.max_blocks, bool) or not isinstance(self.max_blocks, int) \
                or not 2 <= self.max_blocks <= MAX_LAYER + 1:
            raise ValueError(f"max_blocks must be a whole number from 2 to {MAX_LAYER + 1}, got {self.max_blocks!r}")
        if self.observation not in OBSERVATIONS:
            raise ValueError(f"unknown observation {self.observation!r}; allowed: {', '.join(OBSERVATIONS)}")
        if self.resolution is not None and (isinstance(self.resolution, bool)
                                            or not isinstance(self.resolution, (int, float))
                                            or not self.resolution > 0):
            raise ValueError(f"resolution must be a positive number of metres or null, got {self.resolution!r}")
        object.__setattr__(self, "image_size", tuple(int(v) for v in self.image_size))

    def spec(self) -> dict:
        """Plain data that ``TowerSpaces(**spec)`` turns back into these spaces (saved with a policy); also the
        environment parameters that show a policy these spaces (``gym.make(ENV_ID, **spec, ...)``)."""
        out = asdict(self)
        out["image_size"] = list(self.image_size)
        return out

    # -- observations ---------------------------------------------------------------------------

    def observation_space(self):
        from gymnasium import spaces

        remaining = spaces.Box(0.0, max(WIDTHS), (self.max_blocks,), np.float32)
        if self.observation == "image":
            image = spaces.Box(0, 255, (3, *self.image_size), np.uint8)
            return spaces.Dict({"image": image, "remaining": remaining})
        low = np.tile(np.array([0.0, -GRID_HALF_WIDTH, 0.0], np.float32), (self.max_blocks, 1))
        high = np.tile(np.array([max(WIDTHS), GRID_HALF_WIDTH, MAX_LAYER], np.float32), (self.max_blocks, 1))
        return spaces.Dict({"blocks": spaces.Box(low, high, dtype=np.float32), "remaining": remaining})

    def check_fits(self, length: int, task_id: str) -> None:
        if length > self.max_blocks:
            raise ValueError(f"task {task_id} has {length} blocks but the observation holds max_blocks="
                             f"{self.max_blocks}; give max_blocks >= {length}")

    def observe(self, state: State, renderer=None) -> dict[str, np.ndarray]:
        """The observation of ``state`` (``renderer`` draws the image of ``observation="image"``)."""
        remaining = np.zeros(self.max_blocks, np.float32)
        remaining[:len(state.remaining)] = state.remaining
        if self.observation == "image":
            from overhang_framework.render import to_uint8

            image = to_uint8(renderer.render(state.geometry))  # (H, W, 3)
            return {"image": np.ascontiguousarray(np.moveaxis(image, -1, 0)), "remaining": remaining}
        blocks = np.zeros((self.max_blocks, 3), np.float32)
        if len(state.geometry):
            blocks[:len(state.geometry)] = state.geometry.as_array()
        return {"blocks": blocks, "remaining": remaining}

    def renderer(self):
        """The renderer of ``observation="image"`` (``None`` for arrays)."""
        if self.observation != "image":
            return None
        from overhang_framework.render import make_renderer

        return make_renderer({"name": "raster", "size": list(self.image_size)})

    # -- actions --------------------------------------------------------------------------------

    def action_space(self):
        from gymnasium import spaces

        return spaces.Dict({"x": spaces.Box(-GRID_HALF_WIDTH, GRID_HALF_WIDTH, (1,), np.float32),
                            "layer": spaces.Discrete(MAX_LAYER + 1)})

    @staticmethod
    def reachable_layers(state: State) -> int:
        """How many layers a block can go to in ``state``: 1 up to one above the highest block."""
        return max(1, min(MAX_LAYER, max((b.layer for b in state.geometry.blocks), default=0) + 1))

    def flat_action_space(self):
        from gymnasium import spaces

        return spaces.Box(-1.0, 1.0, (2,), np.float32)

    def unflatten(self, flat: Any, state: State) -> dict[str, Any]:
        """The ``Dict`` action of a flat ``[x, layer]`` action in ``[-1, 1]^2`` in ``state`` (values outside
        are clipped): x scaled to ``[-4, 4]``, and the layer one of :meth:`reachable_layers` equal bins."""
        a = np.asarray(flat, dtype=np.float64).reshape(-1)
        if a.shape != (2,) or not np.all(np.isfinite(a)):
            return {"x": np.array([np.nan], np.float32), "layer": 0}
        a = np.clip(a, -1.0, 1.0)
        bins = self.reachable_layers(state)
        layer = 1 + min(bins - 1, int(math.floor((a[1] + 1.0) / 2.0 * bins)))
        return {"x": np.array([a[0] * GRID_HALF_WIDTH], np.float32), "layer": layer}

    def flatten_action(self, action: Action, state: State) -> np.ndarray:
        """A flat action that :meth:`unflatten` maps back to ``action`` in ``state`` (a reachable layer)."""
        bins = self.reachable_layers(state)
        return np.array([action.x / GRID_HALF_WIDTH, ((action.layer - 0.5) / bins) * 2.0 - 1.0], np.float32)

    def to_action(self, action: Any) -> tuple[Action | None, str | None]:
        """``(Action, None)`` for a well-formed ``Dict`` action (x rounded to ``resolution`` when set),
        else ``(None, why)``."""
        try:
            x_arr = np.asarray(action["x"]).reshape(-1)
            layer_arr = np.asarray(action["layer"]).reshape(-1)
        except (TypeError, KeyError, IndexError, ValueError):
            return None, f"an action is a dict with keys 'x' and 'layer', got {action!r}"
        if x_arr.size != 1 or layer_arr.size != 1:
            return None, f"x and layer must be single values, got x={action['x']!r}, layer={action['layer']!r}"
        if x_arr.dtype.kind not in "iuf":
            return None, f"x must be a number, got {action['x']!r}"
        x = float(x_arr[0])
        if not math.isfinite(x):
            return None, f"x must be a finite number, got {x!r}"
        if abs(x) > 1e6:
            return None, f"x={x:g} is far outside the grid [-{GRID_HALF_WIDTH:g}, {GRID_HALF_WIDTH:g}]"
        raw_layer = layer_arr[0]
        if layer_arr.dtype.kind not in "iuf" or not float(raw_layer).is_integer():
            return None, f"layer must be a whole number, got {action['layer']!r}"
        if self.resolution is not None:
            x = round(round(x / self.resolution) * self.resolution, 10)
        else:  # to the micrometre: a float32 x such as 0.3 is the 0.3 it stands for
            x = round(x, KEY_DECIMALS) + 0.0
        return Action(x, int(raw_layer)), None
