"""MkDocs hooks of the documentation site (``mkdocs.yml``).

- The home page (``docs/index.md``) is the README: its block between the ``readme``
  markers is replaced by ``README.md`` at build time, so there is one copy of it. Links
  into ``docs/`` are made relative to the site; links to other files of the repository,
  which the site does not hold, keep their text only.
- The docstrings use Sphinx roles (``:func:`x```, ``:math:`(B, 3, H, W)```), which
  Markdown renders as a role name before the code: the API pages keep only the code.
"""
from __future__ import annotations

import re
from pathlib import Path

_README_BLOCK = re.compile(r"<!-- readme: start -->.*?<!-- readme: end -->", re.S)
_DOCS_LINK = re.compile(r"\]\(docs/([^)\s]+)\)")
_RELATIVE_LINK = re.compile(r"\[([^\]]+)\]\((?!https?://|mailto:|#)([^)\s]+)\)")
_ROLE = re.compile(r":(?:math|func|class|mod|meth|data|attr|obj|exc):(?=<code>)")
_TILDE = re.compile(r"<code>~")


def _readme(config) -> str:
    text = (Path(config.config_file_path).parent / "README.md").read_text(encoding="utf-8")
    text = _DOCS_LINK.sub(r"](\1)", text)
    docs = Path(config.docs_dir)

    def outside(match: re.Match) -> str:
        target = match.group(2).split("#")[0]
        return match.group(0) if (docs / target).is_file() else match.group(1)

    return _RELATIVE_LINK.sub(outside, text)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if page.file.src_uri == "index.md":
        return _README_BLOCK.sub(lambda _: _readme(config), markdown)
    return markdown


def on_page_content(html: str, page, config, files) -> str:
    if page.file.src_uri.startswith("api/"):
        html = _TILDE.sub("<code>", _ROLE.sub("", html))
    return html
