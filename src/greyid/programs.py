"""Traced programs kept on disk, so that a later process need not trace them again.

Tracing greyid's estimation programs (a filter's scan differentiated twice,
vectorised over directions) takes most of a first fit's time once XLA's own
compilation comes from JAX's persistent cache (for the Armadillo model, tracing
takes longer than lowering and loading together).  A program given a ``key`` is exported
as StableHLO (``jax.export``) into ``$GREYID_CACHE_DIR/programs`` and a later
process with the same key loads it instead of tracing.

A kept program must be the one tracing would give, or answers would be
silently wrong: its file name is a hash of the key (the model's equations and
every setting the program closes over, see
[`greyid.model.structure.Structure.fingerprint`][greyid.model.structure.Structure.fingerprint]), the arguments' shapes
and types, greyid's source files and JAX's version and backend.  A process
that replaces greyid's functions or constants at run time (the test suite
does) must set ``GREYID_PROGRAMS=off``: the key does not see such changes.  A
program that cannot be exported (a host callback, say) or a file that cannot
be read or written is simply traced, as without this cache.

A file holds one line of JSON — the format, the results' tree structure
(containers and greyid's own named tuples, by name) and the SHA-256 of the
program — followed by JAX's serialized program (a flatbuffer of StableHLO):
nothing in it is executable Python.  A file whose program does not match its
hash (damaged, or edited) is removed and the program exported again.
``greyid cache info`` and ``greyid cache clear`` show and empty the folder.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import json
import os
import tempfile
from pathlib import Path
from typing import NamedTuple

from . import _jax
import jax

#: Bump to invalidate every kept program (a change in how they are stored).
FORMAT = 3


def folder() -> Path | None:
    """Where programs are kept, or None where greyid's cache is switched off."""
    base = _jax.cache_dir()
    # A folder that cannot be used (said once, when JAX is set up): nothing is kept.
    return None if base is None or _jax.cache_folder_problem(base) else Path(base) / "programs"


def enabled() -> bool:
    """Whether programs are kept: greyid's cache is on and ``GREYID_PROGRAMS`` is not ``off``."""
    return folder() is not None and os.environ.get("GREYID_PROGRAMS", "on").lower() not in OFF


OFF = ("off", "0", "no", "false")


