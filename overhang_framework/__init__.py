"""overhang-framework: sequential physical planning on the Overhang Tower task."""

__version__ = "0.1.0"

from overhang_framework.envs import register as _register_envs  # noqa: E402

_register_envs()
