"""The ``>>>`` examples in the user docs run and print what the docs show."""

import doctest
import re
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"
# installation.md demonstrates float32 round-off and must run without float64; it is not here.
PAGES = ["quickstart.md", "meshes.md", "materials.md"]


@pytest.mark.parametrize("page", PAGES)
def test_doc_examples(page, tmp_path, monkeypatch):
    text = (DOCS / page).read_text()
    src = "\n\n".join(b for b in re.findall(r"```python\n(.*?)```", text, flags=re.S) if ">>>" in b)
    assert src, f"{page} has no examples"
    monkeypatch.chdir(tmp_path)
    test = doctest.DocTestParser().get_doctest(src, {"__name__": "__doc__"}, page, str(DOCS / page), 0)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples in {page} failed (see the output above)"
