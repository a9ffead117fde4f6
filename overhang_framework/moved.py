"""Names that moved: a module's ``__getattr__`` that finds an old name at its new place, with a ``DeprecationWarning``
naming that place (the old one goes in the next release)."""

from __future__ import annotations

import warnings
from types import ModuleType
from typing import Any, Callable, Optional, Sequence


def forwarder(old: str, modules: Sequence[ModuleType], only: Optional[Sequence[str]] = None) -> Callable[[str], Any]:
    """The ``__getattr__`` of the module named ``old``: a name it no longer defines (one of ``only``, when given) is
    taken from the one of ``modules`` that defines it (else the first that has it), with a warning; anything else is
    an ``AttributeError``."""

    def __getattr__(name: str) -> Any:
        if (only is None or name in only) and not name.startswith("__"):
            having = [m for m in modules if hasattr(m, name)]
            home = next((m for m in having if getattr(getattr(m, name), "__module__", None) == m.__name__),
                        having[0] if having else None)
            if home is not None:
                warnings.warn(f"{old}.{name} moved to {home.__name__}.{name}; the old name goes in the next release",
                              DeprecationWarning, stacklevel=2)
                return getattr(home, name)
        raise AttributeError(f"module {old!r} has no attribute {name!r}")

    return __getattr__
