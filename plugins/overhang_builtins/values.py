"""Leaf values for search."""

from overhang_framework.geometry import overhang
from overhang_framework.interfaces import State, Value


class OverhangValue(Value):
    """The overhang of the leaf's geometry (the paper's ``V(s_{t+D})``)."""

    def __init__(self, world=None):
        self.world = world

    def __call__(self, state: State) -> float:
        return overhang(state.geometry)
