"""The command line is a thin layer over the public API (drago.api): it imports nothing else of drago."""

from __future__ import annotations

import ast
from pathlib import Path

import drago.cli
from drago import api


def test_the_cli_imports_only_the_public_api():
    tree = ast.parse(Path(drago.cli.__file__).read_text())
    private = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "drago":
            if node.module != "drago.api" or any(alias.name not in api.__all__ for alias in node.names):
                private.append(f"line {node.lineno}: from {node.module} import "
                               + ", ".join(alias.name for alias in node.names))
        elif isinstance(node, ast.Import) and any(alias.name.startswith("drago") for alias in node.names):
            private.append(f"line {node.lineno}: import " + ", ".join(alias.name for alias in node.names))
    assert not private, "the CLI reaches past drago.api:\n" + "\n".join(private)
