"""Traced programs kept on disk, so that a later process need not trace them again.

Tracing greyid's estimation programs (a filter's scan differentiated twice,
vectorised over directions) takes most of a first fit's time once XLA's own
compilation comes from JAX's persistent cache.  A program given a key is exported
with ``jax.export`` into ``$GREYID_CACHE_DIR/programs``, its arguments' and
results' tree structures with it (greyid's named tuples registered for that by
name), and a later process with the same key loads it instead of tracing.  On by
default; ``GREYID_PROGRAMS=off`` (or ``GREYID_CACHE_DIR=off``) switches it off.

A kept program must be the one tracing would give, or answers would be silently
wrong: its file name is a hash of the key (the model's equations and every setting
the program closes over, see
[`greyid.model.structure.Structure.fingerprint`][greyid.model.structure.Structure.fingerprint]), the
arguments' shapes and types, greyid's code (its compiled modules without line numbers
and functions' docstrings, so that a change to comments, layout or functions' docstrings alone keeps the
programs) and JAX's version and backend.
A process that replaces greyid's functions or constants at run time must switch the
store off: the key does not see such changes (the test suite does so for each test
that replaces one).  A program
that cannot be exported, or a file that cannot be read or written, is traced, as
without the store.

A file is JAX's serialized program (a flatbuffer of StableHLO and the trees;
nothing in it is executable Python) followed by its SHA-256, so that a damaged or
edited file is found before JAX reads it: it is removed and the program exported
again.  ``greyid cache info`` and ``greyid cache clear`` show and empty the folder.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import inspect
import json
import marshal
import os
import sys
import types
import tempfile
from pathlib import Path

import jax

from . import config

#: Bump to invalidate every kept program (a change in how they are stored).
FORMAT = 4
#: Values of ``GREYID_PROGRAMS`` that switch the store off.
OFF = ("off", "0", "no", "false")
DIGEST = 32  # bytes of a SHA-256


def folder() -> Path | None:
    """Where programs are kept, or None where greyid's cache is switched off or cannot be used."""
    base = config.cache_dir()
    return None if base is None or config.cache_folder_problem(base) else Path(base) / "programs"


def switched_on() -> bool:
    """Whether ``GREYID_PROGRAMS`` leaves programs kept by key: on disk where the cache folder is on, and
    shared in the process ([`Program`][greyid.runtime.jit.Program])."""
    return os.environ.get("GREYID_PROGRAMS", "on").lower() not in OFF


def enabled() -> bool:
    """Whether programs are kept: greyid's cache is on and ``GREYID_PROGRAMS`` is not ``off``."""
    return folder() is not None and switched_on()


#: Python versions whose compiler puts a function's docstring (or None) first among its code's constants;
#: there the docstrings are left out of the key (3.14 marks a docstring by a flag instead).
DOCSTRING_FIRST = ((3, 11), (3, 12), (3, 13))
#: Code objects with local variables that are not functions: their first constant may be the code's own.
NOT_FUNCTIONS = frozenset({"<listcomp>", "<setcomp>", "<dictcomp>", "<genexpr>"})


def code_digest(code: types.CodeType) -> bytes:
    """A module's compiled code without what does not change what it computes: its line numbers (so its
    comments and layout), its file's name and its functions' docstrings (where ``DOCSTRING_FIRST``)."""
    def bare(code):
        consts = tuple(bare(c) if isinstance(c, types.CodeType) else c for c in code.co_consts)
        if (sys.version_info[:2] in DOCSTRING_FIRST and code.co_flags & inspect.CO_NEWLOCALS
                and code.co_name not in NOT_FUNCTIONS and consts and isinstance(consts[0], str)):
            consts = (None, *consts[1:])
        return code.replace(co_consts=consts, co_firstlineno=1, co_linetable=b"", co_filename="")

    return marshal.dumps(bare(code))


