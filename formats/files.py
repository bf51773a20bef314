"""Writing files so that nothing is ever half-written, and naming files inside a folder safely.

``atomic_write`` is the only way outputs reach the disk (manifests, reports, DNG frames, fit.json; the
EXR writer follows the same rule): a reader sees the old file or the new one, never a part.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from datetime import datetime, timezone
from pathlib import Path, PurePosixPath, PureWindowsPath

__all__ = ["atomic_write", "file_sha256", "now_iso", "safe_member"]


def atomic_write(path: str | Path, data: bytes, prefix: str = ".tmp-") -> Path:
    """Write ``data`` to ``path`` atomically: a temporary file in the same folder, flushed to disk, then
    renamed over ``path``; readable by all (0644: a session is shared data)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=prefix, suffix=".tmp")
    os.fchmod(fd, 0o644)  # mkstemp makes it private
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def now_iso() -> str:
    """The time now, UTC, ISO 8601 with milliseconds."""
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


def file_sha256(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's content."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


def safe_member(name: str) -> str:
    """``name`` if it is a plain file name inside a folder (optionally in sub-folders), else ValueError.

    A file name read from a manifest is data, not an instruction: an absolute path, a drive, ``..`` or a
    backslash would let it leave the folder."""
    if not isinstance(name, str) or not name or "\x00" in name:
        raise ValueError(f"file name {name!r} is empty or not text")
    if "\\" in name or PureWindowsPath(name).drive or PurePosixPath(name).is_absolute():
        raise ValueError(f"file name {name!r} would leave the session folder (absolute path or drive)")
    parts = PurePosixPath(name).parts
    if any(p in ("..", ".", "") for p in parts):
        raise ValueError(f"file name {name!r} would leave the session folder ('..' or '.')")
    return name
