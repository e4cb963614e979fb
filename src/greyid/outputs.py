"""Files written so that a killed process loses nothing.

* :func:`write_atomic` writes one file: to a temporary file in the same folder,
  flushed to disk, then renamed over the target (a rename within a folder is
  atomic), so a reader sees the old file or the new one, never a part.
* :func:`write_generation` writes a run's files into a folder as one
  generation: every file is written under a temporary name first, then a
  journal naming them is written (atomically), then each is renamed into place
  and the journal removed.  A process killed before the journal leaves the
  previous generation untouched (its temporary files are removed next time); one
  killed after it leaves a journal that :func:`complete_generation` — called by
  every reader and writer of the folder — carries out.  So a folder never shows
  files of two runs side by side.
"""

from __future__ import annotations

import json
import os
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


def write_generation(folder, files: dict) -> None:
    """Write ``files`` (name → text or bytes) into ``folder`` as one generation (see the module doc)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    complete_generation(folder)
    tag = uuid.uuid4().hex[:12]
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
