"""Writing output files without ever losing one: advisory locks, temporary files renamed into place,
and the checks of an output path made before any computation.

Every file shakerlab writes (run files, model JSON, report files, figures) is first written to a
temporary file in the destination's directory and renamed over the destination only once it is
complete (``os.replace``: atomic on one file system). An existing file is therefore never touched
before its replacement is whole; a failure or a crash leaves the old file as it was.

While a process writes ``X``, it holds an exclusive ``fcntl.flock`` on the sidecar ``X.lock`` (the
sidecar holds its process id and is removed when the lock is released; a sidecar left by a killed
process is stale, the kernel released its lock, and it is reused). A second shakerlab process that
wants to write ``X`` finds the lock held and refuses with a :class:`UserFacingError` naming the
holder. The lock is advisory: it binds shakerlab processes, not other programs.

A run file is recorded incrementally (crash safety, see ``shakerlab.runfile.format``) into
``X.partial`` (:func:`partial_path`), renamed to ``X`` when it is closed. After a crash the data is
in ``X.partial``; a later write of ``X`` refuses while it is there, naming the command that recovers it.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import secrets
from pathlib import Path

from shakerlab.errors import UserFacingError

HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def lock_path(path: str | Path) -> Path:
    path = Path(path)
    return path.with_name(path.name + ".lock")


def partial_path(path: str | Path) -> Path:
    """Where a run file is recorded until it is closed (and where a crash leaves it)."""
    path = Path(path)
    return path.with_name(path.name + ".partial")


def is_hdf5(path: str | Path) -> bool:
    """True if ``path`` starts with the HDF5 signature (at 0 or at a user-block offset 512, 1024, ...)."""
    try:
        with open(path, "rb") as fh:
            offset = 0
            while True:
                fh.seek(offset)
                head = fh.read(8)
                if head == HDF5_SIGNATURE:
                    return True
                if len(head) < 8:
                    return False
                offset = 512 if offset == 0 else 2 * offset
    except OSError:
        return False


class OutputLock:
    """An exclusive advisory lock on writing ``path`` (flock on the sidecar ``path.lock``).

    ``acquire()`` never waits: if another process holds the lock it raises UserFacingError.
    """

    def __init__(self, path: str | Path, what: str = "write"):
        self.path = Path(path)
        self.sidecar = lock_path(self.path)
        self.what = what
        self.fd: int | None = None

    def acquire(self) -> "OutputLock":
        for _ in range(20):
            try:
                fd = os.open(self.sidecar, os.O_RDWR | os.O_CREAT, 0o666)
            except OSError as exc:
                raise UserFacingError(f"{self.path}: cannot create the lock file {self.sidecar} ({exc.strerror}); "
                                      f"is the directory writable?") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                holder = _read_pid(fd)
                os.close(fd)
                if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise UserFacingError(
                        f"{self.path}: another shakerlab process{f' (pid {holder})' if holder else ''} is writing "
                        f"this file (lock {self.sidecar}); nothing was changed. Wait until it has finished, "
                        f"or choose another output name.") from None
                raise UserFacingError(f"{self.path}: cannot lock {self.sidecar} ({exc.strerror})") from None
            # the holder before us may have removed the sidecar just before we locked it: lock the live one
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.sidecar))
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            self.fd = fd
            return self
        raise UserFacingError(f"{self.path}: cannot take the lock {self.sidecar} (it keeps changing)")

    def release(self) -> None:
        if self.fd is None:
            return
        with contextlib.suppress(OSError):
            os.unlink(self.sidecar)
        os.close(self.fd)  # closing releases the flock
        self.fd = None

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _read_pid(fd: int) -> str:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        return os.read(fd, 32).decode(errors="replace").strip()
    except OSError:
        return ""


def temp_path(path: str | Path) -> Path:
    """A new, unused name in ``path``'s directory, ending as ``path`` does (matplotlib reads the suffix)."""
    path = Path(path)
    return path.with_name(f".{path.stem}.{secrets.token_hex(4)}.tmp{path.suffix}")


def check_output(path: str | Path, *, overwrite: bool = False, option: str = "-o", never_hdf5: bool = False,
                 what: str = "file") -> Path:
    """Refuse an output path before anything is computed: a missing directory, a directory where a file
    is wanted, an existing file without ``overwrite``, a run file (HDF5) when ``never_hdf5``, and a
    run file being recorded there (``path.partial``)."""
    path = Path(path)
    parent = path.parent
    if not parent.is_dir():
        raise UserFacingError(f"{option} {path}: directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UserFacingError(f"{option} {path}: directory {parent} is not writable")
    if path.is_dir():
        raise UserFacingError(f"{option} {path}: is a directory, expected a {what} name")
    if path.exists():
        if never_hdf5 and is_hdf5(path):
            raise UserFacingError(f"{option} {path}: is an HDF5 file (a run file?); it is never overwritten, "
                                  f"even with --force. Choose another name.")
        if not overwrite:
            raise UserFacingError(f"{option} {path}: file exists (choose another name, or --force)")
    return path


def check_directory(path: str | Path, *, option: str = "-o") -> Path:
    """Refuse an output directory before anything is computed: an existing file of that name, or no
    writable directory to create it in."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UserFacingError(f"{option} {path}: exists and is not a directory")
    anc = path
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise UserFacingError(f"{option} {path}: {anc} is not a directory")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise UserFacingError(f"{option} {path}: directory {anc} is not writable")
    return path


def refuse_partial(path: str | Path) -> None:
    """Refuse to write run file ``path`` while a recording's leftover ``path.partial`` is there."""
    part = partial_path(path)
    if part.exists():
        raise UserFacingError(
            f"{path}: {part} is there, the data of an interrupted recording (or one still running). It is "
            f"never overwritten: recover it with `shakerlab import --recover {part} -o {path}` (add --force "
            f"to replace an existing {Path(path).name}), or move it away.")


@contextlib.contextmanager
def atomic_output(path: str | Path, *, overwrite: bool = True, never_hdf5: bool = False, lock: bool = True):
    """Yield a temporary path next to ``path``; when the block ends without an exception, rename it onto
    ``path`` (under the output lock); otherwise delete it. ``path`` is untouched until the rename."""
    path = Path(path)
    held = OutputLock(path).acquire() if lock else None
    tmp = temp_path(path)
    try:
        yield tmp
        if not tmp.exists():
            raise RuntimeError(f"{tmp}: nothing was written")
        if path.exists():
            if never_hdf5 and is_hdf5(path):
                raise UserFacingError(f"{path}: is an HDF5 file (a run file?); it is never overwritten")
            if not overwrite:
                raise UserFacingError(f"{path}: file exists (choose another name, or --force)")
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if held is not None:
            held.release()


def write_text(path: str | Path, text: str, *, overwrite: bool = True, never_hdf5: bool = False) -> Path:
    """Write a text file through a temporary file (complete or not at all), under the output lock."""
    path = Path(path)
    with atomic_output(path, overwrite=overwrite, never_hdf5=never_hdf5) as tmp:
        try:
            with open(tmp, "w", encoding="utf-8") as fh:
                fh.write(text)
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as exc:
            raise UserFacingError(f"{path}: cannot write ({exc.strerror})") from None
    return path
