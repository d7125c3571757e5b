"""The version of crfdepth, from one source: ``version`` in ``pyproject.toml``.

An installed crfdepth (``pip install .`` or ``-e .``) reads it from the package metadata
that pip wrote from ``pyproject.toml``; a source tree run without installing reads
``pyproject.toml`` itself; anything else reports ``0+unknown``.
"""

from __future__ import annotations

from importlib import metadata
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: only the installed metadata is read
    tomllib = None

__all__ = ["__version__", "package_version"]

_PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"
UNKNOWN = "0+unknown"


def package_version() -> str:
    """``importlib.metadata.version("crfdepth")``, else the source tree's ``pyproject.toml`` version."""
    try:
        return metadata.version("crfdepth")
    except metadata.PackageNotFoundError:
        pass
    if tomllib is None:
        return UNKNOWN
    try:
        project = tomllib.loads(_PYPROJECT.read_text())["project"]
    except (OSError, ValueError, KeyError):
        return UNKNOWN
    return str(project.get("version", UNKNOWN)) if project.get("name") == "crfdepth" else UNKNOWN


__version__ = package_version()
