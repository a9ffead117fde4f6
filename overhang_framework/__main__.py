"""``python -m overhang_framework [overrides...]`` runs the main job; ``... plugins`` lists plugins."""

from overhang_framework.cli import main

if __name__ == "__main__":
    main()
