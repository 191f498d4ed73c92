"""Atomic file writing: a file at its final path is either the old one or the complete new one.

Every writer of vvloc (maps, CSV, g2o, TUM) writes into a temporary file in the destination's
directory, flushes it to disk (``fsync``), and renames it over the destination (``os.replace``,
atomic on POSIX and Windows for paths on one file system), then syncs the directory so that the
rename itself survives a crash. On any error, including ``KeyboardInterrupt`` (and ``SIGTERM``
in the ``vvloc`` command, which turns it into ``SystemExit``), the temporary file is removed and
an existing file at the destination is left untouched.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import hashlib
import io
import logging
import os
import re
import secrets
import shutil
import socket
import stat
import sys
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import IO, Any

__all__ = [
    "AtomicPath",
    "atomic_path",
    "atomic_write",
    "check_readable_file",
    "csv_row",
    "list_entries",
    "remove_stale_temps",
    "stale_temps",
    "symlink_loop",
    "temp_tag",
    "write_together",
]

_log = logging.getLogger(__name__)

#: A number field of the files vvloc reads, as C and most tools write it: Python's own
#: ``int``/``float`` also take ``1_000``, Unicode digits and surrounding blanks, which no
#: writer means.
INT_TEXT = re.compile(r"[+-]?[0-9]+")
FLOAT_TEXT = re.compile(
    # [0-9]+(?:\.[0-9]*)? and not [0-9]+\.?[0-9]*, which matches the same texts but splits a
    # run of digits between its two parts in every way: a 40 000-digit field that failed took
    # 23 s (the time grows with the square of the length)
    r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|[+-]?(?:inf|infinity|nan)",
    re.IGNORECASE,
)


def check_readable_file(path: str | os.PathLike[str]) -> None:
    """``ValueError`` naming ``path`` when it exists and is no regular file (a folder, device or
    named pipe: a reader would block on a pipe without a writer forever); a missing path is
    left to the reader's own ``FileNotFoundError``."""
    if os.path.exists(path) and not os.path.isfile(path):
        raise ValueError(f"{os.fspath(path)}: not a regular file (a folder, device or pipe)")


def csv_row(*fields: object) -> str:
    """One CSV line (no line end) of ``fields`` as ``str()`` gives them; a field holding a
    comma, a double quote or a line break (``\n`` or ``\r``) is quoted (RFC 4180), so that a
    session named ``day,1`` keeps its column."""
    buf = io.StringIO()
    # the writer quotes a field holding a character of its line terminator, so the terminator
    # must hold both line-break characters; it is cut off again below
    csv.writer(buf, lineterminator="\r\n").writerow(fields)
    return buf.getvalue().removesuffix("\r\n")


def list_entries(names: list[str], limit: int = 5) -> str:
    """The first ``limit`` of a folder's entry ``names`` for a message: ``"a, b and 3 more"``."""
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def _process_space() -> str:
    """The host name and, on Linux, the PID namespace of this process: where its process ids
    mean something (containers sharing the host's name, e.g. Docker's ``--network host``,
    each number their own processes)."""
    try:
        namespace = str(os.stat("/proc/self/ns/pid").st_ino)
    except OSError:  # not Linux
        namespace = ""
    return f"{socket.gethostname()}/{namespace}"


#: This process space in temporary names (a hash of :func:`_process_space`): a sweep judges
#: the processes whose ids it can ask about alone (another machine or container writing into a
#: shared folder has process ids of its own).
_HOST = hashlib.sha1(_process_space().encode("utf-8", "replace")).hexdigest()[:8]
#: What a temporary name holds between its prefix and its suffix (:func:`temp_tag`).
_TAG = re.compile(r"(?P<host>[0-9a-f]{8})-(?P<pid>[0-9]{1,10})-[0-9a-f]{12}")


