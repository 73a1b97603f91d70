"""Output paths checked before any work, so that a long run is not lost at its end.

Each check raises DdfuseError naming the option and the path; nothing is created here, so a
run refused later leaves nothing behind.
"""

from __future__ import annotations

import os
from pathlib import Path

from ddfuse.estimation.errors import DdfuseError


def _first_existing(path: Path) -> Path:
    """``path`` or its nearest ancestor that exists (the working directory at worst)."""
    for p in (path, *path.parents):
        if p.exists():
            return p
    return Path(".")


def check_output_file(path: Path, option: str, create_parents: bool = False) -> None:
    """Before any work: ``path`` (given as ``option``) can be written, i.e. it is not a
    directory and its directory exists (or, with ``create_parents``, can be created: no file on
    the way), is a directory and is writable. DdfuseError naming both otherwise."""
    path = Path(path)
    if path.is_dir():
        raise DdfuseError(f"{option} {path}: is a directory; give a file path")
    parent = path.parent
    anchor = _first_existing(parent)
    if not anchor.is_dir():
        raise DdfuseError(f"{option} {path}: {anchor} is a file, not a directory")
    if anchor != parent and not create_parents:
        raise DdfuseError(f"{option} {path}: no such directory {parent}")
    if not os.access(anchor, os.W_OK | os.X_OK):
        raise DdfuseError(f"{option} {path}: directory {anchor} is not writable")


def check_output_dir(path: Path, option: str) -> None:
    """Before any work: the output directory ``path`` (given as ``option``) is a writable
    directory or can be made one (no file on the way, its nearest existing ancestor
    writable); it is not created here, so a run refused later leaves nothing behind.
    DdfuseError naming it otherwise."""
    path = Path(path)
    anchor = _first_existing(path)
    if not anchor.is_dir():
        what = "is a file" if anchor == path else f"{anchor} is a file"
        raise DdfuseError(f"{option} {path}: {what}, not a directory")
    if not os.access(anchor, os.W_OK | os.X_OK):
        raise DdfuseError(f"{option} {path}: directory {anchor} is not writable")
