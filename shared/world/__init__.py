"""Worlds to measure search in beyond the paper's step model: ``continuous`` (a building's map,
travel along free space in metres and seconds, detection by range and line of sight). Needs the
``maps`` extra (scikit-image, SciPy)."""
