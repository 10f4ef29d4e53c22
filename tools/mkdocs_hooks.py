"""MkDocs hook: links from a docs page to repository files outside docs/ (data/SOURCES.md,
benchmarks/results/*.md, ...) point to the file on GitHub in the built site. The pages keep
their relative links, which work when the docs are read in the repository itself. A link to
a file that is not in the repository is left alone, so ``mkdocs build --strict`` reports it."""

from __future__ import annotations

import posixpath
import re
from pathlib import Path

REPO_URL = "https://github.com/difftissue/difftissue/blob/main/"
_LINK = re.compile(r"(\]\()(\.\./[^)\s#]+)(#[^)\s]*)?(\))")


def on_page_markdown(markdown, page, config, files):
    docs_dir = Path(config["docs_dir"]).resolve()
    root = docs_dir.parent
    page_dir = posixpath.dirname(page.file.src_uri)

    def repl(m):
        target = posixpath.normpath(posixpath.join("docs", page_dir, m.group(2)))
        if target.startswith("docs/") or target.startswith(".."):
            return m.group(0)  # inside docs/ (mkdocs checks it) or outside the repository
        if not (root / target).exists():
            return m.group(0)
        return f"{m.group(1)}{REPO_URL}{target}{m.group(3) or ''}{m.group(4)}"

    return _LINK.sub(repl, markdown)
