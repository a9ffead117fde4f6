"""overhang-framework: sequential physical planning on the Overhang Tower task."""

__version__ = "0.1.0"
