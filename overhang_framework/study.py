"""``python -m overhang_framework.study``: planted, null and graded studies (the code: :mod:`overhang_framework.studies`,
one module a job). The names this module held are found at their new places, with a ``DeprecationWarning``."""

import sys

from overhang_framework.moved import forwarder
from overhang_framework.studies import findings as _findings
from overhang_framework.studies import gather as _gather
from overhang_framework.studies import power as _power
from overhang_framework.studies import report as _report
from overhang_framework.studies import run as _run
from overhang_framework.studies import steps as _steps
from overhang_framework.studies.command import main

__getattr__ = forwarder(__name__, [_findings, _power, _gather, _run, _report, _steps])

if __name__ == "__main__":
    sys.exit(main())