def temp_tag() -> str:
    """The middle of a temporary name, ``<host>-<pid>-<random>``: this machine (a hash of its
    host name), this process and 12 random hex digits, so that :func:`remove_stale_temps` can
    tell a temporary a killed process left from one a running process is writing
    (:func:`stale_temps`)."""
    return f"{_HOST}-{os.getpid()}-{secrets.token_hex(6)}"


def _running(pid: int) -> bool:
    """Whether process ``pid`` of this machine runs (or may: when it cannot be asked)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)  # signal 0: the existence check, nothing is sent
    except ProcessLookupError:
        return False
    except (OSError, OverflowError):  # another user's process, or a pid the OS cannot take
        return True
    return True


def stale_temps(directory: Path, prefix: str, suffix: str = "") -> list[Path]:
    """What processes killed outright (SIGKILL, the out-of-memory killer: no handler runs) left
    in ``directory``: the files and folders named ``prefix + temp_tag() + suffix`` whose process
    was of this machine and runs no more, sorted by name. A running process's temporaries,
    other machines' and names of any other form are not among them."""
    try:
        names = sorted(e.name for e in os.scandir(directory))
    except OSError:
        return []
    stale = []
    for name in names:
        if not (name.startswith(prefix) and name.endswith(suffix)):
            continue
        tag = _TAG.fullmatch(name[len(prefix) : len(name) - len(suffix)])
        if tag is not None and tag["host"] == _HOST and not _running(int(tag["pid"])):
            stale.append(directory / name)
    return stale


def remove_stale_temps(directory: Path, prefix: str, suffix: str = "") -> list[Path]:
    """Remove the :func:`stale_temps` of ``directory`` (files, or folders with their contents),
    each with a logged warning; one that cannot be removed is skipped. Returns the removed."""
    removed = []
    for path in stale_temps(directory, prefix, suffix):
        try:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                os.unlink(path)
        except OSError:
            continue
        _log.warning("removed %s, which a stopped vvloc process left", path)
        removed.append(path)
    return removed


@contextlib.contextmanager
def made_folders(folder: str | os.PathLike[str]) -> Iterator[Path]:
    """Make ``folder`` and its missing parents for the block (yields it); when the block
    raises (an error, Ctrl-C), remove the folders made here that it left empty, deepest first
    (one written into meanwhile stays, and so do those above it)."""
    target = Path(folder)
    made = [p for p in (target, *target.parents) if not p.exists()]  # the deepest first
    target.mkdir(parents=True, exist_ok=True)
    try:
        yield target
    except BaseException:
        for p in made:
            try:
                p.rmdir()
            except OSError:  # not empty, or gone
                break
        raise