@functools.cache
def source_hash() -> str:
    """A hash of greyid's source files and of the JAX that traces them."""
    digest = hashlib.sha256()
    root = Path(__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    import jaxlib

    for part in (jax.__version__, jaxlib.__version__, jax.default_backend(), FORMAT,
                 jax.config.jax_enable_x64, jax.config.jax_default_matmul_precision):
        digest.update(repr(part).encode())
    return digest.hexdigest()


def path_for(key, args) -> Path:
    leaves, tree = jax.tree_util.tree_flatten(args)
    signature = (str(tree), [str(jax.typeof(a)) for a in leaves])
    text = repr((key, signature, source_hash()))
    return folder() / f"{hashlib.sha256(text.encode()).hexdigest()}.jaxexport"


def flat_program(jitted, tree, out_trees: list):
    """The function of the arguments' leaves to the results' leaves (export stores neither
    greyid's own argument types nor its results'); tracing appends the results' tree to ``out_trees``."""
    def program(*leaves):
        out_leaves, out_tree = jax.tree_util.tree_flatten(jitted.nested(*jax.tree_util.tree_unflatten(tree, leaves)))
        out_trees.append(out_tree)
        return out_leaves

    return program


class Unkeepable(Exception):
    """A program whose results' structure cannot be written without pickling (it is traced instead)."""


def encode_tree(tree) -> object:
    """The results' tree structure as JSON: tuples, lists, dicts with string keys, None, leaves and
    greyid's own named tuples (by module and name)."""
    def encode(node):
        if node is None:
            return {"none": True}
        if isinstance(node, tuple) and hasattr(type(node), "_fields"):
            cls = type(node)
            if not cls.__module__.startswith("greyid."):
                raise Unkeepable(f"a named tuple of another package: {cls.__module__}.{cls.__qualname__}")
            return {"named": [cls.__module__, cls.__qualname__], "items": [encode(v) for v in node]}
        if type(node) in (tuple, list):
            return {type(node).__name__: [encode(v) for v in node]}
        if type(node) is dict:
            if not all(isinstance(k, str) for k in node):
                raise Unkeepable("a dict with keys that are not strings")
            return {"dict": {k: encode(v) for k, v in node.items()}}
        if node == "leaf":
            return "leaf"
        raise Unkeepable(f"a tree node of type {type(node).__name__}")

    return encode(jax.tree_util.tree_unflatten(tree, ["leaf"] * tree.num_leaves))


def decode_tree(spec):
    """The tree structure [`encode_tree()`][greyid.programs.encode_tree] wrote (named tuples only from greyid's
    modules)."""
    def decode(node):
        if node == "leaf":
            return 0
        if not isinstance(node, dict) or len(node) not in (1, 2):
            raise ValueError(f"not a tree node: {node!r}")
        if "none" in node:
            return None
        if "named" in node:
            module, name = node["named"]
            if not module.startswith("greyid."):
                raise ValueError(f"a named tuple outside greyid: {module}")
            cls = importlib.import_module(module)
            for part in name.split("."):
                cls = getattr(cls, part)
            if not (isinstance(cls, type) and issubclass(cls, tuple) and hasattr(cls, "_fields")):
                raise ValueError(f"{module}.{name} is not a named tuple")
            return cls(*[decode(v) for v in node["items"]])
        if "tuple" in node:
            return tuple(decode(v) for v in node["tuple"])
        if "list" in node:
            return [decode(v) for v in node["list"]]
        if "dict" in node:
            return {k: decode(v) for k, v in node["dict"].items()}
        raise ValueError(f"not a tree node: {node!r}")

    return jax.tree_util.tree_structure(decode(spec))


def pack(out_tree, blob: bytes) -> bytes:
    """A kept file: its JSON header line, then the serialized program."""
    header = {"format": FORMAT, "out_tree": encode_tree(out_tree), "sha256": hashlib.sha256(blob).hexdigest()}
    return json.dumps(header, separators=(",", ":")).encode() + b"\n" + bytes(blob)


def unpack(data: bytes):
    """``(out_tree, blob)`` of a kept file; ValueError where it is damaged (hash, format, header)."""
    line, newline, blob = data.partition(b"\n")
    if not newline:
        raise ValueError("no header")
    header = json.loads(line)
    if header.get("format") != FORMAT:
        raise ValueError(f"format {header.get('format')!r}")
    if hashlib.sha256(blob).hexdigest() != header.get("sha256"):
        raise ValueError("the program does not match its hash")
    return decode_tree(header["out_tree"]), blob


class KeptProgram(NamedTuple):
    """A kept program's call, lowered and ready for XLA, and where it is kept."""

    lowered: object  # jax.stages.Lowered
    out_tree: object  # the results' tree structure
    path: Path

    def runner(self, compiled):
        """A callable taking the jitted function's own arguments, running ``compiled``."""
        out_tree = self.out_tree

        def run(*call_args):
            return jax.tree_util.tree_unflatten(out_tree, compiled(*jax.tree_util.tree_leaves(call_args)))

        return run


def kept_lowering(jitted, args, jax_jit) -> KeptProgram | None:
    """The lowered call of ``jitted``'s program for ``args``: loaded from its kept export, or
    exported now and kept; None when the program cannot be kept (the caller then traces it).
    ``jax_jit`` is the compiler's ``jax.jit`` with its options, which the loaded call is lowered by."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    try:
        path = path_for(jitted.key, args)
        exported = None
        try:
            data = path.read_bytes()
        except OSError:
            data = None
        if data is not None:
            try:
                out_tree, blob = unpack(data)
                exported = jax.export.deserialize(bytearray(blob))
            except Exception:  # noqa: BLE001  damaged or edited: removed, exported again below
                path.unlink(missing_ok=True)
                exported = None
        if exported is None:
            out_trees: list = []
            exported = jax.export.export(jax.jit(flat_program(jitted, tree, out_trees)))(*leaves)
            out_tree, blob = out_trees[-1], exported.serialize()
            write(path, pack(out_tree, blob))
        lowered = jax_jit(exported.call).lower(*leaves)
    except Exception:  # noqa: BLE001  any failure: trace as without the cache
        return None
    return KeptProgram(lowered, out_tree, path)


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
    base = _jax.cache_dir()
    out = {"folder": base, "programs": (0, 0), "compiled": (0, 0),
           "problem": None if base is None else _jax.cache_folder_problem(base)}
    if base is None or out["problem"] or not Path(base).is_dir():
        return out
    kept = [p for p in (Path(base) / "programs").glob("*") if p.is_file()]
    compiled = [p for p in Path(base).iterdir() if p.is_file()]
    out["programs"] = (len(kept), sum(p.stat().st_size for p in kept))
    out["compiled"] = (len(compiled), sum(p.stat().st_size for p in compiled))
    return out


def clear() -> int:
    """Remove what greyid's cache folder holds (kept programs and JAX's compiled entries); returns the
    number of files removed.  A process using them meanwhile falls back to tracing and compiling."""
    base = _jax.cache_dir()
    if base is None or _jax.cache_folder_problem(base) or not Path(base).is_dir():
        return 0
    removed = 0
    for path in list((Path(base) / "programs").glob("*")) + list(Path(base).iterdir()):
        if path.is_file():
            path.unlink(missing_ok=True)
            removed += 1
    return removed
