"""Where numba caches our compiled kernels, and when an entry there is stale.

The folder: a per-user one, not the package's own. numba's default puts a
kernel's cache in ``__pycache__`` beside its source. For an installed
(non-editable) package that is inside ``site-packages``, and pip does not
remove those files when the package is uninstalled or replaced by an editable
install: ``site-packages/md/`` would survive as a folder without
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

Staleness: numba stamps a kernel's cache entry with its own source file only,
yet a kernel compiles in the helpers it calls from other modules (the
neighbour list's ``_cell_list`` the cell and candidate kernels, the cluster
search the prune's helpers), so after an edit, checkout or merge that touched
only a helper's file numba would load the caller with the old helper. Inside
:func:`kernel_cache` numba therefore finds our locator first (numba's
``UserProvidedCacheLocator`` for files under our packages only, in whichever
folder ``NUMBA_CACHE_DIR`` or :func:`cache_directory` names): its
stamp adds, to numba's own, the modification time and size of every module
of ours the kernel's file imports, transitively (:func:`module_dependencies`,
a scan of the ``import`` lines). An edited helper makes its callers'
entries stale, and numba compiles them afresh; nothing needs clearing by
hand. Where numba's internals differ (another version), numba's own locators
serve as before, and a debug message says so.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import re
from collections.abc import Iterable, Iterator
from pathlib import Path

from numba.core import config

logger = logging.getLogger(__name__)

#: Our packages' folders in this installation (the stamp follows imports only within them).
PACKAGE_ROOTS = tuple(
    os.path.realpath(Path(__file__).parent.parent / name)
    for name in ("md", "potentials", "integrators")
)

#: An ``import`` or ``from ... import`` line (its names in parentheses may span lines);
#: matched from a newline, which the regex engine finds fast (``^`` with MULTILINE
#: was four times slower).
_IMPORT_LINE = re.compile(
    rb"\n[ \t]*(?:from[ \t]+(\.*[\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n]*)|import[ \t]+([^\n]*))"
)

#: The roots of each enclosing kernel_cache() block (innermost last).
_active_roots: list[tuple[str, ...]] = []


def cache_directory() -> Path:
    """The folder our kernels' numba cache goes to (unless NUMBA_CACHE_DIR is set)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "leapmd" / "numba"


def module_dependencies(path: str | os.PathLike, roots: Iterable[str | os.PathLike]) -> list[str]:
    """The module files under ``roots`` that the module file ``path`` imports, transitively.

    Parameters
    ----------
    path : path-like
        A ``.py`` file in one of the packages whose folders are ``roots``.
    roots : iterable of path-like
        Package folders (``md/``, ...): an import ``pkg.sub.mod`` (or a relative one)
        is followed when ``pkg`` names one of them and the module's file exists there.

    Returns
    -------
    list of str
        The files' real paths, sorted, ``path`` itself left out. Imports are found by
        a scan of the ``import`` and ``from ... import`` lines (those inside functions
        or ``if TYPE_CHECKING`` blocks too), so the list may hold more than runs; a
        module reached only through ``importlib`` or a function passed in as an
        argument is not found. A package's ``__init__`` counts when a name other than
        a submodule is imported from it. Each file's scan is memoised per process.
    """
    root_items = tuple(
        sorted((os.path.basename(r), r) for r in (_real(os.fspath(r)) for r in roots))
    )
    start = _real(os.fspath(path))
    seen = {start}
    pending = [start]
    while pending:
        for dep in _imports_of(pending.pop(), root_items):
            if dep not in seen:
                seen.add(dep)
                pending.append(dep)
    seen.discard(start)
    return sorted(seen)


def dependency_stamp(
    path: str | os.PathLike, roots: Iterable[str | os.PathLike]
) -> tuple[tuple[str, int, int], ...]:
    """``(file, st_mtime_ns, st_size)`` of each of :func:`module_dependencies`.

    The file names are relative to the folder above the roots (``md/box.py``).
    """
    return _stamp(_real(os.fspath(path)), tuple(_real(os.fspath(r)) for r in roots))


# Memoised per process (a process compiles what it imported, so a later edit changes
# nothing for it): each file's real path, imports, modification time and size once.


@functools.cache
def _stamp(path: str, roots: tuple[str, ...]) -> tuple[tuple[str, int, int], ...]:
    stamp = []
    for dep in module_dependencies(path, roots):
        root = next(r for r in roots if _is_under(dep, r))
        name = dep[len(os.path.dirname(root)) + 1 :]  # relative to the roots' parent
        stamp.append((name, *_file_stat(dep)))
    return tuple(stamp)


@functools.cache
def _file_stat(path: str) -> tuple[int, int]:
    try:
        st = os.stat(path)
    except OSError:
        return (-1, -1)
    return (st.st_mtime_ns, st.st_size)


@functools.cache
def _real(path: str) -> str:
    return os.path.realpath(path)


def _is_under(path: str, root: str) -> bool:
    return path.startswith(root + os.sep)


