"""MkDocs hook: the Sphinx roles of the docstrings (``:func:`name```, ``:class:`~pkg.mod.Name```) in the API
reference, as links to the objects they name.

mkdocstrings renders a role as its name in backticks after the role's own text (``:func:<code>x</code>``). This
hook drops the role's text, shows ``~pkg.mod.Name`` as ``Name`` (Sphinx's meaning of ``~``), and links the name
to the object's entry where the reference documents it: the name as written if it is a full path, else the
nearest enclosing scope that holds it (the object whose docstring it is in, then its parents), else the one
documented object whose path ends with it. A name the reference does not document (a private helper, a
constant without a docstring) stays plain code.

Two passes: every API page's anchors are collected as it is rendered (``on_page_content``), and the links are
made once all pages are (``on_post_page``), so that a name may point to another page.
"""

from __future__ import annotations

import html
import re

from mkdocs.utils import get_relative_url

ROLE = re.compile(r":(?:func|class|meth|mod|data|attr|exc|obj):<code>([^<]+)</code>")
ANCHOR = re.compile(r'id="(warp_vision(?:\.\w+)*)"')
PENDING = re.compile(r'<code data-role="([^"]+)" data-scope="([^"]*)">([^<]*)</code>')

#: documented object path -> the URL of its page, collected over the build
_anchors: dict[str, str] = {}


def on_pre_build(config) -> None:
    _anchors.clear()  # (mkdocs serve builds again in the same process)


def on_page_content(html_text: str, page, config, files) -> str:
    if not page.file.src_uri.startswith("api/"):
        return html_text
    anchors = [(m.start(), m.group(1)) for m in ANCHOR.finditer(html_text)]
    for _, name in anchors:
        _anchors.setdefault(name, page.url)

    def mark(m: re.Match) -> str:
        text = html.unescape(m.group(1)).strip()
        name = text.lstrip("~").removesuffix("()")
        shown = name.rsplit(".", 1)[-1] if text.startswith("~") else text
        scope = next((a for pos, a in reversed(anchors) if pos < m.start()), "")
        return f'<code data-role="{html.escape(name)}" data-scope="{scope}">{html.escape(shown)}</code>'

    return ROLE.sub(mark, html_text)


def _target(name: str, scope: str) -> str | None:
    """The documented path ``name`` refers to from the docstring of ``scope``, or None."""
    if name in _anchors:
        return name
    parts = scope.split(".")
    for k in range(len(parts), 0, -1):
        candidate = ".".join(parts[:k] + [name])
        if candidate in _anchors:
            return candidate
    ends = [a for a in _anchors if a.endswith("." + name)]
    return ends[0] if len(ends) == 1 else None


def on_post_page(output: str, page, config) -> str:
    if not page.file.src_uri.startswith("api/"):
        return output

    def link(m: re.Match) -> str:
        name, scope, shown = html.unescape(m.group(1)), m.group(2), m.group(3)
        target = _target(name, scope)
        if target is None:
            return f"<code>{shown}</code>"
        href = get_relative_url(_anchors[target], page.url) + "#" + target
        return f'<a href="{html.escape(href)}" title="{target}"><code>{shown}</code></a>'

    return PENDING.sub(link, output)
