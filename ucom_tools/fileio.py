"""Every file ucom-tools writes or reads, by the rules of ``ucom(1)``, FILES.

Writing (:class:`Output`, :func:`write_bytes`, :func:`write_text`, :class:`Batch`):

- a regular file (or a name that does not exist yet) is replaced atomically: the data go
  to a temporary file in the same directory, which is synced and renamed over the target,
  with the old file's mode (and, when we may, its owner) or ``0644`` under the umask; a
  failure leaves the old file as it was and no temporary file behind;
- a symbolic link stays a link: the file it points to is replaced (a dangling link gets
  its target created);
- a character device, FIFO or socket (``/dev/null``, ``/dev/stdout``, a named pipe) is
  written through, never replaced; a block device or a directory is refused;
- ``-`` is standard output where a command writes one file.

A target that cannot be written at all (its directory missing, a directory in its place,
a read-only file system) is :class:`~ucom_tools.errors.InputError` raised before anything
is sent or written (exit code 3); a failure while writing or committing (a full disk, an
I/O error) is :class:`~ucom_tools.errors.WriteError` (exit code 5).  The ``key``
parameters name the output or input as the caller's API does (``journal``, ``output``):
the errors' ``key``, which the CLI words as its option.

Reading (:func:`read_input`): input files are regular files (or ``-`` where a command
documents it), never FIFOs or devices that would block or never end, read with a size cap.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any, BinaryIO, Literal, Self

from ucom_tools.errors import InputError, WriteError

STDOUT = "-"
"""The name of standard output (and standard input) where a command documents it."""

DEFAULT_MODE = 0o644
"""The mode of a new file, before the umask."""

MiB = 1 << 20
IMAGE_LIMIT = 16 * MiB
"""The largest firmware image read (S-record or Intel HEX text)."""
TEXT_LIMIT = 4 * MiB
"""The largest attribute tree or topology read (ARMAR-III's largest tree is 5 KiB)."""

Kind = Literal["file", "through", "stdout"]

_umask_lock = threading.Lock()


def _umask() -> int:
    with _umask_lock:  # reading it means setting it: not while another thread does
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def new_file_mode() -> int:
    """The mode a new file gets: ``0644`` under the umask."""
    return DEFAULT_MODE & ~_umask()


def reason(err: BaseException) -> str:
    """An OSError's text without its errno and path (``No space left on device``)."""
    if isinstance(err, OSError) and err.strerror:
        return err.strerror
    return str(err) or type(err).__name__


class _Staged:
    """Committed when a ``with`` block ends without an exception, discarded otherwise."""

    def commit(self) -> None:
        raise NotImplementedError

    def discard(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, kind: Any, exc: Any, tb: Any) -> None:
        if kind is None:
            self.commit()
        else:
            self.discard()


class Output(_Staged):
    """One file to write by the rules of the module docstring.

    Use as a context manager: :attr:`write_path` (or :meth:`open`) is where to write, and
    leaving the block without an exception commits (a regular file renamed into place),
    with one discards.  ``suffix`` is the ending the temporary file's name must have
    (python-can picks a log's format by it); ``allow_stdout`` lets ``-`` mean standard
    output."""

    def __init__(self, path: str | os.PathLike[str], *, key: str | None = None,
                 suffix: str = "", allow_stdout: bool = False) -> None:
        self.name = os.fspath(path)
        self.key = key
        self.kind: Kind
        self._tmp: str | None = None
        self._mode = DEFAULT_MODE
        self._owner: tuple[int, int] | None = None
        self._done = False
        if self.name == STDOUT and allow_stdout:
            self.kind = "stdout"
            self.target = self.name
            return
        self.target = os.path.realpath(self.name)  # a link stays a link: write its target
        try:
            st = os.stat(self.target)
        except FileNotFoundError:
            st = None
        except OSError as err:
            raise self._input(reason(err)) from None
        if st is not None and stat.S_ISDIR(st.st_mode):
            raise self._input("is a directory (a file name is expected)")
        if st is not None and stat.S_ISBLK(st.st_mode):
            raise self._input("is a block device; ucom writes regular files, character "
                              "devices, FIFOs and sockets only")
        if st is not None and not stat.S_ISREG(st.st_mode):
            self.kind = "through"  # a character device, FIFO or socket: never replaced
            self._check_through()
            return
        self.kind = "file"
        directory = os.path.dirname(self.target) or "."
        if not os.path.isdir(directory):
            what = "does not exist" if not os.path.exists(directory) else "is not a directory"
            raise self._input(f"directory {directory} {what}")
        if st is not None:
            self._mode = stat.S_IMODE(st.st_mode)
            if os.geteuid() == 0 and (st.st_uid, st.st_gid) != (0, 0):
                self._owner = (st.st_uid, st.st_gid)
        else:
            self._mode = new_file_mode()
        base = os.path.basename(self.target)
        stem = base[:-len(suffix)] if suffix and base.endswith(suffix) else base
        try:
            fd, self._tmp = tempfile.mkstemp(dir=directory,
                                             prefix=f".{stem.replace('.', '_')}-",
                                             suffix=suffix or ".tmp")
            os.close(fd)
        except OSError as err:
            raise self._input(f"cannot write in {directory}: {reason(err)}") from None

    # ------------------------------------------------------------------ properties
    @property
    def write_path(self) -> str:
        """Where the data go: the temporary file, or the device / FIFO itself."""
        if self.kind == "stdout":
            return "/dev/stdout"
        return self._tmp if self._tmp is not None else self.target

    def _check_through(self) -> None:
        """A character device or FIFO must be writable; a socket must accept a
        connection (checked when written)."""
        mode = os.stat(self.target).st_mode
        if stat.S_ISSOCK(mode):
            return
        if not os.access(self.target, os.W_OK):
            raise self._input("is not writable")

    def _input(self, text: str) -> InputError:
        return InputError(f"cannot write {self.name}: {text}; nothing was written",
                          key=self.key)

    def failed(self, err: BaseException) -> WriteError:
        """The error for a failure while writing this output."""
        return WriteError(f"{self.name}: {reason(err)}", path=self.name, key=self.key)

    # ------------------------------------------------------------------ writing
    def open(self, mode: str = "w", **kwargs: Any) -> IO[Any]:
        """The output opened for writing (``mode`` "w" or "wb"); standard output is not
        closed by closing what this returns."""
        if self.kind == "stdout":
            stream = sys.stdout.buffer if "b" in mode else sys.stdout
            return _Unclosed(stream)  # type: ignore[return-value]
        if self.kind == "through" and stat.S_ISSOCK(os.stat(self.target).st_mode):
            return _open_socket(self.target, mode, **kwargs)
        try:
            return open(self.write_path, mode, **kwargs)
        except OSError as err:
            raise self.failed(err) from None

    def commit(self) -> None:
        """Sync the temporary file and rename it over the target (idempotent).
        :class:`WriteError` when that fails, and the target keeps what it had."""
        if self._done:
            return
        self._done = True
        if self._tmp is None:
            return
        tmp, self._tmp = self._tmp, None
        try:
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
            os.chmod(tmp, self._mode)
            if self._owner is not None:
                with contextlib.suppress(OSError):
                    os.chown(tmp, *self._owner)
            os.replace(tmp, self.target)
        except OSError as err:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise self.failed(err) from None
        _sync_directory(os.path.dirname(self.target) or ".")

    def discard(self) -> None:
        """Keep nothing: the temporary file is removed, the target keeps what it had
        (idempotent; after :meth:`commit` the file stays)."""
        self._done = True
        if self._tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(self._tmp)
            self._tmp = None

    def __del__(self) -> None:  # a forgotten output leaves no temporary file
        with contextlib.suppress(Exception):
            self.discard()


class _Unclosed:
    """A stream whose close() only flushes (standard output stays open)."""

    def __init__(self, stream: IO[Any]) -> None:
        self._stream = stream

    def close(self) -> None:
        self._stream.flush()

    def __enter__(self) -> _Unclosed:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def _open_socket(path: str, mode: str, **kwargs: Any) -> IO[Any]:
    import socket

    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.connect(path)
    except OSError as err:
        sock.close()
        raise WriteError(f"{path}: {reason(err)}", path=path) from None
    binary = sock.makefile("wb")
    sock.close()  # the file keeps the connection
    if "b" in mode:
        return binary
    import io

    return io.TextIOWrapper(binary, encoding=kwargs.get("encoding") or "utf-8",
                            newline=kwargs.get("newline"))


def _sync_directory(directory: str) -> None:
    """The rename is on disk too (where the file system lets a directory be synced)."""
    try:
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):
            os.fsync(fd)
    finally:
        os.close(fd)