def compiled_code(path: Path, source: bytes) -> types.CodeType:
    """The code of the module at ``path`` whose text is ``source``: from the bytecode Python keeps beside it
    where that was written after the file's last change and records its time and size, and the file still
    holds ``source`` (reading it is a tenth of compiling), otherwise compiled from ``source``."""
    try:
        kept = Path(importlib.util.cache_from_source(str(path)))
        stat, kept_stat = path.stat(), kept.stat()
        if kept_stat.st_mtime_ns > stat.st_mtime_ns:
            data = kept.read_bytes()
            if (data[:4] == importlib.util.MAGIC_NUMBER and data[4:8] == bytes(4)
                    and data[8:12] == (int(stat.st_mtime) & 0xFFFFFFFF).to_bytes(4, "little")
                    and data[12:16] == (len(source) & 0xFFFFFFFF).to_bytes(4, "little")
                    and path.read_bytes() == source):  # not changed since ``source`` was read
                return marshal.loads(data[16:])
    except (OSError, ValueError, EOFError, TypeError):
        pass
    return compile(source, str(path), "exec", dont_inherit=True, optimize=sys.flags.optimize)


def file_digest(path: Path, source: bytes) -> str:
    """The SHA-256 of [`code_digest()`][greyid.runtime.store.code_digest] of the module at ``path`` whose
    text is ``source``; of ``source`` itself where Python cannot compile it."""
    try:
        return hashlib.sha256(code_digest(compiled_code(path, source))).hexdigest()
    except Exception:  # noqa: BLE001
        return hashlib.sha256(source).hexdigest()


#: File, in the programs' folder, of each source file's code digest by the digest of its bytes: reading and
#: hashing greyid's files takes a process milliseconds, their bytecode's digests several times as long.
CODE_DIGESTS = "code-digests"
#: Entries kept in it (other versions' files too, for checkouts that share a cache folder).
CODE_DIGESTS_KEPT = 4096


def _remembered_digests(path: Path | None) -> dict:
    """The code digests kept at ``path`` by their files' byte digests; empty where none are (or a damaged
    file: it is written again)."""
    if path is None:
        return {}
    try:
        kept = json.loads(unseal(path.read_bytes()))
    except Exception:  # noqa: BLE001  none, damaged or edited: computed again
        return {}
    return {raw: code for raw, code in kept.items() if isinstance(code, str)} if isinstance(kept, dict) else {}


@functools.cache
def source_hash() -> str:
    """A hash of greyid's code ([`file_digest()`][greyid.runtime.store.file_digest] of each source file,
    remembered in the programs' folder by the file's bytes) and of the JAX that traces it."""
    base = folder()
    memo = None if base is None else base / CODE_DIGESTS
    known = _remembered_digests(memo)
    digest, found = hashlib.sha256(), {}
    root = Path(__file__).resolve().parents[1]
    for path in sorted(root.rglob("*.py")):
        source = path.read_bytes()
        # The bytes' digest names the Python and the optimisation level too: the bytecode depends on them.
        raw = hashlib.sha256(source + repr((sys.version, sys.flags.optimize)).encode()).hexdigest()
        found[raw] = known.get(raw) or file_digest(path, source)
        digest.update(str(path.relative_to(root)).encode())
        digest.update(found[raw].encode())
    if memo is not None and any(raw not in known for raw in found):
        others = [(raw, code) for raw, code in known.items() if raw not in found]
        room = max(CODE_DIGESTS_KEPT - len(found), 0)
        write(memo, seal(json.dumps(dict(others[max(len(others) - room, 0):]) | found).encode()))
    import jaxlib

    for part in (jax.__version__, jaxlib.__version__, jax.default_backend(), FORMAT,
                 jax.config.jax_enable_x64, jax.config.jax_default_matmul_precision):
        digest.update(repr(part).encode())
    return digest.hexdigest()


