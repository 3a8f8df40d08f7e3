"""File-path checks that need nothing heavy, so that a command can refuse a missing file in one
sentence before it imports torch (~4 s on a small CPU)."""

from __future__ import annotations

import os

from relight_core.errors import InputError


def name(path: str) -> str:
    """The file's name, as messages show it (never the server-side folder)."""
    return os.path.basename(path)


def check_path(path) -> str:
    """`path` as a string; InputError unless it is an existing, non-empty file."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError(f"The file {path} does not exist; pick an existing image or video.")
    if os.path.getsize(path) == 0:
        raise InputError(f"The file {name(path)} is empty; pick an image or video with content.")
    return path
