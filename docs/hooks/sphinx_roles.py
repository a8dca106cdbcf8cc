"""MkDocs hook: show the code's Sphinx roles (:class:`~a.b.C`) on the API page as plain code (``C``).

The docstrings are read in a terminal and by IDEs as much as on this site, so they keep Sphinx's
cross-reference roles; mkdocstrings renders the role's name literally before the code span.
"""

from __future__ import annotations

import re

_ROLE = re.compile(r":(?:class|func|meth|mod|data|attr|exc|obj):<code>(~?)([^<]*)</code>")


def _short(match: re.Match[str]) -> str:
    tilde, target = match.groups()
    # "~a.b.C" shows "C" in Sphinx; a plain dotted target shows in full.
    return f"<code>{target.rsplit('.', 1)[-1] if tilde else target}</code>"


def on_page_content(html: str, **_) -> str:
    return _ROLE.sub(_short, html)
