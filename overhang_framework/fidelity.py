"""``python -m overhang_framework.fidelity``: Table 2 over a grid of the models' assumptions and over other draws of
tasks (the code: :mod:`overhang_framework.report.fidelity`). The names this module held are found there, with a
``DeprecationWarning``."""

import sys

from overhang_framework.moved import forwarder
from overhang_framework.report import fidelity as _moved
from overhang_framework.report.fidelity import main

__getattr__ = forwarder(__name__, [_moved])

if __name__ == "__main__":
    sys.exit(main())
