"""``python -m overhang_framework [overrides...]`` runs the main job; ``... plugins`` lists plugins."""

import sys

try:
    from overhang_framework.cli import main
except KeyboardInterrupt:  # Ctrl-C while the libraries load
    sys.stderr.write("interrupted while starting; nothing was written\n")
    sys.exit(130)

if __name__ == "__main__":
    main()
