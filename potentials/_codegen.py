"""What the pair and bonded frames' code generators share.

Each frame runs a kernel template once per term as a module of its own, from a
copy of the template written to the kernel cache folder (:func:`template_copy`),
and names the copy after a hash of everything its compiled kernels depend on
(:func:`hash_value`: a term's functions with what they reach). The generators
themselves are ``potentials._pair_codegen`` and ``potentials._bonded_frame``;
ARCHITECTURE.md ("Generated code") says where the copies go, how to read one
and how to clear them.
"""

from __future__ import annotations

import atexit
import functools
import logging
import shutil
import tempfile
from pathlib import Path
from types import CodeType, FunctionType

import numpy as np
from numba.core import config

from md._files import atomic_path
from md._kernel_cache import cache_directory

logger = logging.getLogger(__name__)


def template_copy(folder_name: str, stem: str, text: bytes) -> Path:
    """A kernel template's copy for one term, ``text``: ``FOLDER_NAME/STEM.py`` in the kernel
    cache folder (the stem names the term and a hash of the copy's code: the same stem, the
    same bytes).

    Written whole under a temporary name and hard-linked into place, so a reader
    sees the complete file or none, and of two processes writing the same copy at
    once the second finds the first's and leaves it as it is (its modification
    time, which numba's cache index records, never changes). If the folder cannot
    be written, the copy goes to a temporary folder for this process only.
    """
    folders = [Path(config.CACHE_DIR or cache_directory()) / folder_name, None]
    for folder in folders:
        folder = folder or scratch_folder()
        path = folder / f"{stem}.py"
        if path.exists():
            return path
        try:
            folder.mkdir(parents=True, exist_ok=True)
            with atomic_path(path, exclusive=True) as partial:
                partial.write_bytes(text)
        except FileExistsError:  # another process wrote it first: the same bytes
            return path
        except OSError as error:
            logger.warning("cannot write %s (%s); using a temporary folder", path, error)
            continue
        return path
    raise OSError(f"no folder to write the {folder_name} kernels to ({folders[0]} is not writable)")


@functools.cache
def scratch_folder() -> Path:
    """A temporary folder for this process's template copies, removed when it exits."""
    folder = tempfile.mkdtemp(prefix="leapmd-pair-terms-")
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    return Path(folder)


def hash_value(digest, value, seen: set) -> None:
    """Add ``value`` to ``digest``: a function (or numba dispatcher) by its code and what it
    reaches, plain values and arrays by their contents; other objects (modules, classes)
    are named in the code that uses them."""
    value = getattr(value, "py_func", value)  # a numba dispatcher: its Python function
    if isinstance(value, FunctionType):
        if value in seen:
            return
        seen.add(value)
        hash_code(digest, value.__code__)
        for inner in (
            *(value.__defaults__ or ()),
            *(c.cell_contents for c in value.__closure__ or ()),
        ):
            hash_value(digest, inner, seen)
        for name in _names(value.__code__):
            if name in value.__globals__:
                digest.update(name.encode())
                hash_value(digest, value.__globals__[name], seen)
    elif isinstance(value, tuple | list):
        for item in value:
            hash_value(digest, item, seen)
    elif isinstance(value, np.ndarray):
        digest.update(repr((value.dtype.str, value.shape)).encode())
        digest.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, int | float | complex | str | bytes | np.generic) or value is None:
        digest.update(repr(value).encode())


def hash_code(digest, code: CodeType) -> None:
    digest.update(code.co_code)
    digest.update(repr(code.co_names).encode())
    for constant in code.co_consts:
        if isinstance(constant, CodeType):
            hash_code(digest, constant)
        elif isinstance(constant, frozenset):  # ``x in {...}``: sorted, as the order varies
            digest.update(repr(sorted(map(repr, constant))).encode())
        else:
            digest.update(repr(constant).encode())


def _names(code: CodeType) -> list[str]:
    """The global (and attribute) names a code object and those nested in it use."""
    nested = (c for c in code.co_consts if isinstance(c, CodeType))
    return [*code.co_names, *(name for inner in nested for name in _names(inner))]


def identifier(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name) or "term"
