"""``python -m overhang_framework.participants [OVERRIDES...]``: simulated participants (the code:
:mod:`overhang_framework.behaviour.simulation`). The names this module held are found there, with a
``DeprecationWarning``."""

from overhang_framework.behaviour import simulation as _simulation
from overhang_framework.behaviour.simulation import main
from overhang_framework.moved import forwarder

__getattr__ = forwarder(__name__, [_simulation])

if __name__ == "__main__":
    main()
