"""The manual's examples run: code, configs and commands in docs/ and README.md.

Every page's fenced blocks are checked in page order:

- ``pycon`` blocks are doctests: each ``>>>`` line runs and its printed result
  must match (ELLIPSIS, NORMALIZE_WHITESPACE);
- ``python`` blocks are executed, unless their first line is ``# not run: REASON``
  (a SLURM cluster, a Jupyter kernel);
- ``toml`` blocks are configs or fragments of one: laid over
  ``examples/lj_small.toml`` (each top-level key or table shown replacing the
  example's), they must pass ``md.config.parse_config``, so every key the
  manual shows is one the code accepts (and the README's config is the LJ
  melt example's);
- ``bash`` blocks: every ``md ...`` command must parse with the ``md``
  command's own argument parser (its subcommand and options exist).

The blocks of one page share a namespace and run in a temporary directory
holding a copy of ``examples/``, so the pages can use the example configs
and write files without touching the checkout. The site itself is built by
``.ci/run`` (Sphinx, warnings as errors).
"""

from __future__ import annotations

import doctest
import re
import shlex
import shutil
import tomllib
from dataclasses import replace
from pathlib import Path

import pytest

from md.cli import build_parser
from md.config import load_config, parse_config
from md.parallel import get_threads, set_threads

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.parts) + [ROOT / "README.md"]
FENCE = re.compile(r"^(`{3,})(\w*)[^\n]*\n(.*?)^\1\s*$", re.M | re.S)
NOT_RUN = "# not run:"


def blocks(page: Path, language: str) -> list[tuple[int, str]]:
    """The ``language`` code blocks of a page, with the line each starts on."""
    text = page.read_text()
    return [
        (text.count("\n", 0, m.start()) + 2, m.group(3))
        for m in FENCE.finditer(text)
        if m.group(2) == language
    ]


def page_id(page: Path) -> str:
    return str(page.relative_to(ROOT))


CODE_PAGES = [p for p in PAGES if blocks(p, "python") or blocks(p, "pycon")]


@pytest.fixture
def in_scratch(tmp_path, monkeypatch):
    """A temporary working directory with a copy of examples/, and one kernel thread.

    One thread, so that the examples' timings do not depend on idle cores (a page
    that sets threads itself, as the performance page does, still can); the
    process's thread count is restored afterwards. The example plug-in package is
    importable, as the plug-ins page's ``PYTHONPATH=examples/plugin_package`` makes it.
    """
    shutil.copytree(ROOT / "examples", tmp_path / "examples")
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path / "examples" / "plugin_package"))
    threads = get_threads()
    set_threads(1)
    yield tmp_path
    set_threads(threads)


@pytest.mark.parametrize("page", CODE_PAGES, ids=page_id)
def test_code_blocks_run_and_their_doctests_pass(page, in_scratch):
    text = page.read_text()
    namespace: dict = {"__name__": "__docs__"}
    parser = doctest.DocTestParser()
    runner = doctest.DocTestRunner(
        optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False
    )
    n_examples = 0
    for match in FENCE.finditer(text):
        language, code = match.group(2), match.group(3)
        line = text.count("\n", 0, match.start()) + 2
        where = f"{page_id(page)}:{line}"
        if language == "python":
            if code.startswith(NOT_RUN):
                assert code[len(NOT_RUN) :].split("\n", 1)[0].strip(), f"{where}: give a reason"
                continue
            exec(compile(code, where, "exec"), namespace)
        elif language == "pycon":
            test = parser.get_doctest(code, namespace, where, str(page), line - 1)
            test.globs = namespace  # DocTest copies its globals: share the page's instead
            assert test.examples, f"{where}: a pycon block without >>> lines"
            n_examples += len(test.examples)
            result = runner.run(test, clear_globs=False)
            assert result.failed == 0, f"{where}: {result.failed} doctest example(s) failed"
    if blocks(page, "pycon"):
        assert n_examples > 0


TOML_BLOCKS = [(page, line, code) for page in PAGES for line, code in blocks(page, "toml")]


@pytest.mark.parametrize(
    "page, line, code", TOML_BLOCKS, ids=[f"{page_id(p)}:{n}" for p, n, _ in TOML_BLOCKS]
)
def test_config_blocks_are_accepted_by_the_config_parser(page, line, code, in_scratch):
    examples = in_scratch / "examples"
    config = tomllib.loads((examples / "lj_small.toml").read_text())
    config.update(tomllib.loads(code))  # a fragment's tables replace the example's
    parse_config(config, source=f"{page_id(page)}:{line}", base=examples)


def test_the_readme_config_is_the_lj_melt_example():
    ((_, code),) = blocks(ROOT / "README.md", "toml")
    shown = parse_config(tomllib.loads(code), base=ROOT / "examples")
    example = load_config(ROOT / "examples" / "lj_melt.toml")
    assert replace(shown, source="", text="") == replace(example, source="", text="")


def md_commands(page: Path) -> list[tuple[int, str]]:
    """``md ...`` command lines of a page's bash blocks (continuations joined)."""
    commands = []
    for line, code in blocks(page, "bash"):
        for offset, command in enumerate(code.replace("\\\n", " ").splitlines()):
            command = command.split(" #", 1)[0].strip()
            if command.startswith("md "):
                commands.append((line + offset, command))
    return commands


COMMANDS = [(page, line, command) for page in PAGES for line, command in md_commands(page)]


@pytest.mark.parametrize(
    "page, line, command", COMMANDS, ids=[f"{page_id(p)}:{n}" for p, n, _ in COMMANDS]
)
def test_commands_shown_parse_with_the_md_parser(page, line, command):
    try:
        build_parser().parse_args(shlex.split(command)[1:])
    except SystemExit as exit:
        pytest.fail(f"{page_id(page)}:{line}: `{command}` does not parse (exit {exit.code})")
