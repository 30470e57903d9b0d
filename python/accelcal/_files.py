"""Atomic file writing: a file the user asked for is either complete or untouched.

- A regular file (or a new path) is written to a temporary file beside it, flushed to disk and
  renamed over it, so readers never see half a file.
- A path that exists and is not a regular file (``/dev/null``, ``/dev/stdout``, a FIFO, a
  character device) is written through directly: renaming over it would replace the device or
  the pipe with a regular file.
- A path whose last component is a symbolic link is refused (the message names the link and
  its target): replacing the link would silently cut it, writing through it would change a file
  the user did not name. Give the target path instead.
- :func:`atomic_create` writes a new file the same way but never replaces one: the complete
  temporary file is hard-linked to its name, which fails when the name exists (a file kept
  by name, such as a fleet's calibration history).
- Temporary files are named ``.accelcal-tmp-<name>-<pid>-<random>`` in the target's folder.
  They are removed on any error, on Ctrl-C and on SIGTERM or SIGHUP (the process then exits
  with status 128 + the signal number); one left by a process that was killed outright
  (SIGKILL, power loss) is removed by the next write to the same path once its process is gone.
"""

from __future__ import annotations

import hashlib
import os
import signal
import stat
import sys
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import IO, Any

from ._core import CalibrationError

TMP_PREFIX = ".accelcal-tmp-"
_SIGNALS = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n))
_live: set[str] = set()  # temporary files of this process not yet renamed


def _umask() -> int:
    um = os.umask(0o022)
    os.umask(um)
    return um


def _remove_live() -> None:
    for tmp in list(_live):
        try:
            os.unlink(tmp)
        except OSError:
            pass
        _live.discard(tmp)


_previous: dict[int, Any] = {}  # the handler each cleanup handler replaced


def _on_signal(signum: int, frame: FrameType | None) -> None:
    """SIGTERM / SIGHUP while a temporary file is open: remove it, then do what the previous
    handler would have done (by default: exit with status 128 + signum)."""
    _remove_live()
    prev = _previous.get(signum)
    if callable(prev) and prev is not _on_signal:
        prev(signum, frame)
        return
    sys.exit(128 + signum)