def write_bytes(path: str | os.PathLike[str], data: bytes, *, key: str | None = None,
                allow_stdout: bool = False) -> None:
    """Write ``data`` to ``path`` by the module's rules, whole or not at all."""
    with Output(path, key=key, allow_stdout=allow_stdout) as out:
        _write_all(out, data, "wb")


def write_text(path: str | os.PathLike[str], text: str, *, encoding: str = "utf-8",
               newline: str | None = "\n", key: str | None = None,
               allow_stdout: bool = False) -> None:
    """Write ``text`` to ``path`` by the module's rules, whole or not at all."""
    try:
        data = text.encode(encoding)
    except UnicodeEncodeError as err:
        raise InputError(f"{os.fspath(path)}: {err.reason} in {encoding}; nothing was "
                         "written", key=key) from None
    if newline not in (None, "\n"):
        data = data.replace(b"\n", newline.encode(encoding))
    write_bytes(path, data, key=key, allow_stdout=allow_stdout)


def _write_all(out: Output, data: bytes, mode: str) -> None:
    try:
        with out.open(mode) as f:
            f.write(data)
            f.flush()
    except WriteError:
        raise
    except OSError as err:
        raise out.failed(err) from None


class Batch(_Staged):
    """Several files written all or none: each is staged in a temporary file beside its
    target, and only when every one is complete are they renamed into place.

    ::

        with Batch(key="-o") as batch:
            for name, text in trees.items():
                batch.write_text(directory / name, text)
        # here every file is in place, or (after an exception) none was touched
    """

    def __init__(self, *, key: str | None = None) -> None:
        self.key = key
        self.outputs: list[Output] = []

    def output(self, path: str | os.PathLike[str], *, suffix: str = "") -> Output:
        out = Output(path, key=self.key, suffix=suffix)
        self.outputs.append(out)
        return out

    def write_bytes(self, path: str | os.PathLike[str], data: bytes) -> None:
        _write_all(self.output(path), data, "wb")

    def write_text(self, path: str | os.PathLike[str], text: str, *,
                   encoding: str = "utf-8") -> None:
        self.write_bytes(path, text.encode(encoding))

    def commit(self) -> None:
        """Rename every staged file into place.  Files are synced before the first
        rename, so a failure there keeps every target as it was."""
        try:
            for out in self.outputs:
                if out._tmp is not None:
                    fd = os.open(out._tmp, os.O_RDONLY)
                    try:
                        os.fsync(fd)
                    finally:
                        os.close(fd)
        except OSError as err:
            self.discard()
            raise WriteError(f"{reason(err)}; nothing was written", key=self.key) from None
        for out in self.outputs:
            out.commit()

    def discard(self) -> None:
        for out in self.outputs:
            out.discard()




