"""Where a command's outputs go: a folder claimed before the work starts, filled whole or not at all.

The promises every command keeps (the README states them once):

- **A session is never written to after its capture.** An output folder inside a session (a folder
  holding ``manifest.json``, or any folder below one) is refused.
- **Nothing is overwritten without ``--force``.** A folder already holding any file the command would
  write is refused, naming the files.
- **Two runs at once do not mix.** The folder is claimed by an exclusive lock file (its creation is
  atomic); a second run is refused while the first holds it. A lock left by a process that is gone is
  taken over.
- **An output is whole or absent.** The command writes into a staging folder inside the claimed one;
  only when everything is written are the files renamed into place, the completion marker (``fit.json``,
  ``calibration.json``) last. On any failure, Ctrl-C included, the staging folder is removed and what
  was there before is untouched.
- **A folder that cannot be written is refused before the work**, not after it: the claim writes there.

``claim_outputs(folder, products, force=…)`` does all of it; the command writes each product to
``staging.path(name)``.
"""

from __future__ import annotations

import errno
import os
import shutil
import socket
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Sequence

from .errors import InputError

__all__ = ["LOCK_NAME", "OutputError", "OutputExistsError", "Staging", "check_outputs", "claim_outputs", "inside_session", "refuse_inside_session", "write_file"]

#: The lock file of a claimed folder (its content: host and process id of the run holding it).
LOCK_NAME = ".skinlayers.lock"
_SESSION_MARKER = "manifest.json"
_STAGING_PREFIX = ".staging-"


class OutputError(InputError, OSError):
    """An output folder or file that cannot be used; the message says why and what to do."""


class OutputExistsError(OutputError, FileExistsError):
    """The output folder already holds what the command would write (``--force`` replaces it)."""


def inside_session(path: str | Path) -> Path | None:
    """The session folder ``path`` lies in or is (a folder holding ``manifest.json``), or None."""
    path = Path(path).resolve()
    for folder in (path, *path.parents):
        if (folder / _SESSION_MARKER).is_file():
            return folder
    return None


def refuse_inside_session(path: str | Path, what: str = "output") -> None:
    """``OutputError`` when ``path`` is a session folder or lies inside one."""
    session = inside_session(path)
    if session is not None:
        raise OutputError(f"{Path(path)}: the {what} would be written inside the session {session}; a session is never "
                          "written to after its capture: choose a folder outside it (-o)")


@dataclass(frozen=True)
class Staging:
    """Where a claimed run writes its ``products`` before they are moved into ``folder``."""

    folder: Path
    staging: Path
    products: tuple[str, ...]

    def path(self, name: str) -> Path:
        """The staging path of product ``name``."""
        if name not in self.products:
            raise ValueError(f"{name!r} is not one of the claimed products {list(self.products)}")
        return self.staging / name


@contextmanager
def claim_outputs(
    folder: str | Path, products: Sequence[str], *, force: bool = False, marker: str | None = None, lock_name: str = LOCK_NAME,
    what: str = "outputs",
) -> Iterator[Staging]:
    """Claim ``folder`` for ``products`` (file names), yield the ``Staging`` to write them to, then move
    every product written into place, ``marker`` last (see the module docstring). ``force`` replaces
    earlier products; without it a folder holding any of them is refused. A product not written is left
    as it was."""
    folder = Path(folder)
    check_outputs(folder, products, force=force, what=what)
    created = [p for p in (folder, *folder.parents) if not p.exists()]  # removed again if the run fails
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{folder}: cannot create the folder ({exc.strerror or exc})") from None
    done = False
    try:
        lock = _lock(folder / lock_name)
        try:
            try:
                staging_dir = Path(tempfile.mkdtemp(prefix=_STAGING_PREFIX, dir=folder))
            except OSError as exc:
                raise OutputError(f"{folder}: cannot write there ({exc.strerror or exc})") from None
            staging = Staging(folder, staging_dir, tuple(products))
            try:
                yield staging
                _commit(staging, products, marker)
                done = True
            finally:
                shutil.rmtree(staging_dir, ignore_errors=True)
        finally:
            lock.unlink(missing_ok=True)
    finally:
        if not done:
            for path in created:  # innermost first; a folder someone else filled meanwhile stays
                try:
                    path.rmdir()
                except OSError:
                    break


