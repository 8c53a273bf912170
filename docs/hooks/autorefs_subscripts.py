"""MkDocs hook: drop mkdocs-autorefs' warning for a 'cross-reference' that is only a number.

Docstrings show doctest lines such as ``ds.truth["images"][0]``, which Markdown reads as a
reference link ``[...][0]``; autorefs then warns that it cannot find the target ``0``. A number
is never the name of a documented object, so only those warnings are dropped; every other
unresolved reference still fails ``mkdocs build --strict``.
"""

from __future__ import annotations

import logging
import re

_NUMBER_TARGET = re.compile(r"Could not find cross-reference target '\d+'")


class _DropNumberTargets(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not _NUMBER_TARGET.search(record.getMessage())


def on_startup(command, dirty):  # noqa: ARG001 - MkDocs hook signature
    for name in ("mkdocs.plugins.mkdocs_autorefs", "mkdocs.plugins.mkdocs_autorefs._internal.plugin"):
        logging.getLogger(name).addFilter(_DropNumberTargets())
