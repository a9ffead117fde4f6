"""Moved to :mod:`overhang_framework.physics.towers`; this name goes in the next release."""

import warnings

from overhang_framework.physics.towers import *  # noqa: F401,F403
from overhang_framework.physics.towers import (  # noqa: F401
    CONTINUOUS, FAMILIES, CriticalTower, Question, Verdicts, episode_questions, family_towers, find_flips,
    last_block_interval, near_critical_towers, random_tower, random_towers, with_last_x)

warnings.warn("overhang_framework.bench.towers moved to overhang_framework.physics.towers; the old name goes in the "
              "next release", DeprecationWarning, stacklevel=2)
