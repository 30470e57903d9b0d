"""Atomic output files: complete or untouched; devices, FIFOs and symlinks never replaced;
temporary files removed on errors, Ctrl-C, SIGTERM and SIGHUP, and stale ones cleaned."""

from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from accelcal import CalibrationError
from accelcal._files import (
    TMP_PREFIX,
    atomic_create,
    atomic_open,
    atomic_write,
    clean_stale_temps,
)


def temps(folder: Path) -> list[str]:
    return sorted(n for n in os.listdir(folder) if n.startswith(TMP_PREFIX))


def test_regular_file_replaced_atomically_keeping_its_mode(tmp_path: Path) -> None:
    p = tmp_path / "out.csv"
    p.write_text("old\n")
    os.chmod(p, 0o640)
    with pytest.raises(RuntimeError):
        with atomic_open(p) as fh:
            fh.write("half")
            raise RuntimeError("boom")
    assert p.read_text() == "old\n" and temps(tmp_path) == []
    atomic_write(p, "new\n")
    assert p.read_text() == "new\n" and stat.S_IMODE(os.stat(p).st_mode) == 0o640
    assert temps(tmp_path) == []


def test_dev_null_is_written_through_not_replaced() -> None:
    before = os.stat("/dev/null")
    atomic_write("/dev/null", "x" * 1000)
    with atomic_open("/dev/null", "wb") as fh:
        fh.write(b"y")
    after = os.stat("/dev/null")
    assert stat.S_ISCHR(after.st_mode) and after.st_ino == before.st_ino
    assert temps(Path("/dev")) == []


def test_fifo_is_written_through(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got: list[str] = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_text()))
    reader.start()
    atomic_write(fifo, "through the pipe\n")
    reader.join(timeout=30)
    assert got == ["through the pipe\n"]
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and temps(tmp_path) == []


def test_symlink_is_refused_and_both_ends_untouched(tmp_path: Path) -> None:
    target = tmp_path / "real.csv"
    target.write_text("keep\n")
    link = tmp_path / "link.csv"
    link.symlink_to(target)
    with pytest.raises(CalibrationError, match="symbolic link.*real.csv"):
        atomic_write(link, "new\n")
    assert link.is_symlink() and target.read_text() == "keep\n" and temps(tmp_path) == []
    dangling = tmp_path / "dangling.csv"
    dangling.symlink_to(tmp_path / "nowhere.csv")
    with pytest.raises(CalibrationError, match="symbolic link"):
        atomic_write(dangling, "new\n")
    assert not (tmp_path / "nowhere.csv").exists()


def test_stale_temps_of_dead_processes_are_cleaned(tmp_path: Path) -> None:
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    dead_pid = int(dead.stdout)
    stale = tmp_path / f"{TMP_PREFIX}out.csv-{dead_pid}-abc123"
    live = tmp_path / f"{TMP_PREFIX}out.csv-{os.getppid()}-def456"
    other = tmp_path / f"{TMP_PREFIX}other.csv-{dead_pid}-ghi789"
    for f in (stale, live, other):
        f.write_text("partial")
    atomic_write(tmp_path / "out.csv", "done\n")
    assert not stale.exists() and live.exists() and other.exists()
    assert clean_stale_temps(tmp_path / "other.csv") == [other]


WRITER = """
import sys, time
from accelcal._files import atomic_open
with atomic_open(sys.argv[1], "wb") as fh:
    fh.write(b"x" * (1 << 20))
    fh.flush()
    print("started", flush=True)
    for _ in range(600):  # a long write: 60 s unless interrupted
        fh.write(b"y" * 4096)
        time.sleep(0.1)
print("finished", flush=True)
"""


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGHUP", "SIGINT"])
@pytest.mark.parametrize("existing", [False, True])
def test_signal_during_long_write_removes_temp(sig: str, existing: bool, tmp_path: Path) -> None:
    signum = getattr(signal, sig)
    out = tmp_path / "big.bin"
    if existing:
        out.write_bytes(b"previous")
    with subprocess.Popen([sys.executable, "-c", WRITER, str(out)], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True) as proc:
        assert proc.stdout is not None and proc.stderr is not None
        assert proc.stdout.readline().strip() == "started"
        assert len(temps(tmp_path)) == 1  # findable while it is being written
        time.sleep(0.2)
        proc.send_signal(signum)
        rc = proc.wait(timeout=60)
        err = proc.stderr.read()
    # SIGTERM/SIGHUP: exit 128 + signum; SIGINT: Python's KeyboardInterrupt (exit 1 or -2).
    if sig == "SIGINT":
        assert rc != 0 and "KeyboardInterrupt" in err
    else:
        assert rc == 128 + signum, err
    assert temps(tmp_path) == []
    if existing:
        assert out.read_bytes() == b"previous"
    else:
        assert not out.exists()


