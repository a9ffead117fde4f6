"""``python -m overhang_framework.benchmark``: score one agent on one split (see :mod:`.run`)."""

from overhang_framework.benchmark.run import main

if __name__ == "__main__":
    main()
