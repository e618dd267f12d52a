"""Shipped assets (network weights, the default phantom's options): ``resources/`` of a checkout,
installed as the package data ``guidewire3d.resources`` (pyproject maps one to the other), so a
wheel carries them. Read them through :func:`resource_path`; nothing is downloaded at run time.
"""
from __future__ import annotations

from importlib import resources as _importlib_resources
from pathlib import Path

__all__ = ["resource_path"]

_CHECKOUT = Path(__file__).resolve().parent.parent / "resources"


def resource_path(name: str) -> Path:
    """The file ``name`` of the shipped resources (may not exist: callers say what is missing)."""
    try:
        p = Path(str(_importlib_resources.files("guidewire3d.resources") / name))
        if p.exists():
            return p
    except (ModuleNotFoundError, TypeError):
        pass
    return _CHECKOUT / name
