"""Atomic file writes: every file RetinexGS writes goes through :func:`atomic_write`.

A temporary file in the destination folder is written, flushed, fsynced and renamed over the target, so a
reader (or a resumed run after a crash or SIGKILL) sees the old file or the new one, never half of one.
"""
from __future__ import annotations

import errno
import hashlib
import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable, Iterable, List, Optional, Sequence, Tuple, Union

from retinexgs.errors import UserError

TMP_PREFIX = ".tmp-"
_NO_SPACE_ERRNOS = {errno.ENOSPC, errno.EDQUOT}
# torch.save into a file that stops taking bytes fails in its zip writer with these (not an OSError).
_TORCH_WRITE_FAILED = ("unexpected pos", "file write failed", "PytorchStreamWriter failed")
_OTHER_CAUSE = {errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOENT, errno.EEXIST, errno.EISDIR, errno.ENOTDIR,
                errno.ENAMETOOLONG}
_NEARLY_FULL = 16 << 20  # bytes: an unexplained write failure with less than this free is taken as a full disk


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def default_file_mode() -> int:
    """The permissions a plain ``open(path, "w")`` gives a new file: 0666 minus the umask. Every output gets them
    (``mkstemp``'s temporaries alone would be 0600, readable by their owner only)."""
    return 0o666 & ~_umask()


def nearest_existing(path: Path) -> Path:
    """``path`` itself, or its nearest parent that exists."""
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_writable_folder(path: Path, flag: str = "--out") -> None:
    """Refuse a folder path that is a file, lies under a file, or cannot be written (checked by creating and
    removing a temporary file in it, or in its nearest existing parent)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UserError(f"{flag} {path} is a file; a folder is needed here (choose another {flag})")
    existing = nearest_existing(path.absolute())
    if not existing.is_dir():
        raise UserError(f"{flag} {path} lies under {existing}, which is a file, not a folder (choose another {flag})")
    reason = write_probe(existing)
    if reason:
        raise UserError(f"{flag} {path}: cannot write in {existing} ({reason}); choose another "
                        f"{flag} or fix the folder's permissions")


def check_writable_file(path: Path, flag: str = "--out") -> None:
    """Refuse a file path whose folder (or nearest existing folder above it) is a file or cannot be written."""
    folder = nearest_existing(Path(path).absolute().parent)
    if not folder.is_dir():
        raise UserError(f"{flag} {path}: {folder} is a file, not a folder; choose another {flag}")
    reason = write_probe(folder)
    if reason:
        raise UserError(f"{flag} {path}: cannot write in {folder} ({reason}); choose another {flag}")


def write_probe(folder: Path) -> str:
    """'' when a file can be created (and is at once removed) in ``folder``, else the reason. A real write:
    os.access says yes to root on a read-only mount or for a chmod 555 folder."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=TMP_PREFIX, dir=folder)
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        return str(exc.strerror or exc)
    return ""


def free_bytes(folder: Union[str, Path]) -> Optional[int]:
    """Bytes available to this user on the file system holding ``folder`` (or its nearest existing parent);
    None when that cannot be asked."""
    p = Path(folder)
    while not p.exists() and p.parent != p:
        p = p.parent
    try:
        st = os.statvfs(p)
    except (OSError, AttributeError):  # AttributeError: no statvfs (Windows)
        return None
    return st.f_bavail * st.f_frsize


def is_out_of_space(exc: BaseException, folder: Union[str, Path]) -> bool:
    """True when ``exc``, raised while writing into ``folder``, means the disk (or the quota) is full: an
    OSError ENOSPC/EDQUOT (also found in its cause or context), torch's zip-writer failure (``unexpected pos``,
    ``file write failed``), or any write error while ``folder``'s disk is nearly full (ffmpeg, a broken pipe)."""
    seen = 0
    e: Optional[BaseException] = exc
    while e is not None and seen < 5:
        if isinstance(e, OSError) and e.errno in _NO_SPACE_ERRNOS:
            return True
        if isinstance(e, RuntimeError) and any(m in str(e) for m in _TORCH_WRITE_FAILED):
            return True
        if "No space left on device" in str(e):
            return True
        e, seen = e.__cause__ or e.__context__, seen + 1
    if isinstance(exc, OSError) and exc.errno in _OTHER_CAUSE:
        return False  # a read-only mount also reports no free space: it is not "full"
    if isinstance(exc, (OSError, RuntimeError)):
        free = free_bytes(folder)
        return free is not None and free < _NEARLY_FULL
    return False


def out_of_space_error(path: Union[str, Path], elsewhere: str = "--out") -> UserError:
    """The error for a write of ``path`` that failed because its disk is full. ``elsewhere``: how the
    caller's command moves this output to another disk (e.g. ``--out``, ``--set data.cache_dir=DIR``)."""
    free = free_bytes(Path(path).parent)
    mib = free / 2**20 if free is not None else 0.0
    room = f" ({mib:.{1 if mib < 10 else 0}f} MiB free on that disk)" if free is not None else ""
    where = f" with {elsewhere}" if elsewhere else ""
    return UserError(f"no space left on device writing {path}{room}: free some space or write elsewhere{where}")


