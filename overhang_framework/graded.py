"""``python -m overhang_framework.graded``: a graded study's sample sizes, or the predictions, trends and sample sizes
of any fit's fitted measures (the code: :mod:`overhang_framework.studies.graded`). The names this module held are
found there, with a ``DeprecationWarning``."""

import sys

from overhang_framework.moved import forwarder
from overhang_framework.studies import graded as _graded
from overhang_framework.studies.graded import main

__getattr__ = forwarder(__name__, [_graded])

if __name__ == "__main__":
    sys.exit(main())