def path_for(key, args) -> Path:
    """The file of the program with ``key`` for arguments like ``args``."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    signature = (str(tree), [str(jax.typeof(a)) for a in leaves])
    text = repr((key, signature, source_hash()))
    return folder() / f"{hashlib.sha256(text.encode()).hexdigest()}.jaxexport"


_registered: set = set()


def register_named_tuples() -> None:
    """Register greyid's named tuples with ``jax.export`` by module and name, so that programs whose
    arguments or results hold them serialize and load (those of every greyid module imported so far)."""
    for name, module in list(sys.modules.items()):
        if not name.startswith("greyid.") or module is None:
            continue
        for value in list(vars(module).values()):
            if (isinstance(value, type) and issubclass(value, tuple) and hasattr(value, "_fields")
                    and value.__module__ == name and value not in _registered):
                jax.export.register_namedtuple_serialization(value, serialized_name=f"{name}.{value.__qualname__}")
                _registered.add(value)


def seal(blob: bytes) -> bytes:
    """A kept file: the serialized program, then its SHA-256."""
    blob = bytes(blob)
    return blob + hashlib.sha256(blob).digest()


def unseal(data: bytes) -> bytes:
    """The serialized program of a kept file; ValueError where it does not match its hash."""
    blob, digest = data[:-DIGEST], data[-DIGEST:]
    if len(data) <= DIGEST or hashlib.sha256(blob).digest() != digest:
        raise ValueError("the program does not match its hash")
    return blob


def load(path: Path):
    """The ``jax.export.Exported`` kept at ``path``, or None (none there; a damaged one is removed)."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    try:
        register_named_tuples()
        return jax.export.deserialize(bytearray(unseal(data)))
    except Exception:  # noqa: BLE001  damaged, edited or of unknown types: removed, exported again
        path.unlink(missing_ok=True)
        return None


def lowered(jitted, key, args):
    """The lowered call of ``jitted`` (a ``jax.jit`` function) for ``args``: from its kept export, or
    exported now and kept; None where the store is off or the program cannot be kept (the caller then
    traces it)."""
    if not enabled():
        return None
    try:
        path = path_for(key, args)
        exported = load(path)
        if exported is None:
            exported = jax.export.export(jitted)(*args)
            register_named_tuples()
            write(path, seal(exported.serialize()))
        return jax.jit(exported.call).lower(*args)
    except Exception:  # noqa: BLE001  any failure: traced as without the store
        return None


def write(path: Path, blob: bytes) -> None:
    """Write atomically, so that a process reading at the same time sees all of it or nothing."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as out:
            out.write(blob)
        os.replace(temporary, path)
    except OSError:
        Path(temporary).unlink(missing_ok=True)


def usage() -> dict:
    """What greyid's cache folder holds: ``{"folder", "programs": (files, bytes), "compiled": (files, bytes),
    "problem"}`` (compiled: JAX's persistent cache entries in the folder; problem: why the folder cannot be
    used, or None)."""
    base = config.cache_dir()
    out = {"folder": base, "programs": (0, 0), "compiled": (0, 0),
           "problem": None if base is None else config.cache_folder_problem(base)}
    if base is None or out["problem"] or not Path(base).is_dir():
        return out
    kept = [p for p in (Path(base) / "programs").glob("*.jaxexport") if p.is_file()]
    compiled = [p for p in Path(base).iterdir() if p.is_file()]
    out["programs"] = (len(kept), sum(p.stat().st_size for p in kept))
    out["compiled"] = (len(compiled), sum(p.stat().st_size for p in compiled))
    return out


def clear() -> int:
    """Remove what greyid's cache folder holds (kept programs and JAX's compiled entries); returns the
    number of files removed.  A process using them meanwhile falls back to tracing and compiling."""
    base = config.cache_dir()
    if base is None or config.cache_folder_problem(base) or not Path(base).is_dir():
        return 0
    removed = 0
    for path in list((Path(base) / "programs").glob("*")) + list(Path(base).iterdir()):
        if path.is_file():
            path.unlink(missing_ok=True)
            removed += 1
    return removed
