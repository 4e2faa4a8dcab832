"""What wrote a file: the ``created_with`` stamp of scenes and runs."""

from __future__ import annotations

from importlib.metadata import version


def package_version() -> str:
    """``"garmentnerf <version>"`` of the installed package, or ``"garmentnerf (source tree)"``."""
    try:
        return f"garmentnerf {version('garmentnerf')}"
    except Exception:  # not installed
        return "garmentnerf (source tree)"