def write_file(path: str | Path, write: Callable[[Path], object], *, force: bool = False, what: str = "output") -> Path:
    """One output file under the same promises: ``write(staging_path)`` makes it, and it is renamed to
    ``path`` when whole (a figure, a maps file)."""
    path = Path(path)
    with claim_outputs(path.parent, [path.name], force=force, lock_name=f".{path.name}.lock", what=what) as staging:
        write(staging.path(path.name))
    return path


def check_outputs(folder: str | Path, products: Sequence[str], *, force: bool = False, what: str = "outputs") -> None:
    """The refusals of ``claim_outputs`` without claiming: a folder inside a session, a path that is not a
    folder, products already there without ``force``, a folder that cannot be created or written."""
    folder = Path(folder)
    refuse_inside_session(folder, what)
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{folder}: exists and is not a folder; choose another -o")
    existing = [name for name in products if (folder / name).exists()]
    if existing and not force:
        raise OutputExistsError(f"{folder}: already holds {', '.join(existing)}; choose another -o, or pass --force to replace them")
    nearest = next((p for p in (folder.absolute(), *folder.absolute().parents) if p.exists()), None)
    if nearest is None or not nearest.is_dir():
        raise OutputError(f"{folder}: cannot be written ({nearest} is not a folder); choose another -o")
    try:  # the only test of writability that holds for every user and file system: writing
        fd, probe = tempfile.mkstemp(prefix=".probe-", dir=nearest)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise OutputError(f"{folder}: cannot be written ({nearest}: {exc.strerror or exc}); choose another -o") from None


def _commit(staging: Staging, products: Sequence[str], marker: str | None) -> None:
    """Rename the written products into place: the old marker removed first, the new one last, so a
    folder with a marker always holds that run's products."""
    written = [name for name in products if (staging.staging / name).exists()]
    if marker is not None and marker in written:
        (staging.folder / marker).unlink(missing_ok=True)
    for name in sorted(written, key=lambda n: n == marker):
        os.replace(staging.staging / name, staging.folder / name)


def _lock(path: Path) -> Path:
    """Create the lock file exclusively (taking over one whose process is gone); ``OutputError`` when a
    live run holds it or the folder cannot be written."""
    me = f"{socket.gethostname()} {os.getpid()}\n"
    for _ in range(2):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            holder = _holder(path)
            if holder is None:  # its process is gone: a run that was killed, whose staging area is junk
                path.unlink(missing_ok=True)
                for stale in path.parent.glob(_STAGING_PREFIX + "*"):
                    shutil.rmtree(stale, ignore_errors=True)
                continue
            raise OutputError(f"{path.parent}: another run ({holder}) is writing here; wait for it, or choose another -o "
                              f"(if no run is active, remove {path})") from None
        except OSError as exc:
            if exc.errno in (errno.EACCES, errno.EROFS, errno.EPERM, errno.ENOSPC):
                raise OutputError(f"{path.parent}: cannot write there ({exc.strerror})") from None
            raise OutputError(f"{path.parent}: cannot claim the folder ({exc.strerror or exc})") from None
        with os.fdopen(fd, "w") as f:
            f.write(me)
        return path
    raise OutputError(f"{path.parent}: cannot claim the folder (its lock {path} keeps reappearing)")


def _holder(path: Path) -> str | None:
    """Who holds a lock: "host pid", or None when it is this host's and the process is gone."""
    try:
        host, pid = path.read_text().split()
    except (OSError, ValueError):
        return "an unknown run"
    if host != socket.gethostname():
        return f"process {pid} on {host}"
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return None
    except (PermissionError, ValueError):
        pass
    return f"process {pid}"