def test_nohup_keeps_sighup_ignored(tmp_path: Path) -> None:
    code = WRITER.replace("import sys, time", "import sys, time, signal\n"
                          "signal.signal(signal.SIGHUP, signal.SIG_IGN)")
    code = code.replace("range(600)", "range(10)")
    with subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "o.bin")],
                          stdout=subprocess.PIPE, text=True) as proc:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "started"
        proc.send_signal(signal.SIGHUP)
        assert proc.wait(timeout=60) == 0
    assert (tmp_path / "o.bin").stat().st_size > (1 << 20) and temps(tmp_path) == []


def test_cli_output_to_dev_null(tmp_path: Path) -> None:
    import numpy as np
    from accelcal.cli import main
    from click.testing import CliRunner

    rng = np.random.default_rng(0)
    f = tmp_path / "rec.csv"
    np.savetxt(f, rng.normal(size=(2000, 3)), delimiter=",", header="ax,ay,az", comments="")
    r = CliRunner().invoke(main, ["dwells", str(f), "--fs", "100", "-o", "/dev/null"])
    assert r.exit_code == 0, r.output
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode) and temps(Path("/dev")) == []
    link = tmp_path / "link.csv"
    link.symlink_to(tmp_path / "t.csv")
    r = CliRunner().invoke(main, ["dwells", str(f), "--fs", "100", "-o", str(link)])
    assert r.exit_code == 2 and "symbolic link" in r.output


def test_atomic_create_never_replaces_a_file_and_leaves_no_temporary(tmp_path: Path) -> None:
    p = tmp_path / "sub" / "cal.json"
    assert atomic_create(p, b"first\n")
    assert p.read_bytes() == b"first\n"
    assert (p.stat().st_mode & 0o777) == (0o666 & ~_umask_now())
    assert not atomic_create(p, b"second\n")
    assert p.read_bytes() == b"first\n"
    link = tmp_path / "sub" / "link.json"
    link.symlink_to(p)
    assert not atomic_create(link, "third\n")
    assert p.read_bytes() == b"first\n" and link.is_symlink()
    assert temps(p.parent) == []


def _umask_now() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def test_read_small_text_refuses_devices_and_files_too_large(tmp_path: Path) -> None:
    """A calibration or bounds file that is a device (/dev/zero, /dev/urandom) was read
    without end (MemoryError with an empty message); now it is refused, and so is a file
    above the limit (its size named, before it is read), and a pipe is read up to it."""
    from accelcal._files import read_small_text

    with pytest.raises(CalibrationError) as e:
        read_small_text("/dev/zero", "calibration file")
    assert str(e.value) == "calibration file '/dev/zero' is a character device, not a file"
    with pytest.raises(CalibrationError, match="is a folder, not a file"):
        read_small_text(tmp_path, "calibration file")
    big = tmp_path / "big.json"
    with open(big, "wb") as fh:  # sparse: no disk space used
        fh.truncate((64 << 20) + 1)
    with pytest.raises(CalibrationError) as e:
        read_small_text(big, "calibration file")
    assert str(e.value) == (f"calibration file {str(big)!r} holds 67108865 bytes, more than "
                            "the 64 MB such a file can hold: is it the right file?")
    ok = tmp_path / "ok.json"
    ok.write_bytes("\ufeff{}".encode())
    assert read_small_text(ok, "calibration file") == "{}"  # the BOM dropped
    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)

    def feed(n: int) -> None:
        try:
            with open(fifo, "wb") as fh:
                fh.write(b"x" * n)
        except BrokenPipeError:
            pass

    t = threading.Thread(target=feed, args=(300,), daemon=True)
    t.start()
    with pytest.raises(CalibrationError, match=r"'.*pipe.json' holds more than the "
                       r"0.000190735 MB"):
        read_small_text(fifo, "calibration file", limit=200)
    t.join(5)
    t = threading.Thread(target=feed, args=(100,), daemon=True)
    t.start()
    assert read_small_text(fifo, "calibration file", limit=200) == "x" * 100
    t.join(5)