def make_folders(folder: Union[str, Path]) -> List[Path]:
    """Create ``folder`` and its missing parents; returns the folders this call made, deepest first, for
    :func:`remove_empty_folders` when what was to go into them could not be written."""
    folder = Path(folder)
    made: List[Path] = []
    p = folder
    while not (p.exists() or p.is_symlink()) and p != p.parent:
        made.append(p)
        p = p.parent
    folder.mkdir(parents=True, exist_ok=True)
    return made


def remove_empty_folders(made: Sequence[Path]) -> None:
    """Remove the folders of ``made`` (deepest first, as :func:`make_folders` lists them) while they are empty: a
    folder that holds anything stays, and so do the ones above it. Only what a failed write made itself is passed
    here, so a full disk leaves no empty folders behind and never touches the user's."""
    for p in made:
        try:
            os.rmdir(p)
        except FileNotFoundError:
            continue
        except OSError:  # not empty (another writer's file), or not ours to remove
            return


def missing_folders(paths: Iterable[Union[str, Path]]) -> List[Path]:
    """For each path that does not exist: its outermost missing folder (itself, or the first parent that
    ``mkdir(parents=True)`` would make), as an absolute path. Taken before a command runs: what a failed command
    created there is its own (:func:`remove_empty_trees`)."""
    found: List[Path] = []
    for path in paths:
        p, top = Path(path).absolute(), None
        while not (p.exists() or p.is_symlink()) and p != p.parent:
            top, p = p, p.parent
        if top is not None and top not in found:
            found.append(top)
    return found


def remove_empty_trees(roots: Iterable[Path]) -> List[Path]:
    """Remove each folder of ``roots`` and the folders below it that hold nothing else (deepest first; a folder
    with a file, a link or a non-empty folder in it stays, and so do its parents). Returns the folders removed."""
    removed: List[Path] = []
    for root in roots:
        root = Path(root)
        if root.is_symlink() or not root.is_dir():
            continue
        for folder, _, _ in os.walk(root, topdown=False):  # links are not followed: a link keeps its folder
            try:
                os.rmdir(folder)
            except OSError:
                continue
            removed.append(Path(folder))
    return removed


def temporary_file(folder: Path, prefix: str, suffix: str = "") -> Tuple[int, str, List[Path]]:
    """``mkstemp`` in ``folder``, made first when missing: (fd, name, the folders made, see :func:`make_folders`).
    Another writer's failed call may remove the empty folder between the two steps: it is then made once more."""
    made: List[Path] = []
    for attempt in (0, 1):
        try:
            made = make_folders(folder) + made
            fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=folder)
            return fd, tmp, made
        except FileNotFoundError:
            if attempt:
                remove_empty_folders(made)
                raise
        except BaseException:
            remove_empty_folders(made)
            raise
    raise AssertionError("unreachable")


def atomic_write(path: Union[str, Path], write: Callable[[BinaryIO], None], elsewhere: str = "--out") -> Path:
    """Call ``write(f)`` on a binary temporary file next to ``path`` and rename it to ``path`` when done.

    The folder is created if needed; the file gets the usual permissions (0666 minus the umask, where
    ``mkstemp`` alone would leave 0600); on any error the temporary file is removed, ``path`` untouched, and the
    folders this call made are removed again while empty. A full disk (see :func:`is_out_of_space`) raises a
    :class:`UserError` naming ``path``, the free space and ``elsewhere`` (the caller's option for writing to
    another disk).
    """
    path = Path(path)
    try:
        fd, tmp, made = temporary_file(path.parent, TMP_PREFIX, path.suffix)
    except OSError as exc:
        if is_out_of_space(exc, path.parent):
            raise out_of_space_error(path, elsewhere) from None
        raise
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, default_file_mode())
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        remove_empty_folders(made)
        if isinstance(exc, Exception) and not isinstance(exc, UserError) and is_out_of_space(exc, path.parent):
            raise out_of_space_error(path, elsewhere) from None
        raise
    return path


def atomic_write_text(path: Union[str, Path], text: str, elsewhere: str = "--out") -> Path:
    """Write ``text`` (UTF-8) atomically to ``path``."""
    return atomic_write(path, lambda f: f.write(text.encode("utf-8")), elsewhere)


def content_digest(path: Union[str, Path], length: int = 16) -> str:
    """The first ``length`` hex digits of the SHA-256 of the file's bytes: what every cache is keyed by (a copy
    with an old mtime, or another scene's photo of the same name, never matches a stale entry)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()[:length]