def symlink_loop(path: str | os.PathLike[str]) -> str | None:
    """``"<path> is a symbolic link that loops"`` (for a message) when following ``path``, or a
    folder above it, meets a loop of symbolic links (``ELOOP``: it can be neither read nor
    written, and ``Path.exists`` calls it missing); None otherwise. Writers refuse such an
    output path with ``FileExistsError`` (as a dangling link is refused), readers say it in
    their ``FileNotFoundError``."""
    try:
        os.stat(path)
    except OSError as e:
        if e.errno == errno.ELOOP:
            return f"{os.fspath(path)} is a symbolic link that loops (or lies below one)"
    return None


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(path: Path) -> None:
    # Directory fsync makes the rename durable; some platforms/file systems refuse it (Windows).
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _is_stream(path: Path) -> bool:
    """Whether ``path`` is to be written in place, as a plain ``open`` would, and never renamed
    over: it exists and is not a regular file or folder (a device, named pipe or socket,
    followed through symbolic links), or it names a process's open file (``/dev/stdout``,
    ``/dev/fd/N``, ``/proc/<pid>/fd/N``), which may be a regular file a shell redirected: a
    rename would take the file's name from under the open descriptor."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    if stat.S_ISDIR(mode):
        return False  # refused as a folder
    if not stat.S_ISREG(mode):
        return True
    return any(
        p.startswith(("/dev/", "/proc/")) for p in (os.path.abspath(path), os.path.realpath(path))
    )


def _own_descriptor(path: Path) -> int | None:
    """The descriptor of this process that ``path`` names (``/dev/stdout`` 1, ``/dev/stderr``
    2, ``/dev/fd/N``, ``/proc/self/fd/N``, ``/proc/<this pid>/fd/N``), else None."""
    text = os.path.abspath(path)
    named = {"/dev/stdin": 0, "/dev/stdout": 1, "/dev/stderr": 2}
    if text in named:
        return named[text]
    m = re.fullmatch(rf"/(?:dev/fd|proc/(?:self|{os.getpid()})/fd)/(\d+)", text)
    return int(m[1]) if m else None


def _open(path: Path, mode: str, **kwargs: Any) -> IO[Any]:
    """``open(path, mode)``, except that a path naming one of this process's descriptors
    (:func:`_own_descriptor`) writes through a duplicate of it: a file a shell redirected
    stdout to is written at the descriptor's offset, after what the process printed, not
    truncated and overwritten by a second, independent opening."""
    fd = _own_descriptor(path)
    if fd is None:
        return open(path, mode, **kwargs)
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(AttributeError, OSError, ValueError):
            stream.flush()  # what was printed comes first
    return os.fdopen(os.dup(fd), mode, **kwargs)


class AtomicPath:
    """A temporary path next to ``path`` that replaces ``path`` on :meth:`commit`.

    Use as a context manager: ``with AtomicPath(p) as tmp: write(tmp)`` commits when the block
    ends normally and aborts (removes the temporary file) when it raises. The temporary file is
    created empty (mode 0o666 minus the umask, like a plain ``open``; replacing an existing file
    keeps that file's mode, as writing into it would: its group and other bits from the start,
    so that a private file's new contents are never readable by others, and its owner bits at
    the commit, so that a read-only file can be replaced) with a hidden random name
    ``.<name>.<host>-<pid>-<hex>.tmp`` in the destination's directory, so the final rename never
    crosses file systems. A destination that is a symbolic link is followed: its target is
    replaced and the link kept, as writing into it would. A process killed outright (SIGKILL,
    power loss) may leave the hidden temporary file behind, the destination intact either way;
    the next write of that destination on this machine removes it (:func:`remove_stale_temps`).
    :meth:`commit` and :meth:`abort` may also be called explicitly (once).

    A destination that exists and is not a regular file (``/dev/null``, a named pipe), or that
    names an open file of a process (``/dev/stdout``, ``/dev/fd/N``: a terminal, a pipe or a
    file a shell redirected to) is a stream, not a file to replace: renaming over it would
    destroy the device node (as root, ``/dev/null`` would become a plain file that every later
    ``> /dev/null`` fills) or take a redirected file's name from under its descriptor.
    With ``streams=True`` (the default) such a destination is written directly, as a plain
    ``open`` would (``tmp`` is the destination itself; commit and abort touch nothing); with
    ``streams=False`` (a writer that needs a seekable file, such as an HDF5 map) it is refused
    with a ``ValueError``.
    """

    def __init__(self, path: str | os.PathLike[str], *, streams: bool = True) -> None:
        self.path = Path(os.fspath(path))
        if self.path.name in ("", ".", ".."):
            raise ValueError(f"path: expected a file path, got {os.fspath(path)!r}")
        self._done = False
        self.direct = _is_stream(self.path)
        if self.direct:
            if not streams:
                raise ValueError(
                    f"path: {self.path} is not a regular file (a device, pipe or socket); "
                    "expected the path of a file to write"
                )
            self.tmp = self.path  # a stream: written in place, never renamed over or removed
            return
        loop = symlink_loop(self.path)
        if loop:  # found only when the finished file was renamed into place
            raise FileExistsError(f"path: {loop}; expected the path of a file")
        if self.path.is_symlink():
            self.path = Path(os.path.realpath(self.path))  # replace the target, keep the link
        if self.path.is_dir():
            raise IsADirectoryError(f"{self.path}: is a folder; expected the path of a file")
        if not self.path.parent.is_dir():
            raise FileNotFoundError(
                f"{self.path}: its folder {self.path.parent} does not exist (create it first)"
            )
        self.tmp = self._create_temp()

    def _create_temp(self) -> Path:
        directory = self.path.parent
        try:  # a rewrite's temporary file is no more open than the file it replaces, and
            # its owner can write and read it (a read-only destination's mode is set at commit)
            mode = (stat.S_IMODE(os.stat(self.path).st_mode) & 0o077) | 0o600
        except FileNotFoundError:
            mode = 0o666
        remove_stale_temps(directory, f".{self.path.name}.", ".tmp")
        for _ in range(100):
            tmp = directory / f".{self.path.name}.{temp_tag()}.tmp"
            try:
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
            except FileExistsError:
                continue
            except OSError as e:  # a read-only or foreign folder: name the destination
                raise OSError(
                    e.errno, f"{e.strerror} (cannot create a file in {directory})", str(self.path)
                ) from e
            os.close(fd)
            return tmp
        raise FileExistsError(f"could not create a temporary file next to {self.path}")

    def commit(self) -> None:
        """Flush the temporary file to disk and rename it over the destination."""
        if self._done:
            raise RuntimeError(f"{self.path}: atomic write already finished")
        self._done = True
        if self.direct:
            return
        try:
            _fsync_file(self.tmp)
            with contextlib.suppress(FileNotFoundError):  # a rewrite keeps the file's mode
                os.chmod(self.tmp, stat.S_IMODE(os.stat(self.path).st_mode))
            os.replace(self.tmp, self.path)
        except BaseException:
            self._remove_temp()
            raise
        _fsync_dir(self.path.parent)

    def abort(self) -> None:
        """Remove the temporary file; the destination is left as it was. Idempotent."""
        self._done = True
        self._remove_temp()

    def _remove_temp(self) -> None:
        if self.direct:
            return
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.tmp)

    def __enter__(self) -> Path:
        return self.tmp

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.abort()


def atomic_path(path: str | os.PathLike[str]) -> AtomicPath:
    """Return an :class:`AtomicPath` for ``path`` (a context manager yielding the temp path)."""
    return AtomicPath(path)


@contextlib.contextmanager
def atomic_write(
    path: str | os.PathLike[str],
    mode: str = "w",
    *,
    encoding: str | None = "utf-8",
    newline: str | None = None,
) -> Iterator[IO[Any]]:
    """Open a temporary file for writing that atomically replaces ``path`` when the block ends.

    ``mode`` is ``"w"`` (text, ``encoding``/``newline`` as for :func:`open`) or ``"wb"``. If the
    block raises, nothing at ``path`` changes and the temporary file is removed.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"mode: expected 'w' or 'wb', got {mode!r}")
    with AtomicPath(path) as tmp:
        if mode == "wb":
            with _open(tmp, "wb") as fb:
                yield fb
        else:
            with _open(tmp, "w", encoding=encoding, newline=newline) as ft:
                yield ft


def write_together(folder: str | os.PathLike[str], files: dict[str, bytes]) -> None:
    """Write several files of ``folder`` as one change, as far as a file system allows: every
    file is written to its temporary and flushed to disk before the first of them replaces
    its destination, and the renames then follow one another. A failure or interrupt while
    writing (the slow part) changes no file; only one inside the few renames, a window of
    microseconds, could leave some files new and others old. ``files`` maps file names to
    their bytes."""
    folder = Path(os.fspath(folder))
    pending: list[AtomicPath] = []
    try:
        for name, data in files.items():
            ap = AtomicPath(folder / name)
            pending.append(ap)
            with _open(ap.tmp, "wb") as f:
                f.write(data)
            if not ap.direct:
                _fsync_file(ap.tmp)
        for ap in pending:
            ap.commit()
    except BaseException:
        for ap in pending:
            ap.abort()  # a committed one has no temporary left: nothing to undo there
        raise
