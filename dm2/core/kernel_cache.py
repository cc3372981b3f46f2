"""Compiled kernels cached against the whole source they were compiled from.

numba caches each compiled function (``cache=True``) beside its own file and reuses it while
that one file is unchanged. A kernel also holds code from other files: the functions it inlines
(``inline="always"``: the TSDF's ray walk and voxel update live in one file and are compiled
into the kernels of two others) and the constants it reads from other modules, frozen at compile
time. After an edit or an upgrade that changed only such a file, numba would load the old
machine code and the kernel would silently compute what the old source said.

:func:`key_kernel_caches` makes the cached code of every function defined under a package's
folder carry a key of all the ``.py`` files it may draw on: a cache saved under another key is
stale and is compiled again (and saved over, in the same place numba would use). The files are
those that define compiled functions and every module of the packages they import from, to the
end of the chain (with the package ``__init__`` files on the way): a kernel's globals are its
own module's names, so compiled code draws on nothing else. Editing any other file (the CLI,
the report) compiles nothing again. The key is a SHA-256 of those files' paths and contents
(about 20 ms for this package), computed once per process.
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

_REGISTERED: dict[tuple[str, ...], str] = {}  # package folders -> source key
# a decorator that compiles the function below it
_COMPILED = re.compile(rb"^\s*@(?:numba\.)?(?:njit|jit|vectorize|guvectorize|cfunc|stencil)\b",
                       re.M)
_FROM = re.compile(rb"^\s*from\s+([\w.]+)\s+import\s+(\([^)]*\)|[^\n]*)", re.M)
_IMPORT = re.compile(rb"^\s*import\s+([\w.]+)", re.M)


def kernel_sources(roots: tuple[Path, ...]) -> list[Path]:
    """The ``.py`` files under the package folders ``roots`` that compiled code can draw on:
    those that define compiled functions, and every module of these packages they import from,
    transitively, with the ``__init__`` files of the packages on the way; sorted."""
    roots = tuple(root.resolve() for root in roots)
    files = {p: p.read_bytes() for root in roots for p in root.rglob("*.py")}
    tops = {root.name.encode() for root in roots}
    parents = {root.name: root.parent for root in roots}

    def module_files(dotted: bytes) -> list[Path]:
        parts = dotted.decode().split(".")
        base = parents[parts[0]]
        found = [base.joinpath(*parts[:k], "__init__.py") for k in range(1, len(parts) + 1)]
        found.append(base.joinpath(*parts).with_suffix(".py"))
        return [f for f in found if f in files]

    todo = [p for p, text in files.items() if _COMPILED.search(text)]
    seen = set(todo)
    while todo:
        text = files[todo.pop()]
        modules = [m.group(1) for m in _IMPORT.finditer(text)]
        for m in _FROM.finditer(text):
            modules.append(m.group(1))  # and each name, in case it is a submodule
            names = m.group(2).strip(b"()").replace(b"\n", b" ").split(b",")
            modules += [m.group(1) + b"." + n.split()[0] for n in names if n.split()]
        for dotted in modules:
            if dotted.split(b".")[0] in tops:
                for f in module_files(dotted):
                    if f not in seen:
                        seen.add(f)
                        todo.append(f)
    return sorted(seen)


def source_key(roots: tuple[Path, ...]) -> str:
    """SHA-256 (hex, 16 digits) of the paths (relative to the packages' parent) and contents of
    the :func:`kernel_sources` of the package folders ``roots``."""
    roots = tuple(root.resolve() for root in roots)
    h = hashlib.sha256()
    for path in kernel_sources(roots):
        root = next(r for r in roots if path.is_relative_to(r))
        h.update(path.relative_to(root.parent).as_posix().encode())
        h.update(b"\0")
        h.update(path.read_bytes())
        h.update(b"\0")
    return h.hexdigest()[:16]


def key_kernel_caches(packages: tuple[Path, ...], sources: tuple[Path, ...]) -> str:
    """Key the numba cache of every function defined under the folders ``packages`` with
    :func:`source_key` of the folders ``sources`` (which include ``packages``); returns the key.
    Call it before the packages' kernels are defined (from the package's ``__init__``); a
    second call for the same packages changes nothing."""
    folders = tuple(str(p.resolve()) + os.sep for p in packages)
    if folders in _REGISTERED:
        return _REGISTERED[folders]
    from numba.core import caching

    key = source_key(sources)
    keyed = [_keyed(base, folders, key) for base in (
        caching.UserProvidedCacheLocator, caching.InTreeCacheLocator,
        caching.UserWideCacheLocator)]
    impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)
    if impl is None:  # numba >= 0.68 names it CacheImpl, earlier releases _CacheImpl
        import numba

        raise ImportError(f"dm2.core.kernel_cache: numba {numba.__version__} has no "
                          "numba.core.caching.CacheImpl whose cache locators it could key")
    impl._locator_classes[:0] = keyed
    _REGISTERED[folders] = key
    return key


def _keyed(base: type, folders: tuple[str, ...], key: str) -> type:
    """numba's cache locator ``base`` for the files under ``folders`` only, its source stamp
    joined with ``key``."""

    class Keyed(base):
        def get_source_stamp(self):
            return super().get_source_stamp(), key

        @classmethod
        def from_function(cls, py_func, py_file):
            if not os.path.realpath(py_file).startswith(folders):
                return None
            return super().from_function(py_func, py_file)

    Keyed.__name__ = Keyed.__qualname__ = f"Keyed{base.__name__}"
    return Keyed
