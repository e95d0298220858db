"""MkDocs hook: the site's changelog page is the repository's CHANGELOG.md.

docs/changelog.md holds one line, ``--8<-- "CHANGELOG.md"``; this hook puts the file there before the
page is converted, with its links to ``docs/...`` (written from the repository root, where GitHub shows
the file) made relative to the docs folder, so ``mkdocs build --strict`` resolves them.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any

INCLUDE = re.compile(r'^--8<-- "([^"]+)"\s*$', re.MULTILINE)


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    root = Path(config["config_file_path"]).resolve().parent

    def include(match: re.Match[str]) -> str:
        text = (root / match.group(1)).read_text(encoding="utf-8")
        return text.replace("](docs/", "](")

    return INCLUDE.sub(include, markdown)
