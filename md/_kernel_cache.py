"""Where numba caches our compiled kernels: a per-user folder, not the package's own.

numba's default puts a kernel's cache in ``__pycache__`` beside its source. For
an installed (non-editable) package that is inside ``site-packages``, and pip
does not remove those files when the package is uninstalled or replaced by an
editable install: ``site-packages/md/`` would survive as a folder without
``__init__.py`` and shadow the real package as a namespace package in any
process started outside the checkout. So each package's ``__init__`` imports
its kernel modules inside :func:`kernel_cache`, which points numba at
``$XDG_CACHE_HOME/leapmd/numba`` (default ``~/.cache/leapmd/numba``) while
the kernels are decorated (numba picks a kernel's cache folder then), and
restores numba's setting afterwards, so other libraries' caches are left
where numba puts them. numba keeps one sub-folder per source folder, so two
installs (a checkout and a wheel) never share cache files. A user's own
``NUMBA_CACHE_DIR`` wins; an unwritable folder makes numba fall back to its
usual places.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from numba.core import config


def cache_directory() -> Path:
    """The folder our kernels' numba cache goes to (unless NUMBA_CACHE_DIR is set)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "leapmd" / "numba"


@contextlib.contextmanager
def kernel_cache() -> Iterator[None]:
    """Decorate ``@njit(cache=True)`` kernels inside this block to cache them per user."""
    if config.CACHE_DIR:  # NUMBA_CACHE_DIR, or an enclosing kernel_cache(): leave it
        yield
        return
    config.CACHE_DIR = str(cache_directory())
    try:
        yield
    finally:
        config.CACHE_DIR = ""
