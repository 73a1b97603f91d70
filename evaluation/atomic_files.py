"""Files written whole or not at all: every file ddfuse writes goes through ``replacing``.

The data go to a hidden temporary file beside the target (``.<name>.partial-<pid>``, the same
directory, so the same file system), which is renamed onto the target only once it is complete
(``os.replace``, atomic on POSIX). A process killed at any point (SIGKILL included) or a disk
that fills up leaves the target as it was, the old file or none, never a truncated one; at worst
a ``.partial-`` file, which the next run into that directory removes (``remove_partials``).

An OSError while writing (no space left, permission denied, a read-only file system) becomes
``OutputError``, whose one line names the file: ``cannot write OUTDIR/smoother.csv: No space
left on device``. It is an ``OSError`` too, for callers that catch those. Not synced to the
disk (``fsync``): a power cut may still lose the last files; a killed process cannot.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import IO

from ddfuse.estimation.errors import DdfuseError

PARTIAL = ".partial-"  # in the temporary files' names: .<name>.partial-<pid>


class OutputError(DdfuseError, OSError):
    """A file that could not be written; the message names it and the system's reason."""

    @classmethod
    def of(cls, path: Path, e: OSError) -> OutputError:
        """'cannot write PATH: REASON', with the errno, reason and path of OSError ``e``."""
        return cls(e.errno, e.strerror or str(e), str(path))

    def __init__(self, errno=None, strerror=None, filename=None):
        super().__init__(errno, strerror, filename)

    def __str__(self) -> str:
        return f"cannot write {self.filename}: {self.strerror}"


def partial_path(path: Path) -> Path:
    """The temporary file ``path`` is written to before it is renamed into place."""
    return path.with_name(f".{path.name}{PARTIAL}{os.getpid()}")


@contextmanager
def replacing(path: str | Path, mode: str = "w") -> Iterator[IO]:
    """Open a temporary file for ``path`` (``mode`` 'w' text in UTF-8, or 'wb'); on leaving the
    block without an exception it replaces ``path``; on an exception (Ctrl-C included) it is
    removed and ``path`` is left as it was. An OSError becomes ``OutputError`` naming ``path``."""
    path = Path(path)
    tmp = partial_path(path)
    try:
        with open(tmp, mode, **({} if "b" in mode else {"encoding": "utf-8"})) as f:
            yield f
        os.replace(tmp, path)
    except OSError as e:
        _discard(tmp)
        if isinstance(e, OutputError):
            raise
        raise OutputError.of(path, e) from None
    except BaseException:
        _discard(tmp)
        raise


def write_text(path: str | Path, text: str) -> Path:
    """``Path(path).write_text(text)``, whole or not at all (``replacing``); returns the path."""
    with replacing(path) as f:
        f.write(text)
    return Path(path)


def write_bytes(path: str | Path, data: bytes) -> Path:
    """``Path(path).write_bytes(data)``, whole or not at all (``replacing``); returns the path."""
    with replacing(path, "wb") as f:
        f.write(data)
    return Path(path)


def remove(path: str | Path) -> None:
    """Remove the file ``path`` if it is there; OutputError naming it if it cannot be."""
    try:
        Path(path).unlink(missing_ok=True)
    except OSError as e:
        raise OutputError.of(Path(path), e) from None


def remove_partials(directory: Path) -> None:
    """Remove the temporary files that a killed writer left in ``directory``."""
    for p in Path(directory).glob(f".*{PARTIAL}*"):
        remove(p)


def _discard(tmp: Path) -> None:
    with suppress(OSError):  # the error that brought us here is the one to report
        tmp.unlink(missing_ok=True)
