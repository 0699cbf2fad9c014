"""MkDocs hook: a link from a page of docs/ to the repository's README, which is not a page of the site.

docs/RESULTS.md and docs/ARCHITECTURE.md are read on GitHub as well as on the site, and on GitHub they
point to ``../README.md``. On the site that link leads to the home page (docs/index.md), the README's
counterpart, rather than out of the site. Any other link out of docs/ is left to MkDocs, which warns about it.
"""

from __future__ import annotations

import posixpath
import re

README = "README.md"
LINK = re.compile(r"\]\(([^)\s#]+)(#[^)\s]*)?\)")


def on_page_markdown(markdown: str, page, config, files) -> str:
    here = posixpath.dirname(page.file.src_uri)
    home = posixpath.relpath("index.md", here or ".")

    def relink(m: re.Match) -> str:
        target = m.group(1)
        if "://" in target or posixpath.normpath(posixpath.join(here, target)) != posixpath.join("..", README):
            return m.group(0)
        return f"]({home})"

    return LINK.sub(relink, markdown)
