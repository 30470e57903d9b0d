"""Atomic file writing: a file the user asked for is either complete or untouched.

- A regular file (or a new path) is written to a temporary file beside it, flushed to disk and
  renamed over it, so readers never see half a file.
- A path that exists and is not a regular file (``/dev/null``, ``/dev/stdout``, a FIFO, a
  character device) is written through directly: renaming over it would replace the device or
  the pipe with a regular file.
- A path whose last component is a symbolic link is refused (the message names the link and
  its target): replacing the link would silently cut it, writing through it would change a file
  the user did not name. Give the target path instead. Two kinds of link are written through:
  the process's own streams (``/dev/stdout``, ``/dev/stderr``, ``/dev/fd/N``,
  ``/proc/self/fd/N``: a pipe, a terminal or a file the shell opened, whatever it is) and a
  link to a device or FIFO (nothing to replace).
- :func:`atomic_path` gives a library that writes by file name (HDF5) the name of the
  temporary file, renamed over the output at the end; devices, FIFOs and links are refused.
- :func:`atomic_create` writes a new file the same way but never replaces one: the complete
  temporary file is hard-linked to its name, which fails when the name exists (a file kept
  by name, such as a fleet's calibration history).
- Temporary files are named ``.accelcal-tmp-<name>-<pid>@<host>-<random>`` in the target's
  folder (``<name>`` shortened to its start and a hash when the whole would exceed the file
  system's longest file name, NAME_MAX). They are removed on any error, on Ctrl-C and on
  SIGTERM or SIGHUP (the process then exits with status 128 + the signal number).
- One left by a process that was killed outright (SIGKILL, power loss) is removed by the next
  write to the same path, once it is known to be stale. The writer holds an advisory lock
  (``flock``) on its temporary file while it writes, so a file someone holds locked is never
  removed, whoever holds it (a process in another PID namespace or container, another NFS
  host). A file nobody holds locked is removed when it was made on this host by a process that
  is gone, or, made on another host, when it was last modified more than a day ago (where
  locks do not reach across hosts, a writer on another host cannot be told from a dead one).
- Errors name the path the user gave, never the temporary file.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import secrets
import signal
import socket
import stat
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import IO, Any

from ._core import CalibrationError

try:
    import fcntl
except ImportError:  # pragma: no cover - not on Windows: no locks, the pid and age rules only
    fcntl = None  # type: ignore[assignment]

TMP_PREFIX = ".accelcal-tmp-"
#: This host in temporary file names (letters, digits, ``.`` and ``_`` only; at most 40).
HOST = re.sub(r"[^A-Za-z0-9._]", "_", socket.gethostname())[:40] or "host"
#: A temporary file of another host is removed only when it is older than this (seconds).
FOREIGN_TEMP_AGE = 86400.0
#: The longest suffix a temporary file may be given (see :func:`_temp_beside`).
_MAX_SUFFIX = 16
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


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):
        return 255


def temp_prefix(path: str | os.PathLike[str]) -> str:
    """The start of the names of the temporary files of ``path``:
    ``.accelcal-tmp-<name>-``, where a name too long to leave room for the rest (pid, host,
    random part, suffix) within the file system's NAME_MAX is shortened to its first 32
    characters, ``~`` and a hash of the whole."""
    p = Path(path)
    name = p.name
    # pid (10) + "@" + host (40) + "-" + random (8) + suffix: the same for every host.
    room = len(os.fsencode(f"{TMP_PREFIX}{name}-")) + 10 + 1 + 40 + 1 + 8 + _MAX_SUFFIX
    if room > _name_max(_folder(p)):
        name = f"{name[:32]}~{hashlib.sha256(os.fsencode(name)).hexdigest()[:16]}"
    return f"{TMP_PREFIX}{name}-"


def _lock(fd: int) -> int | None:
    """Hold an exclusive advisory lock on the open file ``fd`` (on a duplicate descriptor, so
    that closing ``fd`` keeps it): the descriptor to close to release it, or None where the
    file system has no locks."""
    if fcntl is None:
        return None
    dup = os.dup(fd)
    try:
        fcntl.flock(dup, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(dup)
        return None
    return dup


def _stale(f: Path, pid: int, host: str) -> bool:
    """Whether the temporary file ``f`` of process ``pid`` on ``host`` ('' for names written
    before hosts were named: this host) may be removed; see the module doc."""
    flags = os.O_RDWR | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    try:
        fd = os.open(f, flags)
    except OSError:
        return False
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            return False
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as e:
                if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    return False  # its writer holds it: alive, wherever it runs
                # no locks on this file system: the pid and age rules alone
        age = time.time() - st.st_mtime
        if host not in ("", HOST):
            return age > FOREIGN_TEMP_AGE
        return not (pid == os.getpid() or _pid_alive(pid))
    finally:
        os.close(fd)  # the lock, if taken, goes with it


def clean_stale_temps(path: str | os.PathLike[str]) -> list[Path]:
    """Remove temporary files left beside ``path`` by accelcal processes that no longer run
    (see the module doc for how that is told); return what was removed."""
    p = Path(path)
    folder = _folder(p)
    removed: list[Path] = []
    prefix = temp_prefix(p)
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    for n in names:
        if not n.startswith(prefix):
            continue
        pid_s, _, host = n[len(prefix):].split("-", 1)[0].partition("@")
        if not pid_s.isdigit() or not _stale(folder / n, int(pid_s), host):
            continue
        try:
            os.unlink(folder / n)
            removed.append(folder / n)
        except OSError:
            pass
    return removed


#: Errors of writing that carry no file name: the message then names the output.
_WRITE_ERRNOS = {getattr(errno, n) for n in ("ENOSPC", "EDQUOT", "EFBIG", "EROFS", "EIO")
                 if hasattr(errno, n)}


def user_path_error(e: OSError, path: str | os.PathLike[str]) -> OSError:
    """``e`` naming ``path`` (the output the user gave) where it names a temporary file of
    ours, or where it is a write error that names no file (disk full); else ``e`` itself."""
    name = e.filename
    ours = (name is not None and os.path.basename(os.fsdecode(name)).startswith(TMP_PREFIX))
    if not ours and not (name is None and e.errno in _WRITE_ERRNOS):
        return e
    if e.errno is None:
        return OSError(f"{e}: {os.fspath(path)!r}")
    return OSError(e.errno, e.strerror or os.strerror(e.errno), os.fspath(path))


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
    if kind == "symlink" and _through_link(p):
        kind = "special"
    if kind == "symlink":
        raise _symlink_refused(p)
    if kind == "special":
        try:
            with open(p, mode) as fh:
                yield fh
                fh.flush()
        except OSError as e:
            raise user_path_error(e, p) from None
        return
    with _temp_beside(p) as (fd, tmp):
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        _replace_keeping_mode(tmp, p)
    _fsync_dir(_folder(p))


@contextmanager
def atomic_path(path: str | os.PathLike[str], what: str = "this output") -> Iterator[str]:
    """:func:`atomic_open` for a library that writes a file by its name (HDF5): the name of a
    new, empty temporary file beside ``path`` that replaces ``path`` (mode as
    :func:`atomic_open` gives it) when the block ends without an error, and is removed
    otherwise. ``path`` must be a regular file or a new one: a symbolic link, a device or a
    FIFO is refused (such a file is written by seeking, not through a pipe)."""
    p = Path(path)
    kind = _kind(p)
    if kind == "symlink":
        raise _symlink_refused(p)
    if kind == "special":
        raise CalibrationError(f"{str(p)!r} is not a regular file: {what} is written by "
                               "seeking in it, not through a device or pipe")
    with _temp_beside(p) as (fd, tmp):
        os.close(fd)  # the library opens it by name; the lock stays held (a duplicate)
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        _replace_keeping_mode(tmp, p)
    _fsync_dir(_folder(p))


def _symlink_refused(p: Path) -> CalibrationError:
    """The error for an output that is a symbolic link (not one written through)."""
    return CalibrationError(f"refusing to write to {str(p)!r}: it is a symbolic link to "
                            f"{os.readlink(p)!r}; give the target path itself")


def _replace_keeping_mode(tmp: str, p: Path) -> None:
    """Put the complete temporary file ``tmp`` in the place of ``p``, with the mode of the file
    it replaces, or the one an ordinary ``open()`` gives a new file."""
    try:
        perm = os.stat(p).st_mode & 0o7777
    except FileNotFoundError:
        perm = 0o666 & ~_umask()
    os.chmod(tmp, perm)
    os.replace(tmp, p)


def _folder(p: Path) -> Path:
    return p.parent if str(p.parent) else Path(".")


#: The process's own streams, which a link names: written through whatever they are.
_OWN_STREAMS = re.compile(r"/dev/(stdout|stderr|fd/\d+)|/proc/(self|thread-self)/fd/\d+")


def _through_link(p: Path) -> bool:
    """Whether the symbolic link ``p`` is written through: ``/dev/stdout`` and the like (the
    process's own output, a pipe, a terminal or a file the shell opened), or a link to a
    device or FIFO (nothing to replace, no file changed that the user did not name)."""
    if _OWN_STREAMS.fullmatch(os.fspath(p)):
        return True
    try:
        st = os.stat(p)
    except OSError:
        return False
    return not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode))


def _locked_temp(p: Path, folder: Path, suffix: str) -> tuple[int, str, int | None]:
    """A new temporary file of ``p``: ``(fd, name, lock)``. It is created and locked under a
    name the cleaner of ``p`` does not look at, then linked to its own name: a cleaner
    never finds it unlocked while it lives."""
    fd, pre = tempfile.mkstemp(prefix=f"{TMP_PREFIX}new-{os.getpid()}-", dir=folder)
    _live.add(pre)
    try:
        lock = _lock(fd)
        stem = f"{temp_prefix(p)}{os.getpid()}@{HOST}-"
        for _ in range(100):
            tmp = os.path.join(folder, f"{stem}{secrets.token_hex(4)}{suffix}")
            try:
                os.link(pre, tmp)
            except FileExistsError:
                continue
            except OSError:  # no hard links on this file system
                os.rename(pre, tmp)
            _live.add(tmp)
            return fd, tmp, lock
        raise FileExistsError(errno.EEXIST, "no free temporary file name", tmp)
    except BaseException:
        os.close(fd)
        raise
    finally:
        _live.discard(pre)
        try:
            os.unlink(pre)
        except OSError:
            pass


@contextmanager
def _temp_beside(p: Path, suffix: str = "") -> Iterator[tuple[int, str]]:
    """A new temporary file in the folder of ``p`` (created if need be; stale temporaries of
    ``p`` cleaned first): ``(fd, name)``, locked while the block runs (see the module doc).
    It is removed on a signal and when the block ends unless the block renamed it. An
    OSError of the temporary file names ``p``. ``suffix`` (at most 16 characters) ends the
    name: several temporary files of one output told apart."""
    if len(suffix) > _MAX_SUFFIX:
        raise ValueError(f"temporary file suffix {suffix!r} is longer than {_MAX_SUFFIX}")
    folder = _folder(p)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        clean_stale_temps(p)
        with _signals_cleanup():
            fd, tmp, lock = _locked_temp(p, folder, suffix)
            try:
                yield fd, tmp
            finally:
                _live.discard(tmp)
                try:
                    os.unlink(tmp)  # renamed already: nothing there
                except OSError:
                    pass
                if lock is not None:
                    os.close(lock)
    except OSError as e:
        raise user_path_error(e, p) from None


def temp_beside(path: str | os.PathLike[str], suffix: str = ""
                ) -> contextlib.AbstractContextManager[tuple[int, str]]:
    """A temporary file beside ``path``, named, locked and cleaned as the module doc says:
    ``(fd, name)``, removed when the block ends (a part of an output assembled at the end,
    such as the arrays of a .npz)."""
    return _temp_beside(Path(path), suffix)


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


#: The most a small input file (a calibration, a list of dwell bounds) may hold, bytes: a
#: calibration file is a few kB; a device such as /dev/zero would be read without end.
SMALL_FILE_LIMIT = 64 << 20


def file_kind(mode: int) -> str:
    """A file type in words, for a message: 'a FIFO', 'a character device' ..."""
    for test, words in ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR,
                        "a character device"), (stat.S_ISBLK, "a block device"),
                        (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a folder")):
        if test(mode):
            return words
    return "not a regular file"


def read_small_text(path: str | os.PathLike[str], what: str,
                    limit: int = SMALL_FILE_LIMIT) -> str:
    """The text (UTF-8, a BOM dropped) of a small input file such as a calibration: a device
    (``/dev/zero``, ``/dev/urandom``: endless) or a folder is refused, and so is a file of more
    than ``limit`` bytes (its size named); a pipe (``<(cat cal.json)``) is read up to
    ``limit``. CalibrationError naming ``what`` and the path; OSError when it cannot be
    opened or read; UnicodeDecodeError when it is not text."""
    p = os.fspath(path)
    st = os.stat(p)
    if not (stat.S_ISREG(st.st_mode) or stat.S_ISFIFO(st.st_mode)):
        raise CalibrationError(f"{what} {p!r} is {file_kind(st.st_mode)}, not a file")
    mb = f"{limit / (1 << 20):g} MB"
    if st.st_size > limit:
        raise CalibrationError(f"{what} {p!r} holds {st.st_size} bytes, more than the "
                               f"{mb} such a file can hold: is it the right file?")
    with open(p, "rb") as fh:
        data = fh.read(limit + 1)
    if len(data) > limit:
        raise CalibrationError(f"{what} {p!r} holds more than the {mb} such a file can "
                               "hold: is it the right file?")
    return data.decode("utf-8-sig")


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