@functools.cache
def _imports_of(path: str, root_items: tuple[tuple[str, str], ...]) -> tuple[str, ...]:
    """The files under the roots that the module file ``path`` imports directly."""
    roots = dict(root_items)
    package = _module_name(path, roots)
    if package is None:
        return ()
    try:
        with open(path, "rb") as f:
            text = f.read()
    except OSError:
        return ()
    package = package if os.path.basename(path) == "__init__.py" else package.rpartition(".")[0]
    found = []
    for match in _IMPORT_LINE.findall(b"\n" + text):
        module, names, modules = (group.decode("latin-1") for group in match)
        if modules:  # import a.b, c as d
            for item in modules.split("#")[0].split(","):
                target = _module_file(item.split(" as ")[0].strip(), root_items)
                if target is not None:
                    found.append(target)
            continue
        base = _absolute(module, package)
        target = None if base is None else _module_file(base, root_items)
        if target is None:
            continue
        if not target.endswith("__init__.py"):
            found.append(target)
            continue
        names = [
            item.split()[0]
            for item in re.sub(r"#[^\n]*", "", names).strip("()").split(",")
            if item.strip()
        ]
        subs = [_module_file(f"{base}.{name}", root_items) for name in names]
        found.extend(sub for sub in subs if sub is not None)
        if None in subs:  # a name defined in the package's __init__ itself
            found.append(target)
    return tuple(dict.fromkeys(found))


def _module_name(path: str, roots: dict[str, str]) -> str | None:
    """The dotted name of the module file ``path`` under one of the roots."""
    for name, root in roots.items():
        if _is_under(path, root):
            parts = path[len(root) + 1 : -len(".py")].split(os.sep)
            if parts[-1] == "__init__":
                parts.pop()
            return ".".join([name, *parts])
    return None


def _absolute(module: str, package: str) -> str | None:
    """The absolute name of ``from MODULE import`` written in ``package``."""
    level = len(module) - len(module.lstrip("."))
    if level == 0:
        return module
    parts = package.split(".")
    if level > len(parts):
        return None
    base = ".".join(parts[: len(parts) - level + 1])
    rest = module[level:]
    return f"{base}.{rest}" if rest else base


@functools.cache
def _module_file(name: str, root_items: tuple[tuple[str, str], ...]) -> str | None:
    """The file of module ``name`` if it is under one of the roots."""
    first, _, rest = name.partition(".")
    root = dict(root_items).get(first)
    if root is None or not name.replace(".", "").replace("_", "").isalnum():
        return None
    folder = os.path.join(root, *rest.split(".")) if rest else root
    for candidate in (folder + ".py", os.path.join(folder, "__init__.py")):
        if os.path.isfile(candidate):
            return candidate
    return None


@functools.cache
def _numba_caching():
    """(numba's cache module, our locator class), or None where numba's internals are not
    as this expects (another numba version; logged once at debug)."""
    try:
        from numba.core import caching  # numba's cache internals, needed only here

        base = caching.UserProvidedCacheLocator
        if not isinstance(caching.CacheImpl._locator_classes, list):
            raise TypeError("CacheImpl._locator_classes is not a list")
    except (ImportError, AttributeError, TypeError) as error:
        logger.debug("numba's cache stamps only each kernel's own file here (%s)", error)
        return None

    class DependencyStampLocator(base):
        """numba's locator for its ``config.CACHE_DIR`` (ours or ``NUMBA_CACHE_DIR``), for
        files under an open block's roots only, whose source stamp adds the
        :func:`dependency_stamp` of the modules the file imports."""

        @classmethod
        def from_function(cls, py_func, py_file):
            path = _real(py_file)
            for roots in reversed(_active_roots):
                if any(_is_under(path, root) for root in roots):
                    self = super().from_function(py_func, py_file)
                    if self is not None:
                        self._dependency_roots = roots
                    return self
            return None

        def get_source_stamp(self):
            own = super().get_source_stamp()
            return own, dependency_stamp(self._py_file, self._dependency_roots)

    return caching, DependencyStampLocator


@contextlib.contextmanager
def kernel_cache(roots: Iterable[str | os.PathLike] | None = None) -> Iterator[None]:
    """Decorate ``@njit(cache=True)`` kernels inside this block to cache them per user.

    Parameters
    ----------
    roots : iterable of path-like, optional
        The package folders whose kernels get the dependency stamp and whose
        modules it follows (default :data:`PACKAGE_ROOTS`, ours).
    """
    roots = PACKAGE_ROOTS if roots is None else tuple(_real(os.fspath(r)) for r in roots)
    with _dependency_locator(roots):
        if config.CACHE_DIR:  # NUMBA_CACHE_DIR, or an enclosing kernel_cache(): leave it
            yield
            return
        config.CACHE_DIR = str(cache_directory())
        try:
            yield
        finally:
            config.CACHE_DIR = ""


@contextlib.contextmanager
def _dependency_locator(roots: tuple[str, ...]) -> Iterator[None]:
    """Put our locator first in numba's list while the outermost block is open."""
    found = _numba_caching()
    if found is None:
        yield
        return
    caching, locator = found
    outermost = not _active_roots
    if outermost:
        previous = caching.CacheImpl._locator_classes
        caching.CacheImpl._locator_classes = [locator, *previous]
    _active_roots.append(roots)
    try:
        yield
    finally:
        _active_roots.pop()
        if outermost:
            caching.CacheImpl._locator_classes = previous