def prepare_directory(path: str | os.PathLike[str], *, key: str | None = None,
                      create: bool = True) -> Path:
    """A directory to write files into: created (with its parents) when ``create``;
    :class:`InputError` when it cannot be, or a non-directory is in its place."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise InputError(f"{os.fspath(p)}: is not a directory; nothing was written",
                         key=key)
    if not p.exists():
        if not create:
            raise InputError(f"{os.fspath(p)}: directory does not exist", key=key)
        try:
            p.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise InputError(f"{os.fspath(p)}: cannot create the directory: {reason(err)}; "
                             "nothing was written", key=key) from None
    return p


# ---------------------------------------------------------------------- reading
Refusal = Callable[[str], InputError]
"""Makes the error for an input that cannot be read, from the reason (without the path)."""


def _refusal(name: str, key: str | None) -> Refusal:
    return lambda text: InputError(f"{name}: {text}", key=key)


def open_input(path: str | os.PathLike[str], *, limit: int, what: str = "a file",
               key: str | None = None, error: Refusal | None = None) -> BinaryIO:
    """Input file ``path`` opened for reading: a regular file of at most ``limit`` bytes.
    A FIFO, device, socket or directory is refused without blocking on it (it is opened
    non-blocking and looked at first).  ``error`` makes the exception (default: an
    :class:`InputError` naming ``key`` and the path)."""
    name = os.fspath(path)
    refuse = error or _refusal(name, key)
    try:
        fd = os.open(name, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0)
                     | getattr(os, "O_NOCTTY", 0))
    except FileNotFoundError:
        raise refuse("no such file") from None
    except IsADirectoryError:
        raise refuse(f"is a directory, not {what}") from None
    except OSError as err:
        if err.errno == errno.ENXIO:  # a socket
            raise refuse("is a socket, not a regular file") from None
        raise refuse(f"cannot read: {reason(err)}") from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise refuse(f"is a directory, not {what}")
        if not stat.S_ISREG(st.st_mode):
            kind = ("a FIFO" if stat.S_ISFIFO(st.st_mode)
                    else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
                    else "something else")
            raise refuse(f"is {kind}, not a regular file")
        if st.st_size > limit:
            raise refuse(f"{_size(st.st_size)} is larger than {_size(limit)}, the limit "
                         f"for {what}")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_input(path: str | os.PathLike[str], *, limit: int, what: str = "a file",
               key: str | None = None, allow_stdin: bool = False,
               error: Refusal | None = None) -> bytes:
    """The bytes of input file ``path`` (see :func:`open_input`), or of standard input
    for ``-`` where ``allow_stdin``; at most ``limit`` bytes, also if it grows while it
    is read."""
    name = os.fspath(path)
    refuse = error or _refusal(name, key)
    if name == STDOUT and allow_stdin:
        data = sys.stdin.buffer.read(limit + 1)
        if len(data) > limit:
            raise refuse(f"standard input is larger than {_size(limit)}, the limit for "
                         f"{what}")
        return data
    with open_input(name, limit=limit, what=what, key=key, error=error) as f:
        try:
            data = f.read(limit + 1)
        except OSError as err:
            raise refuse(f"cannot read: {reason(err)}") from None
    if len(data) > limit:
        raise refuse(f"larger than {_size(limit)}, the limit for {what}")
    return data


def _size(n: int) -> str:
    if n >= MiB:
        return f"{n / MiB:.1f} MiB"
    if n >= 1024:
        return f"{n / 1024:.1f} KiB"
    return f"{n} bytes"


@contextlib.contextmanager
def output_stream(path: str | os.PathLike[str], mode: str = "w", *,
                  key: str | None = None, suffix: str = "", allow_stdout: bool = False,
                  **kwargs: Any) -> Iterator[IO[Any]]:
    """``with output_stream(path) as f: ...``: a stream to write by the module's rules,
    committed when the block ends without an exception, discarded otherwise."""
    with Output(path, key=key, suffix=suffix, allow_stdout=allow_stdout) as out:
        f = out.open(mode, **kwargs)
        try:
            yield f
            f.close()  # a full disk shows here at the latest: then nothing is committed
        except OSError as err:
            raise out.failed(err) from None
        finally:
            if not getattr(f, "closed", True):
                with contextlib.suppress(OSError):
                    f.close()
