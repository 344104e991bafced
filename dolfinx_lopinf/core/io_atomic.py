"""Atomic file writes: a file of ours is either the previous version or the new one, never
half of either.

Every writer goes through :func:`atomic_write`: the content is written to a temporary file in
the target's directory (same file system, so the rename is atomic), flushed and ``fsync``-ed,
then ``os.replace``-d over the target, and the directory entry is ``fsync``-ed too. If
anything fails before the rename (disk full, an exception in the writer, Ctrl-C), the
temporary file is removed and the previous file is untouched. The final file gets the
permissions a plain ``open(path, "w")`` would give it (``0o666 & ~umask``), or keeps the
permissions of the file it replaces.

A process killed while writing (SIGKILL, power loss) cannot remove its temporary file. Each
temporary is therefore named after its target and its owner, ``.<target>.<host>-<pid>.<random>
.tmp``, and the next write of the same target removes the temporaries of that target whose
owner is gone (same host, no such process; :func:`stale_temporaries`). Temporaries without an
owner tag (written by an older version) are removed once they are an hour old.

Folders (a VTX ``.bp``) are replaced by :func:`swap_folder`: on Linux one
``renameat2(RENAME_EXCHANGE)`` exchanges the new folder with the old one atomically, so the
target is the old or the new version at every instant; where the file system cannot exchange,
the old version is first renamed to ``.<target>.previous`` beside it, and
:func:`recover_folder` (called before every replacement) puts it back if a kill came between
the two renames.

    >>> import numpy as np
    >>> from dolfinx_lopinf.core.io_atomic import atomic_savez
    >>> path = atomic_savez("/tmp/example", K=np.eye(2))   # writes /tmp/example.npz
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import re
import shutil
import socket
import tempfile
import time
import zipfile
import zlib
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import FileFormatError

__all__ = ["atomic_write", "atomic_savez", "atomic_savez_compressed", "atomic_write_text",
           "atomic_write_bytes", "npz_path", "open_npz", "stale_temporaries", "temporary_prefix",
           "swap_folder", "recover_folder"]

#: untagged temporaries (from a version without owner tags) older than this are stale (s)
LEGACY_TEMPORARY_AGE = 3600.0


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname())[:40] or "host"


def temporary_prefix(name: str) -> str:
    """The prefix of this process's temporaries for the target ``name``:
    ``.<name>.<host>-<pid>.`` (a random part and ``.tmp`` follow)."""
    return f".{name}.{_host()}-{os.getpid()}."


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # it exists (another user's), or we cannot tell: keep its files
    return True


def stale_temporaries(directory, name: str) -> list[Path]:
    """Temporaries of the target ``name`` in ``directory`` left by writers that are gone: owner
    tag of this host and no such process, or no owner tag and older than
    :data:`LEGACY_TEMPORARY_AGE`. Files and folders. (Another host's temporaries are left
    alone: whether their writer lives cannot be told from here.)"""
    directory = Path(directory)
    tagged = re.compile(rf"^\.{re.escape(name)}\.(?P<host>[A-Za-z0-9_-]+)-(?P<pid>\d+)\.[^.]+\.tmp$")
    legacy = re.compile(rf"^\.{re.escape(name)}\.[A-Za-z0-9_]{{6,12}}\.tmp$")
    try:
        entries = os.listdir(directory)
    except OSError:
        return []
    host, now, out = _host(), time.time(), []
    for entry in entries:
        m = tagged.match(entry)
        if m is not None:
            if m["host"] == host and not _alive(int(m["pid"])):
                out.append(directory / entry)
        elif legacy.match(entry):
            try:
                if now - os.lstat(directory / entry).st_mtime > LEGACY_TEMPORARY_AGE:
                    out.append(directory / entry)
            except OSError:
                pass
    return out


def remove_stale_temporaries(directory, name: str) -> int:
    """Delete :func:`stale_temporaries`; returns the bytes freed (best effort, never raises)."""
    freed = 0
    for path in stale_temporaries(directory, name):
        try:
            if path.is_dir() and not path.is_symlink():
                freed += sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
                shutil.rmtree(path, ignore_errors=True)
            else:
                freed += path.stat().st_size
                path.unlink()
        except OSError:
            pass
    return freed


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
    remove_stale_temporaries(directory, path.name)  # of writes of this target that were killed
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=temporary_prefix(path.name), suffix=".tmp")
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


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Exchange the paths a and b atomically (Linux renameat2 RENAME_EXCHANGE). False when the
    system or file system cannot (then nothing changed); OSError on any other failure."""
    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    renameat2.restype = ctypes.c_int
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EPERM):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _previous(target: Path) -> Path:
    return target.parent / f".{target.name}.previous"


def recover_folder(target) -> str | None:
    """Finish a :func:`swap_folder` that was killed: the previous version parked at
    ``.<target>.previous`` goes back to ``target`` when ``target`` is missing, and is deleted
    when ``target`` (the new version, complete) exists. Returns what was done, or None."""
    target = Path(target)
    previous = _previous(target)
    if not previous.exists():
        return None
    if target.exists():
        shutil.rmtree(previous, ignore_errors=True)
        return f"removed {previous}, left by an interrupted replacement of {target}"
    os.replace(previous, target)
    return f"restored {target} from {previous}, left by an interrupted replacement"


def swap_folder(new, target) -> None:
    """Put the complete folder ``new`` at ``target`` (same file system). An existing
    ``target`` is exchanged with ``new`` atomically where the system can (``new`` then holds
    the old version, for the caller to delete); elsewhere it is parked at
    ``.<target>.previous`` first, restored if the second rename fails, and deleted after -
    recoverable by :func:`recover_folder` at every instant."""
    new, target = Path(new), Path(target)
    if not target.exists():
        os.replace(new, target)
    elif not _exchange(new, target):
        previous = _previous(target)
        os.replace(target, previous)
        try:
            os.replace(new, target)
        except BaseException:
            os.replace(previous, target)
            raise
        shutil.rmtree(previous, ignore_errors=True)
    _fsync_dir(target.parent)


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
