"""Safe file output: checked before the work starts, written atomically, never over anything else.

:func:`check_output_path` is called by every command before it plans or computes anything:
it refuses (``OutputError``) a path that exists and is not a regular file (a folder, a device
node such as ``/dev/null``, a FIFO, a socket, a symlink), a path that is one of the command's
inputs, a path whose folder cannot be made or written, and an extension the writer does not
support. :func:`atomic_path` then writes under a temporary name beside the final one and
renames it into place, so that a file appears complete or not at all; a temporary file left
by a killed writer is removed at the next write of the same path.
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from fiberplan.errors import OutputError

_TMP_TAG = ".part"


def _kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISDIR, "a folder"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket"), (stat.S_ISLNK, "a symbolic link"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.abspath(a) == os.path.abspath(b)


def check_output_path(
    path: str | os.PathLike[str],
    *,
    what: str = "output",
    suffixes: Iterable[str] | None = None,
    inputs: Iterable[str | os.PathLike[str] | None] = (),
) -> Path:
    """Refuse an output path that must not or cannot be written; return it as a ``Path``.

    Args:
        path: where the command will write.
        what: the option or role named in messages (``--out``, ``--picture``...).
        suffixes: the extensions the writer supports (lower case, with the dot), or ``None``
            for any.
        inputs: the command's input files; the output may not be one of them.

    Raises:
        OutputError: the path exists and is not a regular file, is one of the inputs, has an
            unsupported extension, or its folder cannot be made or written. The message names
            the user's path and the fix.
    """
    final = Path(path)
    if str(path) == "":
        raise OutputError(f"{what}: empty path; give a file name")
    _refuse_non_regular(final, what)
    for source in inputs:
        if source is not None and Path(source).exists() and _same_file(final, Path(source)):
            raise OutputError(f"{what} {str(final)!r} is also an input of this command; write the output to another path")
    if suffixes is not None:
        allowed = tuple(suffixes)
        if final.suffix.lower() not in allowed:
            raise OutputError(
                f"{what} {str(final)!r}: unsupported extension {final.suffix or '(none)'!r}; use one of {', '.join(allowed)}"
            )
    folder = final.parent if str(final.parent) else Path(".")
    existing = folder
    while not existing.exists() and not existing.is_symlink():
        if existing.parent == existing:
            break
        existing = existing.parent
    if not existing.is_dir():
        raise OutputError(
            f"{what} {str(final)!r}: its folder cannot be made because {str(existing)!r} is {_describe(existing)}; give another path"
        )
    if not _writable(existing):
        raise OutputError(f"{what} {str(final)!r}: folder {str(existing)!r} is not writable; give another path")
    return final


def _refuse_non_regular(final: Path, what: str) -> None:
    """Refuse a path that exists and is not a regular file (a symlink included: never followed)."""
    try:
        info = os.lstat(final)
    except (FileNotFoundError, NotADirectoryError):  # the folder check names a file in the way
        return
    except OSError as e:
        raise OutputError(f"{what} {str(final)!r}: cannot be checked ({e.strerror or e})") from e
    if not stat.S_ISREG(info.st_mode):
        raise OutputError(
            f"{what} {str(final)!r} exists and is {_kind(info.st_mode)}; fiberplan writes only new or regular files, give another path"
        )


def _describe(path: Path) -> str:
    try:
        return _kind(os.lstat(path).st_mode) if not path.is_file() else "a file"
    except OSError:
        return "not accessible"


def _writable(folder: Path) -> bool:
    """Whether a file can be created in ``folder`` (tried: permission bits mean little to root)."""
    try:
        fd, name = tempfile.mkstemp(prefix=".fiberplan-probe.", dir=folder)
    except OSError:
        return False
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(name)
    return True


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temporaries(final: Path) -> int:
    """Remove temporary files of ``final`` left by writers that no longer run; returns how many."""
    folder = final.parent if str(final.parent) else Path(".")
    removed = 0
    if not folder.is_dir():
        return 0
    for tmp in folder.glob(f".{final.name}.*{_TMP_TAG}{final.suffix}"):
        parts = tmp.name[len(final.name) + 2:].split(".")
        pid = int(parts[0]) if parts and parts[0].isdigit() else None
        if pid is None or (pid != os.getpid() and not _pid_alive(pid)):
            with contextlib.suppress(OSError):
                tmp.unlink()
                removed += 1
    return removed


@contextlib.contextmanager
def atomic_path(final_path: str | os.PathLike[str], *, what: str = "output") -> Iterator[Path]:
    """Yield a temporary path beside ``final_path``; rename it into place on success.

    The temporary file lives in the same folder so that :func:`os.replace` is an atomic
    rename, and its name carries the writer's process id, so that a later write of the same
    path removes what a killed writer left. If the body raises, the temporary file is removed
    and ``final_path`` is left as it was (absent, or holding its previous complete content).
    A path that exists and is not a regular file is refused (never replaced).

    Raises:
        OutputError: the path must not be written (:func:`check_output_path`), or writing
            failed; the message names ``final_path``, not the temporary file.
    """
    final = Path(final_path)
    _refuse_non_regular(final, what)
    directory = final.parent if str(final.parent) else Path(".")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{what} {str(final)!r}: cannot make its folder ({e.strerror or e})") from e
    remove_stale_temporaries(final)
    # The temporary name keeps the final suffix: some writers pick the format from it.
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{final.name}.{os.getpid()}.", suffix=f"{_TMP_TAG}{final.suffix}", dir=directory)
    except OSError as e:
        raise OutputError(f"{what} {str(final)!r}: cannot be written ({e.strerror or e})") from e
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        try:
            yield tmp
        except OSError as e:
            if isinstance(e, OutputError):
                raise
            raise OutputError(f"{what} {str(final)!r}: writing failed ({e.strerror or e})") from e
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        # Checked again just before the rename: something may have appeared there meanwhile.
        _refuse_non_regular(final, what)
        os.replace(tmp, final)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


_LOCKS_HELD: set[int] = set()
"""File descriptors of the locks :func:`exclusive` holds in this process."""


def _drop_locks_in_child() -> None:
    # A forked child (a worker pool's process, a leg planned ahead) gets copies of the lock's file
    # descriptor, and with them the lock: a killed run's orphaned workers would keep it held. The
    # child closes its copies; the lock stays with the parent's.
    for fd in _LOCKS_HELD:
        with contextlib.suppress(OSError):
            os.close(fd)
    _LOCKS_HELD.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_drop_locks_in_child)


@contextlib.contextmanager
def exclusive(path: str | os.PathLike[str], *, what: str = "output", fix: str = "wait for it to end, or stop it") -> Iterator[None]:
    """Hold the only right to write ``path`` (a result that a run rewrites as it goes) while the
    block runs; a second run that asks for it meanwhile is refused (:class:`OutputError`,
    naming the process that holds it and the fix) instead of racing the first (two resumes of one
    result each rewriting it with their own rows would lose the other's).

    The right is an advisory lock (``flock``) on a hidden file beside ``path``
    (``.<name>.lock``): the system releases it when its process ends, however it ends, so no stale
    lock outlives a killed run (forked children close their copies of it: a killed run's orphaned
    workers do not hold it). The file itself stays (removing it could let a third run lock a
    new file while a second still holds the old one)."""
    import fcntl

    final = Path(path)
    folder = final.parent if str(final.parent) else Path(".")
    folder.mkdir(parents=True, exist_ok=True)
    lock = folder / f".{final.name}.lock"
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip()  # (empty: the other run has just taken it)
            who = f"process {holder}" if holder else "it has just started"
            raise OutputError(f"{what} {str(final)!r} is being written by another run ({who}); {fix}") from None
        _LOCKS_HELD.add(fd)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        _LOCKS_HELD.discard(fd)
        os.close(fd)  # (closing releases the lock)
