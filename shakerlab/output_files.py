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
import re
import secrets
import signal
import stat
import threading
from pathlib import Path

from shakerlab.errors import Terminated, UserFacingError

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
            try:    # never through a symbolic link: the lock file is truncated and rewritten
                fd = os.open(self.sidecar, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK, 0o666)
            except OSError as exc:
                if exc.errno == errno.ELOOP:
                    raise UserFacingError(f"{self.path}: the lock file {self.sidecar} is a symbolic link; it is "
                                          f"never followed. Remove it (nothing was changed).") from None
                if disk_full(exc):
                    raise no_space(self.sidecar) from None
                raise UserFacingError(f"{self.path}: cannot create the lock file {self.sidecar} ({exc.strerror}); "
                                      f"is the directory writable?") from None
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                os.close(fd)
                raise UserFacingError(f"{self.path}: the lock file {self.sidecar} is not a regular file; "
                                      f"remove it (nothing was changed)")
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
            try:
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
            except OSError as exc:
                with contextlib.suppress(OSError):
                    os.unlink(self.sidecar)
                os.close(fd)
                if disk_full(exc):
                    raise no_space(self.sidecar) from None
                raise UserFacingError(f"{self.path}: cannot write the lock file {self.sidecar} ({exc.strerror})") \
                    from None
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
    path = check_name(path, option=option)
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
    writable directory to create it in, a name that is not valid UTF-8."""
    path = check_name(path, option=option)
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
    ``path`` (under the output lock); otherwise delete it. ``path`` is untouched until the rename. SIGINT
    and SIGTERM are held meanwhile (:func:`signals_deferred`): one that arrives stops the write before the
    rename. A full file system is a one-line :class:`UserFacingError`."""
    path = check_name(path)
    with signals_deferred():
        held = OutputLock(path).acquire() if lock else None
        tmp = temp_path(path)
        try:
            try:
                yield tmp
            except (OSError, RuntimeError, ValueError) as exc:
                if disk_full(exc):
                    raise no_space(path, f"{path.name} was left as it was" if path.exists()
                                   else "nothing was written") from None
                raise
            if not tmp.exists():
                raise RuntimeError(f"{tmp}: nothing was written")
            if path.exists():
                if never_hdf5 and is_hdf5(path):
                    raise UserFacingError(f"{path}: is an HDF5 file (a run file?); it is never overwritten")
                if not overwrite:
                    raise UserFacingError(f"{path}: file exists (choose another name, or --force)")
            check_signals()
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
            if disk_full(exc):
                raise no_space(path) from None
            raise UserFacingError(f"{path}: cannot write ({exc.strerror})") from None
    return path


# ---- names ----------------------------------------------------------------------------------------------

def check_name(path: str | Path, *, option: str = "-o") -> Path:
    """Refuse a path that is not valid UTF-8 (HDF5 and the report's HTML and JSON store names as UTF-8)."""
    path = Path(path)
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        shown = os.fsencode(path).decode("utf-8", errors="backslashreplace")
        raise UserFacingError(f"{option} {shown}: the name is not valid UTF-8 (run files, reports and models "
                              f"store their names as UTF-8); choose another name. Nothing was written.") from None
    return path


def inside(directory: str | Path, name: str, suffix: str = "", *, option: str = "--plots") -> Path:
    """``directory / (name + suffix)``, refused unless it is a plain file name inside ``directory`` (a
    name from a run file never reaches outside the folder the user gave)."""
    directory = Path(directory)
    target = directory / f"{name}{suffix}"
    if (not name or "/" in name or "\\" in name or "\0" in name or name in (".", "..")
            or target.resolve().parent != directory.resolve()):
        raise UserFacingError(f"{option} {directory}: the output name {name + suffix!r} would be written outside "
                              f"{directory}; refused, nothing was written there")
    return target


# ---- full disk ----------------------------------------------------------------------------------------

_NO_SPACE = re.compile(r"No space left on device|errno = 28\b|\[Errno 28\]|ENOSPC")


def disk_full(exc: BaseException) -> bool:
    """True for the ways a full file system reaches Python: OSError ENOSPC, or an HDF5 (h5py) or PIL error
    whose message carries it."""
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    while exc is not None:
        if _NO_SPACE.search(str(exc)):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def mount_point(path: str | Path) -> Path:
    """The mount point of the file system holding ``path`` (or its nearest existing ancestor)."""
    p = Path(os.path.abspath(path))
    while not p.exists():
        p = p.parent
    while not os.path.ismount(p):
        p = p.parent
    return p


def free_bytes(path: str | Path) -> int:
    """Bytes available to this user on the file system holding ``path``."""
    p = Path(os.path.abspath(path))
    while not p.exists():
        p = p.parent
    st = os.statvfs(p)
    return st.f_bavail * st.f_frsize


def no_space(path: str | Path, what: str = "nothing was changed") -> UserFacingError:
    """The one-line error of a full file system: the device (mount point) and the file."""
    return UserFacingError(f"no space left on {mount_point(path)} (writing {path}); {what}")


def need_space(path: str | Path, n_bytes: int, what: str = "nothing was written") -> None:
    """Refuse before writing when the file system holding ``path`` has less than ``n_bytes`` free."""
    free = free_bytes(path)
    if free < n_bytes:
        raise UserFacingError(f"no space left on {mount_point(path)} (writing {path}: about {n_bytes} bytes "
                              f"needed, {free} free); {what}")


# ---- signals while a file is written -------------------------------------------------------------------

_pending: list[list[int]] = []      # one list of caught signals per active signals_deferred() block


def _interrupt(signum: int) -> KeyboardInterrupt:
    return Terminated("SIGTERM") if signum == signal.SIGTERM else KeyboardInterrupt()


def check_signals() -> None:
    """Raise the SIGINT (KeyboardInterrupt) or SIGTERM (Terminated) held by the innermost
    :func:`signals_deferred` block, if one arrived; a safe point between writes."""
    if _pending and _pending[-1]:
        signum = _pending[-1][0]
        _pending[-1].clear()
        raise _interrupt(signum)


@contextlib.contextmanager
def signals_deferred():
    """Hold SIGINT and SIGTERM while a file is written: an exception raised inside HDF5 or a write call
    can leave a file half done (or be swallowed as "Exception ignored"); held, the signal is raised at
    the next :func:`check_signals` or when the block ends, where the temporary files are removed and the
    existing file is left as it was."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []

    def hold(signum, frame):
        caught.append(signum)

    previous = {sig: signal.signal(sig, hold) for sig in (signal.SIGINT, signal.SIGTERM)}
    _pending.append(caught)
    try:
        yield
    finally:
        _pending.pop()
        for sig, old in previous.items():
            signal.signal(sig, old)
    if caught:
        raise _interrupt(caught[0])


def terminate_raises() -> None:
    """From now on SIGTERM raises :class:`Terminated` in the main thread (cleanup runs as for Ctrl-C)."""
    def handler(signum, frame):
        raise Terminated("SIGTERM")

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, handler)
