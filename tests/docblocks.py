"""The one harness for code in the docs: the fenced blocks of a Markdown page, run as doctests
(``>>>`` blocks) or executed as scripts. Imported by the tests that check a page's examples
(tests/ is on sys.path, as for tests/calculix.py)."""

from __future__ import annotations

import doctest
import re
from contextlib import redirect_stdout
from io import StringIO
from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs"
_FENCE = re.compile(r"```python\n(.*?)```", flags=re.S)


def page_text(page: str | Path) -> str:
    """The text of ``page`` (a path, or a name under docs/)."""
    path = Path(page)
    return (path if path.is_absolute() else DOCS / path).read_text()


def python_blocks(page: str | Path, *, doctest_only: bool = False) -> list[str]:
    """The ```` ```python ```` blocks of ``page``; with ``doctest_only`` those with ``>>>``."""
    blocks = _FENCE.findall(page_text(page))
    return [b for b in blocks if ">>>" in b] if doctest_only else blocks


def run_doctests(page: str | Path, globs: dict | None = None) -> tuple[int, int]:
    """Run the ``>>>`` examples of ``page`` as one doctest (ELLIPSIS, NORMALIZE_WHITESPACE),
    sharing one namespace; returns ``(failed, attempted)`` (failures are printed). Asserts the
    page has examples."""
    src = "\n\n".join(python_blocks(page, doctest_only=True))
    assert src, f"{page} has no >>> examples"
    name = Path(page).name
    test = doctest.DocTestParser().get_doctest(src, {"__name__": "__doc__", **(globs or {})}, name, str(DOCS / name), 0)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    runner.run(test)
    result = runner.summarize(verbose=False)
    return result.failed, result.attempted


def assert_doctests_pass(page: str | Path, globs: dict | None = None) -> None:
    failed, attempted = run_doctests(page, globs)
    assert failed == 0, f"{failed} of {attempted} examples in {page} failed (see the output above)"


def exec_blocks(page: str | Path, blocks: list[str] | None = None, namespace: dict | None = None) -> str:
    """Execute ``blocks`` (default: every python block of ``page``) in order in one namespace,
    as scripts; returns what they printed."""
    namespace = {} if namespace is None else namespace  # no __name__: classes the blocks define get module "builtins", as in a plain exec
    buf = StringIO()
    with redirect_stdout(buf):
        for block in python_blocks(page) if blocks is None else blocks:
            exec(compile(block, f"docs/{Path(page).name}", "exec"), namespace)
    return buf.getvalue()
