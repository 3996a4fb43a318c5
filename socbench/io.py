"""Output files: atomic writes, and output paths checked before any work is done.

* :func:`atomic_write_bytes` (``_text``, ``_frame``): a reader never sees a half-written result, an interrupted run
  never leaves a corrupt file;
* :func:`output_dir`, :func:`output_file`: every command checks its ``--out``/``--json`` paths first — an existing
  file where a folder is expected, a folder where a file is expected, a path under a file, a folder it cannot write
  into — and stops with one line naming the option and the path (:class:`~socbench.errors.ConfigError`, exit 2),
  before a long study or fit runs. A write that still fails on the path (the folder made read-only meanwhile) raises
  the same kind of one-line error.
"""

from __future__ import annotations

import errno
import os
import tempfile
from pathlib import Path

from .errors import ConfigError

_WHY = {errno.EACCES: "permission denied", errno.EPERM: "not permitted", errno.EROFS: "read-only file system",
        errno.ENOSPC: "no space left on the device", errno.ENOTDIR: "a part of the path is a file, not a folder",
        errno.EEXIST: "exists and is not a folder"}


def _fail(option: str, path, why: str) -> ConfigError:
    return ConfigError(f"{option} {path}: {why}")


def _file_above(p: Path) -> Path | None:
    """The nearest existing ancestor of ``p`` when it is not a folder (a path *under a file*), else None."""
    for parent in p.parents:
        if parent.exists():
            return None if parent.is_dir() else parent
    return None


def output_dir(path, option: str = "--out") -> Path:
    """``path`` as a folder this process can write into (created if missing), or a one-line ConfigError."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise _fail(option, path, "is an existing file; expected a folder")
    above = _file_above(p)
    if above is not None:
        raise _fail(option, path, f"{above} is a file, not a folder")
    try:
        _probe(p)
    except OSError as exc:
        raise _fail(option, path, f"cannot write into this folder ({_WHY.get(exc.errno, exc.strerror)})") from None
    return p


def _probe(folder: Path) -> None:
    """Create ``folder`` if needed and write (then remove) a file in it: the only test that also holds for root,
    whom permission bits do not stop (a read-only mount does). Raises the OSError."""
    folder.mkdir(parents=True, exist_ok=True)
    fd, probe = tempfile.mkstemp(prefix=".socbench-write-test.", dir=folder)
    os.close(fd)
    os.unlink(probe)


def output_file(path, option: str = "--out") -> Path:
    """``path`` as a file this process can write (its folder created if missing), or a one-line ConfigError."""
    p = Path(path)
    if p.is_dir():
        raise _fail(option, path, "is an existing folder; expected a file name")
    if str(path).endswith(("/", os.sep)):
        raise _fail(option, path, "names a folder; expected a file name")
    above = _file_above(p)
    if above is not None:
        raise _fail(option, path, f"{above} is a file, not a folder")
    try:
        _probe(p.parent)
    except OSError as exc:
        why = _WHY.get(exc.errno, exc.strerror)
        raise _fail(option, path, f"cannot write into its folder {p.parent} ({why})") from None
    return p


def _umask() -> int:
    mask = os.umask(0)  # reading the umask sets it: set it back at once (done once, at import, before any thread)
    os.umask(mask)
    return mask


#: the mode a plain ``open`` gives a new file under the process' umask: ``mkstemp`` makes its files 0600, results
#: other users of a shared machine could not read
FILE_MODE = 0o666 & ~_umask()


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and ``os.replace``; the file gets the
    mode a plain write would give it (:data:`FILE_MODE`)."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:  # the path is not writable: the user's to fix, one line
        raise ConfigError(f"cannot write {path}: {_WHY.get(exc.errno, exc.strerror)}") from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fchmod(fh.fileno(), FILE_MODE)
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(exc, IsADirectoryError):  # a folder of the file's name in the way: the user's to fix
            raise ConfigError(f"cannot write {path}: a folder of that name is in the way") from None
        if isinstance(exc, OSError) and exc.errno in _WHY:
            raise ConfigError(f"cannot write {path}: {_WHY[exc.errno]}") from None
        raise


def atomic_write_text(path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_frame(path, frame, **to_csv_kwargs) -> None:
    """Write a pandas DataFrame as CSV atomically."""
    atomic_write_text(path, frame.to_csv(index=False, **to_csv_kwargs))