def test_a_bounds_file_that_is_a_device_is_refused() -> None:
    """`dwells --bounds /dev/urandom` read without end; now one line naming it."""
    from accelcal.io import read_bounds

    with pytest.raises(CalibrationError) as e:
        read_bounds("/dev/urandom")
    assert str(e.value) == "the bounds file '/dev/urandom' is a character device, not a file"


LOCKED_CLEANER = """
import sys
import accelcal._files as f
f._pid_alive = lambda pid: False  # as from another PID namespace: no pid is visible
print([p.name for p in f.clean_stale_temps(sys.argv[1])])
"""


def test_live_temp_is_locked_and_kept_by_a_cleaner_that_cannot_see_its_pid(
        tmp_path: Path) -> None:
    """A second writer in another PID namespace (containers on one volume) took the first
    writer's live temporary file for stale and deleted it."""
    out = tmp_path / "out.csv"
    with atomic_open(out) as fh:
        fh.write("partial")
        fh.flush()
        (live,) = temps(tmp_path)
        r = subprocess.run([sys.executable, "-c", LOCKED_CLEANER, str(out)],
                           capture_output=True, text=True, check=True)
        assert r.stdout.strip() == "[]", r.stdout
        assert temps(tmp_path) == [live]
        fh.write(" and the rest\n")
    assert out.read_text() == "partial and the rest\n" and temps(tmp_path) == []
    # Left by a process killed outright (nobody holds its lock): removed.
    with atomic_open(out) as fh:
        (live,) = temps(tmp_path)
        os.link(tmp_path / live, tmp_path / (live + "x"))
    r = subprocess.run([sys.executable, "-c", LOCKED_CLEANER, str(out)],
                       capture_output=True, text=True, check=True)
    assert live + "x" in r.stdout and temps(tmp_path) == []


def test_another_hosts_temp_is_removed_only_when_old(tmp_path: Path) -> None:
    from accelcal._files import FOREIGN_TEMP_AGE, HOST

    other = "elsewhere" if HOST != "elsewhere" else "elsewhere2"
    young = tmp_path / f"{TMP_PREFIX}out.csv-1@{other}-aaaa1111"
    old = tmp_path / f"{TMP_PREFIX}out.csv-2@{other}-bbbb2222"
    for f in (young, old):
        f.write_text("partial")
    t = time.time() - FOREIGN_TEMP_AGE - 60
    os.utime(old, (t, t))
    assert clean_stale_temps(tmp_path / "out.csv") == [old]
    assert young.exists()


def test_temp_name_fits_a_long_output_name(tmp_path: Path) -> None:
    """A legal 254-byte output name failed: the temporary name added ~30 bytes."""
    name = "a" * 250 + ".csv"
    p = tmp_path / name
    seen: list[str] = []
    with atomic_open(p) as fh:
        fh.write("x\n")
        seen = temps(tmp_path)
    assert p.read_text() == "x\n" and temps(tmp_path) == []
    assert len(seen) == 1 and len(seen[0].encode()) <= os.pathconf(tmp_path, "PC_NAME_MAX")


def test_errors_name_the_output_not_the_temporary_file(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    p = tmp_path / "out.csv"

    def refuse(src: str, dst: str) -> None:
        raise PermissionError(13, "Permission denied", src)

    monkeypatch.setattr(os, "replace", refuse)
    with pytest.raises(PermissionError) as e:
        atomic_write(p, "x\n")
    assert e.value.filename == str(p) and TMP_PREFIX not in str(e.value)
    monkeypatch.undo()

    def full(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError, match="No space left") as e:
        atomic_write(p, "x\n")
    assert str(p) in str(e.value)
    monkeypatch.undo()
    assert temps(tmp_path) == [] and not p.exists()
    # Written through (a device): a full disk names the device.
    with pytest.raises(OSError, match="No space left") as e:
        atomic_write("/dev/full", "x" * 100_000)
    assert "/dev/full" in str(e.value)


def test_dev_stdout_is_written_through() -> None:
    """The module doc says /dev/stdout is written through; it was refused as a symlink."""
    code = "from accelcal._files import atomic_write; atomic_write('/dev/stdout', 'hello\\n')"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout == "hello\n"
