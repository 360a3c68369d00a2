"""Writing an output so that it is the previous file or the whole new one, never half of either.

Every file calstation writes for its user — exports, imported recordings, point clouds,
calibration files, reports, the run folder's report and calibration — goes through
:func:`atomic_output` (or :func:`write_atomic` for bytes and text in memory):

1. the target is checked first: a folder, a device (``/dev/null``), a FIFO or a socket named as
   the output is refused, and so is a target whose folder does not exist (unless the caller
   makes it), before anything is written;
2. the new content goes to a temporary file beside the target (same folder, so the same file
   system), which is flushed to the disk (``fsync``);
3. only then is it renamed over the target, and the folder is flushed so that the rename
   survives a power cut.

On any failure — a full disk, a refused permission, Ctrl-C, the caller's own exception — the
temporary file is removed and the target is exactly as it was. An :class:`OSError` becomes an
:class:`~calstation.errors.OutputError` of one sentence naming the file.

Where the new content must wait for something else before it replaces the target (a run's
report waits for its database commit), :func:`stage` writes the temporary file and
:func:`commit` puts it in place later.
"""

from __future__ import annotations

import os
import secrets
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from calstation.errors import OutputError

__all__ = ["atomic_output", "check_output", "commit", "stage", "write_atomic"]


def _kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISDIR, "folder"),
        (stat.S_ISCHR, "character device"),
        (stat.S_ISBLK, "block device"),
        (stat.S_ISFIFO, "named pipe (FIFO)"),
        (stat.S_ISSOCK, "socket"),
    ):
        if test(mode):
            return name
    return "special file"


def check_output(path: str | Path, what: str = "output", *, make_parents: bool = False) -> Path:
    """The file to write for the output ``path``: ``path`` itself, or the file a symbolic link
    there points to. :class:`OutputError` when it names a folder, a device, a FIFO or a socket,
    or when its folder does not exist (created instead with ``make_parents``). ``what`` names
    the output in messages ("export", "PLY file")."""
    p = Path(path).expanduser()
    if p.is_symlink():
        p = p.resolve()
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        mode = None
    except OSError as exc:
        raise OutputError(f"cannot write the {what} {p}: {exc.strerror or exc}") from None
    if mode is not None and not stat.S_ISREG(mode):
        kind = _kind(mode)
        raise OutputError(
            f"the {what} {p} is a {kind}: calstation writes its outputs to regular files only "
            f"and never replaces a {kind}; name a file"
        )
    folder = p.parent
    if make_parents:
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(
                f"cannot create the folder {folder} for the {what} {p}: {exc.strerror or exc}"
            ) from None
    elif not folder.is_dir():
        what_is = "is not a folder" if folder.exists() else "does not exist"
        raise OutputError(f"cannot write the {what} {p}: the folder {folder} {what_is}")
    return p


def _temporary(target: Path) -> tuple[Path, int]:
    """A new file beside ``target`` (open for writing; mode as ``target``'s, else as a new file
    of this process would get) and its descriptor."""
    for _ in range(100):
        tmp = target.with_name(f".{target.name}.{secrets.token_hex(4)}.tmp")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0),
                         0o666)
        except FileExistsError:
            continue
        try:
            os.chmod(tmp, stat.S_IMODE(os.stat(target).st_mode))
        except FileNotFoundError:
            pass  # a new file: the umask decided its mode
        except OSError:
            os.close(fd)
            tmp.unlink(missing_ok=True)
            raise
        return tmp, fd
    raise FileExistsError(f"no free temporary name beside {target}")


def _fsync_folder(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return  # a file system without folder descriptors: the rename is all it offers
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _failed(target: Path, what: str, exc: OSError) -> OutputError:
    reason = exc.strerror or str(exc)
    return OutputError(
        f"cannot write the {what} {target}: {reason}; "
        + (f"{target} is as it was" if target.exists() else "nothing was written")
    )


def stage(path: str | Path, data: bytes | str, what: str = "output", *,
          make_parents: bool = False) -> Path:
    """Write ``data`` (text as UTF-8) to a temporary file beside the output ``path``, flushed to
    the disk, and return the temporary file's path, for :func:`commit` to put in place. The
    target is checked as :func:`check_output` does; on failure nothing is left behind."""
    target = check_output(path, what, make_parents=make_parents)
    payload = data.encode("utf-8") if isinstance(data, str) else data
    tmp: Path | None = None
    try:
        tmp, fd = _temporary(target)
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
    except BaseException as exc:
        if tmp is not None:
            tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise _failed(target, what, exc) from None
        raise
    return tmp


def commit(tmp: str | Path, path: str | Path, what: str = "output") -> None:
    """Put the staged file ``tmp`` (from :func:`stage`, or written and flushed by
    :func:`atomic_output`) in place of ``path``, and flush the folder. The target is checked
    again first (it may have changed since it was staged): a folder, device, FIFO or socket
    there is refused and ``tmp`` removed."""
    target = Path(path)
    try:
        target = check_output(target, what)
        os.replace(tmp, target)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise _failed(target, what, exc) from None
        raise
    _fsync_folder(target.parent)


@contextmanager
def atomic_output(path: str | Path, what: str = "output", *,
                  make_parents: bool = False) -> Iterator[Path]:
    """Write the output ``path`` whole or not at all: yields a temporary path beside it for the
    caller to write (and close); when the block ends without an exception the file is flushed to
    the disk and renamed over ``path``. On any exception the temporary file is removed, ``path``
    is left as it was, and an :class:`OSError` is raised again as
    :class:`~calstation.errors.OutputError` naming ``path``. ``what`` names the output in
    messages; ``make_parents`` creates a missing folder instead of refusing."""
    target = check_output(path, what, make_parents=make_parents)
    try:
        tmp, fd = _temporary(target)
    except OSError as exc:
        raise _failed(target, what, exc) from None
    os.close(fd)
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise _failed(target, what, exc) from exc
        raise
    commit(tmp, target, what)


def write_atomic(path: str | Path, data: bytes | str, what: str = "output", *,
                 make_parents: bool = False) -> Path:
    """Write ``data`` (text as UTF-8) to the output ``path`` whole or not at all (see
    :func:`atomic_output`); the path written."""
    target = check_output(path, what, make_parents=make_parents)
    commit(stage(target, data, what), target, what)
    return target
