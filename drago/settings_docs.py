"""Each setting's description, read from the comments beside and above its field in drago/config.py.

One owner for what a setting means: ``drago list --settings`` prints these descriptions and the docs' settings
page (docs/hooks/settings_page.py) renders them, so neither can drift from the code.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import io
import re
import textwrap
import tokenize
from functools import cache

# A comment block of this form above a field starts a group of settings: "# -- EWC --", "# Planning."
_GROUP = re.compile(r"^--\s*(.+?)\s*--$")


@dataclasses.dataclass
class FieldDoc:
    name: str
    description: str
    group: str | None


def clean(text: str) -> str:
    """A comment as a description: its whitespace collapsed."""
    return re.sub(r"\s+", " ", text).strip()


def _comments_by_line(source: str) -> dict[int, tuple[str, bool]]:
    """Line number -> (comment text, whether the line holds nothing but the comment)."""
    comments: dict[int, tuple[str, bool]] = {}
    lines = source.splitlines()
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            row, col = token.start
            alone = not lines[row - 1][:col].strip()
            comments[row] = (token.string.lstrip("#").strip(), alone)
    return comments


def field_docs(cls: type) -> list[FieldDoc]:
    """Every field of a config dataclass with the comments around it in the source."""
    source = textwrap.dedent(inspect.getsource(cls))
    comments = _comments_by_line(source)
    class_node = ast.parse(source).body[0]
    docs: list[FieldDoc] = []
    group: str | None = None
    for node in class_node.body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        # The comment block right above the field (no blank line in between), read upwards.
        block: list[str] = []
        row = node.lineno - 1
        while row >= 1 and row in comments and comments[row][1]:
            block.insert(0, comments[row][0])
            row -= 1
        text = " ".join(block)
        heading = _GROUP.match(text)
        if heading:
            group, text = clean(heading.group(1)), ""
        elif text:
            # A block that opens with a one- or two-word sentence ("Planning.", "Speed (...).") starts a
            # group; the rest of the block describes the field below it.
            first, _, rest = text.partition(". ")
            if len(re.sub(r"\([^)]*\)", "", first).rstrip(".").split()) <= 2:
                group, text = clean(first).rstrip("."), rest
        inline = comments.get(node.end_lineno)
        parts = []
        if inline and not inline[1]:
            # The comment after the field first (often the valid values), then the block above it.
            parts.append(inline[0] if not text or inline[0].endswith((".", ";", ":")) else inline[0] + ".")
        if text:
            parts.append(text)
        docs.append(FieldDoc(node.target.id, clean(" ".join(parts)), group))
    return docs


@cache
def setting_descriptions() -> dict[str, str]:
    """``{"section.key": description}`` of every setting of the config's dataclasses."""
    import drago.config as config

    out = {}
    for section, cls in config.SECTION_CLASSES.items():
        out.update({f"{section}.{doc.name}": doc.description for doc in field_docs(cls)})
    return out


def describe_all(plugins: bool = True) -> list[tuple[str, str, object, str]]:
    """(key, type, default, description) of every setting, plug-in methods' own included."""
    import drago.config as config

    described = setting_descriptions()
    rows = [(key, kind, default, described.get(key, "")) for key, kind, default in config.describe_settings()]
    if plugins:
        config.load_method_plugins()
        for method, declared in config.METHOD_SETTINGS.items():
            rows += [(f"method.{name}", f"{s.kind.__name__}, {method} only", s.default, s.description)
                     for name, s in declared.items()]
    return rows
