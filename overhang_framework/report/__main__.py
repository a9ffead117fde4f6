"""``python -m overhang_framework.report DIR`` writes report.md and its figures (see :mod:`.build`)."""

import sys

from overhang_framework.report.build import main

if __name__ == "__main__":
    sys.exit(main())