@contextmanager
def _signals_cleanup() -> Iterator[None]:
    """Install the cleanup handlers for the duration of a write. Only in the main thread (where
    Python runs signal handlers); an ignored signal (``nohup``) stays ignored; a handler the
    application installed still runs, after the cleanup."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.getsignal(s) for s in _SIGNALS}
    for s, h in old.items():
        if h is signal.SIG_IGN or h is None or h is _on_signal:
            continue
        _previous[s] = h
        signal.signal(s, _on_signal)
    try:
        yield
    finally:
        for s, h in old.items():
            if h is not None and h is not signal.SIG_IGN and h is not _on_signal:
                signal.signal(s, h)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def clean_stale_temps(path: str | os.PathLike[str]) -> list[Path]:
    """Remove temporary files left beside ``path`` by accelcal processes that no longer run;
    return what was removed."""
    p = Path(path)
    folder = p.parent if str(p.parent) else Path(".")
    removed: list[Path] = []
    prefix = f"{TMP_PREFIX}{p.name}-"
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    for n in names:
        if not n.startswith(prefix):
            continue
        pid_s = n[len(prefix):].split("-", 1)[0]
        if not pid_s.isdigit() or int(pid_s) == os.getpid() or _pid_alive(int(pid_s)):
            continue
        try:
            os.unlink(folder / n)
            removed.append(folder / n)
        except OSError:
            pass
    return removed


def _kind(p: Path) -> str:
    """'missing', 'symlink', 'regular' or 'special' (device, FIFO, socket, ...)."""
    try:
        st = os.lstat(p)
    except FileNotFoundError:
        return "missing"
    if stat.S_ISLNK(st.st_mode):
        return "symlink"
    if stat.S_ISREG(st.st_mode):
        return "regular"
    if stat.S_ISDIR(st.st_mode):
        raise IsADirectoryError(21, "is a directory, not a file", str(p))
    return "special"


@contextmanager
def atomic_open(path: str | os.PathLike[str], mode: str = "w") -> Iterator[IO[Any]]:
    """Open ``path`` for writing so that it ends up complete or untouched (see the module doc).

    A regular file is written through a temporary file that replaces it once complete (the new
    file gets the mode an ordinary ``open()`` would give it, or keeps the mode of the file it
    replaces); a device or FIFO is written directly; a symbolic link is refused.
    """
    p = Path(path)
    kind = _kind(p)
    if kind == "symlink":
        raise CalibrationError(
            f"refusing to write to {str(p)!r}: it is a symbolic link to "
            f"{os.readlink(p)!r}; give the target path itself"
        )
    if kind == "special":
        with open(p, mode) as fh:
            yield fh
            fh.flush()
        return
    with _temp_beside(p) as (fd, tmp):
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        try:
            perm = os.stat(p).st_mode & 0o7777
        except FileNotFoundError:
            perm = 0o666 & ~_umask()
        os.chmod(tmp, perm)
        os.replace(tmp, p)
    _fsync_dir(_folder(p))


def _folder(p: Path) -> Path:
    return p.parent if str(p.parent) else Path(".")


@contextmanager
def _temp_beside(p: Path) -> Iterator[tuple[int, str]]:
    """A new temporary file in the folder of ``p`` (created if need be; stale temporaries of
    ``p`` cleaned first): ``(fd, name)``. It is removed on a signal and when the block ends
    unless the block renamed it."""
    folder = _folder(p)
    folder.mkdir(parents=True, exist_ok=True)
    clean_stale_temps(p)
    with _signals_cleanup():
        fd, tmp = tempfile.mkstemp(prefix=f"{TMP_PREFIX}{p.name}-{os.getpid()}-", dir=folder)
        _live.add(tmp)
        try:
            yield fd, tmp
        finally:
            _live.discard(tmp)
            try:
                os.unlink(tmp)  # renamed already: nothing there
            except OSError:
                pass


def atomic_create(path: str | os.PathLike[str], data: str | bytes) -> bool:
    """Write ``data`` to the new file ``path`` atomically, never replacing a file of that
    name, even one another process creates at the same moment: the complete temporary file
    is hard-linked to its name (on a file system without hard links: checked, then renamed,
    best effort). False, and nothing written, when ``path`` exists."""
    p = Path(path)
    if os.path.lexists(p):
        return False
    with _temp_beside(p) as (fd, tmp):
        with os.fdopen(fd, "wb" if isinstance(data, bytes) else "w") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        try:
            os.link(tmp, p)
        except FileExistsError:
            return False
        except OSError:
            if os.path.lexists(p):
                return False
            os.replace(tmp, p)
    _fsync_dir(_folder(p))
    return True


def _fsync_dir(folder: Path) -> None:
    """Make the rename durable (best effort: not every platform can open a folder)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike[str], data: str | bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder, then rename);
    devices and FIFOs are written directly, symbolic links refused (see :func:`atomic_open`)."""
    with atomic_open(path, "wb" if isinstance(data, bytes) else "w") as fh:
        fh.write(data)
    return Path(path)


def sha256_file(path: str | os.PathLike[str]) -> str:
    """The SHA-256 of a file's bytes (hex), read in blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def file_record(path: str | os.PathLike[str]) -> dict[str, Any]:
    """What a written file records of an input file: its absolute path, size and SHA-256
    (standard input, ``-``, cannot be read twice: its hash and size are null)."""
    if os.fspath(path) == "-":
        return {"path": "-", "sha256": None, "bytes": None}
    return {"path": os.path.abspath(path), "sha256": sha256_file(path),
            "bytes": os.path.getsize(path)}
