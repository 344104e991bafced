"""Atomic file writes: a file of ours is either the previous version or the new one, never
half of either.

Every writer goes through :func:`atomic_write`: the content is written to a temporary file in
the target's directory (same file system, so the rename is atomic), flushed and ``fsync``-ed,
then ``os.replace``-d over the target, and the directory entry is ``fsync``-ed too. If
anything fails before the rename (disk full, an exception in the writer, Ctrl-C), the
temporary file is removed and the previous file is untouched. The final file gets the
permissions a plain ``open(path, "w")`` would give it (``0o666 & ~umask``), or keeps the
permissions of the file it replaces.

    >>> import numpy as np
    >>> from dolfinx_lopinf.core.io_atomic import atomic_savez
    >>> path = atomic_savez("/tmp/example", K=np.eye(2))   # writes /tmp/example.npz
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
import zipfile
import zlib
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import FileFormatError

__all__ = ["atomic_write", "atomic_savez", "atomic_savez_compressed", "atomic_write_text",
           "atomic_write_bytes", "npz_path", "open_npz"]


def npz_path(path) -> Path:
    """The path ``np.savez(path, ...)`` writes: ``path`` with ``.npz`` appended unless it
    already ends in ``.npz``."""
    path = Path(path)
    return path if path.suffix == ".npz" else path.with_name(path.name + ".npz")


def _umask() -> int:
    try:  # Linux: read it without changing it (thread-safe)
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # e.g. Windows: directories cannot be opened; the rename is still atomic
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write(path, write: Callable, *, binary: bool = True) -> Path:
    """Write ``path`` atomically: ``write(f)`` fills an open temporary file ``f`` in the same
    directory, which then replaces ``path`` (flush, fsync, ``os.replace``, fsync of the
    directory). On any exception (including ``KeyboardInterrupt``) the temporary file is
    deleted, ``path`` is left as it was and the exception propagates.

    Args:
        path: the final file name (its directory must exist).
        write: callable taking the open file object.
        binary: open the temporary file in binary (default) or text mode (UTF-8).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.
    """
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise FileNotFoundError(2, f"cannot write {path}: directory {directory} does not exist "
                                   "(create it first)", str(directory))
    try:
        mode = os.stat(path).st_mode & 0o7777
    except OSError:
        mode = 0o666 & ~_umask()
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with (os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", encoding="utf-8")) as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    _fsync_dir(directory)
    return path


def atomic_savez(path, **arrays) -> Path:
    """``np.savez(path, **arrays)``, atomically. Returns the path actually written (``.npz``
    appended unless already there)."""
    return atomic_write(npz_path(path), lambda f: np.savez(f, **arrays))


def atomic_savez_compressed(path, **arrays) -> Path:
    """``np.savez_compressed(path, **arrays)``, atomically; returns the path written."""
    return atomic_write(npz_path(path), lambda f: np.savez_compressed(f, **arrays))


def atomic_write_bytes(path, data: bytes) -> Path:
    """``Path(path).write_bytes(data)``, atomically."""
    return atomic_write(path, lambda f: f.write(data))


def atomic_write_text(path, text: str) -> Path:
    """``Path(path).write_text(text)`` (UTF-8), atomically; e.g. for JSON metrics."""
    return atomic_write(path, lambda f: f.write(text), binary=False)


_READ_ERRORS = (zipfile.BadZipFile, EOFError, ValueError, OSError, zlib.error, KeyError)


@contextlib.contextmanager
def open_npz(path, what: str):
    """Open an ``.npz`` of ours for reading, with errors that name the file and the problem.

    Yields ``(data, read)``: the ``np.lib.npyio.NpzFile`` (for ``data.files``) and
    ``read(name)``, which returns one entry and turns a truncated or corrupt member into a
    :class:`~dolfinx_lopinf.errors.FileFormatError`. Pickled objects are never loaded.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        FileFormatError: ``path`` is a directory, a text file, a single ``.npy`` array, or a
            truncated/corrupt archive; ``what`` (e.g. ``"ROM (save_rom)"``) says what was
            expected.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(errno.ENOENT, f"no such {what} file", str(path))
    if path.is_dir():
        raise FileFormatError(f"{path}: is a directory, not a {what} file")
    with open(path, "rb") as f:
        magic = f.read(6)
    if magic.startswith(b"\x93NUMPY"):
        raise FileFormatError(f"{path}: is a single .npy array (np.save), not an .npz archive; "
                              f"expected a {what} file")
    if not magic.startswith(b"PK"):
        head = "it is empty" if not magic else f"it starts with {magic!r}"
        raise FileFormatError(f"{path}: is not an .npz archive ({head}); expected a {what} file")
    try:
        data = np.load(path, allow_pickle=False)
    except _READ_ERRORS as exc:
        raise FileFormatError(f"{path}: truncated or corrupt .npz ({type(exc).__name__}: {exc}); "
                              f"write the {what} file again") from exc

    def read(name):
        try:
            return data[name]
        except ValueError as exc:
            if "allow_pickle" in str(exc):
                raise FileFormatError(f"{path}: entry {name!r} holds pickled Python objects, "
                                      "which are not loaded (they could run code); not a "
                                      f"{what} file") from exc
            raise FileFormatError(f"{path}: entry {name!r} is truncated or corrupt ({exc}); "
                                  f"write the {what} file again") from exc
        except _READ_ERRORS as exc:
            raise FileFormatError(f"{path}: entry {name!r} is truncated or corrupt "
                                  f"({type(exc).__name__}: {exc}); write the {what} file "
                                  "again") from exc

    with data:
        yield data, read


def plain(obj):
    """``obj`` with numpy values made plain Python (dict keys as str, arrays and tuples as lists,
    numpy scalars as bool/int/float, a time-integration scheme as its spec text), ready for
    ``json.dumps``. Non-finite floats stay floats (``json`` writes them as NaN/Infinity,
    which Python reads back)."""
    if isinstance(obj, dict):
        return {str(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    spec = getattr(obj, "spec", None)  # a dolfinx_lopinf.core.schemes.Scheme
    if isinstance(spec, str):
        return spec
    return obj
