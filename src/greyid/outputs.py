"""Files written so that a killed process loses nothing.

* [`write_atomic()`][greyid.outputs.write_atomic] writes one file: to a temporary file in the same folder,
  flushed to disk, then renamed over the target (a rename within a folder is
  atomic), so a reader sees the old file or the new one, never a part.
* [`write_generation()`][greyid.outputs.write_generation] writes a run's files into a folder as one
  generation.  On Linux the files are written into a new sibling folder, with
  any other files of the old folder linked into it, and the two folders are
  exchanged in one step (``renameat2`` with ``RENAME_EXCHANGE``): at every moment
  the folder's path holds the previous run's files or the new run's, as any
  program that opens it sees them.  Where the exchange is not available (another
  system, a file system without it) every file is written under a temporary name
  first, then a journal naming them is written (atomically), then each is
  renamed into place and the journal removed; a run killed after the journal
  leaves it for [`complete_generation()`][greyid.outputs.complete_generation], which every reader and writer of the
  folder calls.  Leftovers of a killed run are removed by the next write.

The generation an exchange retires stays beside the folder, hidden, until the
next write has exchanged its own: a program that opened the folder just before
an exchange reads the whole previous generation, not files removed under it.
"""

from __future__ import annotations

import ctypes
import errno
import json
import os
import shutil
import sys
import tempfile
import uuid
from pathlib import Path

#: The journal of a generation being moved into place.
JOURNAL = ".greyid-generation.json"
#: Temporary files of a generation carry this in their names.
PARTIAL = ".greyid-partial"


def _sync_folder(folder: Path) -> None:
    try:
        handle = os.open(folder, os.O_RDONLY)
    except OSError:  # not supported everywhere (Windows): the renames are still atomic
        return
    try:
        os.fsync(handle)
    except OSError:
        pass
    finally:
        os.close(handle)


def _write_new(path: Path, blob: bytes) -> None:
    with open(path, "xb") as out:
        out.write(blob)
        out.flush()
        os.fsync(out.fileno())


def _as_bytes(content) -> bytes:
    return content.encode("utf-8") if isinstance(content, str) else bytes(content)


def write_atomic(path, content) -> None:
    """Write ``content`` (text as UTF-8, or bytes) to ``path`` atomically (see the module doc)."""
    path = Path(path)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=PARTIAL)
    os.close(handle)
    temporary = Path(temporary)
    try:
        temporary.unlink()
        _write_new(temporary, _as_bytes(content))
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    _sync_folder(path.parent)


def complete_generation(folder) -> None:
    """Finish moving a generation into ``folder`` that a killed process left half done, and remove
    the temporary files of one killed before its journal was written."""
    folder = Path(folder)
    journal = folder / JOURNAL
    if journal.is_file():
        try:
            moves = json.loads(journal.read_text(encoding="utf-8"))
        except (OSError, ValueError):  # written atomically: unreadable means not ours to trust
            moves = {}
        for name, temporary in moves.items():
            source = folder / temporary
            if source.is_file() and "/" not in name and "/" not in temporary:
                os.replace(source, folder / name)
        journal.unlink(missing_ok=True)
        _sync_folder(folder)
    if folder.is_dir():
        for leftover in folder.glob(f".*{PARTIAL}"):
            leftover.unlink(missing_ok=True)


def _exchange(first: Path, second: Path) -> bool:
    """Swap two folders in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where the system or
    the file system cannot."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):  # a C library without renameat2 (glibc before 2.28, musl)
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    renameat2.restype = ctypes.c_int
    here, exchange = -100, 2  # AT_FDCWD, RENAME_EXCHANGE
    if renameat2(here, os.fsencode(first), here, os.fsencode(second), exchange) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOTSUP):
        return False
    raise OSError(code, os.strerror(code), str(second))


def _carry_over(old: Path, new: Path, names) -> None:
    """Link (or copy) into ``new`` what ``old`` holds besides this generation's files: a user's
    own files in the output folder are kept, not dropped."""
    for entry in old.iterdir():
        if entry.name in names or entry.name == JOURNAL or entry.name.endswith(PARTIAL):
            continue
        target = new / entry.name
        if entry.is_symlink():
            os.symlink(os.readlink(entry), target)
        elif entry.is_dir():
            shutil.copytree(entry, target, symlinks=True, copy_function=_link_or_copy)
        else:
            _link_or_copy(entry, target)


def _link_or_copy(source, target) -> None:
    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)


def _sibling(folder: Path, kind: str, tag: str) -> Path:
    return folder.parent / f".{folder.name}.{tag}.{kind}{PARTIAL}"


def _remove_leftovers(folder: Path, kinds: str = "*", keep: Path | None = None) -> None:
    """Remove the sibling folders of ``kinds`` ("new": a run killed before its exchange, "retired": a
    previous generation), all but ``keep``."""
    if folder.parent.is_dir():
        for leftover in folder.parent.glob(f".{folder.name}.*.{kinds}{PARTIAL}"):
            if leftover.is_dir() and not leftover.is_symlink() and leftover != keep:
                shutil.rmtree(leftover, ignore_errors=True)


def write_generation(folder, files: dict) -> None:
    """Write ``files`` (name → text or bytes) into ``folder`` as one generation (see the module doc)."""
    folder = Path(folder)
    if folder.is_symlink():  # a link to the user's output folder: the folder itself is replaced, not the link
        folder = folder.resolve()
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(f"'{folder}' is a file, not a folder for the generation's files")
    folder.parent.mkdir(parents=True, exist_ok=True)
    _remove_leftovers(folder, kinds="new")  # the retired generation may still be read: it goes after the exchange
    if folder.is_dir():
        complete_generation(folder)
    tag = uuid.uuid4().hex[:12]
    new = _sibling(folder, "new", tag)
    new.mkdir()
    try:
        for name, content in files.items():
            _write_new(new / name, _as_bytes(content))
        if folder.is_dir():
            _carry_over(folder, new, files)
        _sync_folder(new)
        if not folder.exists():
            os.rename(new, folder)
            _sync_folder(folder.parent)
            return
        if _exchange(new, folder):
            # The previous generation, now under the new one's name, is kept for a reader that opened
            # it before the exchange; the one before it goes.
            retired = _sibling(folder, "retired", tag)
            os.rename(new, retired)
            _sync_folder(folder.parent)
            _remove_leftovers(folder, keep=retired)
            return
    except BaseException:
        shutil.rmtree(new, ignore_errors=True)
        raise
    shutil.rmtree(new, ignore_errors=True)
    _write_by_journal(folder, files, tag)
    _remove_leftovers(folder)


def _write_by_journal(folder: Path, files: dict, tag: str) -> None:
    """The generation renamed file by file behind a journal, where folders cannot be exchanged."""
    moves = {}
    try:
        for name, content in files.items():
            temporary = f".{name}.{tag}{PARTIAL}"
            _write_new(folder / temporary, _as_bytes(content))
            moves[name] = temporary
        write_atomic(folder / JOURNAL, json.dumps(moves))
    except BaseException:
        for temporary in moves.values():
            (folder / temporary).unlink(missing_ok=True)
        raise
    complete_generation(folder)


__all__ = ["write_atomic", "write_generation", "complete_generation"]
