"""``python -m overhang_framework.docfigures``: the docs' figures, each registered with its command and the kept file
it comes from, checked against them (the code: :mod:`overhang_framework.report.docfigures`). The names this module
held are found there, with a ``DeprecationWarning``."""

import sys

from overhang_framework.moved import forwarder
from overhang_framework.report import docfigures as _moved
from overhang_framework.report.docfigures import main

__getattr__ = forwarder(__name__, [_moved])

if __name__ == "__main__":
    sys.exit(main())
