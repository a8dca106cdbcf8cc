"""MkDocs hook: the settings reference, generated at build time from drago/config.py.

``docs/reference/settings.md`` holds only an introduction and two markers; this hook replaces them:

* ``<!-- drago:settings -->`` with one table per config section (env, agent, train, method, transfer):
  every setting's key, type and default from ``drago.config.describe_settings()``, and its description
  from the comments beside and above the dataclass field (``drago.settings_docs``, which ``drago list
  --settings`` prints too);
* ``<!-- drago:presets -->`` with what each preset YAML in drago/presets changes from those defaults.

So the page cannot drift from the code: a new setting, a changed default or comment shows up at the
next ``mkdocs build``. tests/test_docs.py builds the site and checks every setting is on the page.
"""

from __future__ import annotations

import importlib
import inspect
import logging
import re
import sys
from pathlib import Path
from typing import Any

log = logging.getLogger("mkdocs.hooks.settings_page")

PAGE = "reference/settings.md"
SETTINGS_MARKER = "<!-- drago:settings -->"
PRESETS_MARKER = "<!-- drago:presets -->"


def _docs_module():
    # The descriptions' one owner is drago.settings_docs, which `drago list --settings` prints too.
    return importlib.import_module("drago.settings_docs")


def field_docs(cls: type):
    return _docs_module().field_docs(cls)


def _clean(text: str) -> str:
    return _docs_module().clean(text)


def _config_module():
    # import_module, not `from drago import config`: the latter asks the package for an attribute first,
    # and drago's lazy public API would import the whole trainer to answer it.
    return importlib.import_module("drago.config")


def _value(value: Any) -> str:
    """A default as one would write it in a preset or an override."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    return str(value)


def _cell(text: str) -> str:
    """Comment text for a table cell, Markdown-safe outside its `code` spans."""
    # Python-Markdown's tables never split a row at a pipe inside a code span, and would show a
    # backslash there literally, so pipes are escaped outside code spans only.
    pieces = re.split(r"(`[^`]*`)", text)
    for i in range(0, len(pieces), 2):
        pieces[i] = pieces[i].replace("<", "&lt;").replace(">", "&gt;").replace("*", "\\*").replace("|", "\\|")
    return "".join(pieces) or "—"


def _code(text: str) -> str:
    return f"`{text}`"


def _readers_line(section: str) -> str:
    """Who reads a kind's or a method's section, from the registries (empty for the five main sections)."""
    parts = section.split(".")
    if len(parts) != 2:
        return ""
    if parts[0] == "agent":
        return f"Read when `agent.kind={parts[1]}`; a run of another kind refuses it on the command line."
    continual = importlib.import_module("drago.continual")
    readers = [name for name in continual.available_methods()
               if parts[1] in continual.get_method(name).reads]
    return ("Read by " + ", ".join(f"`{name}`" for name in readers)
            + "; another method refuses it on the command line.") if readers else ""


def settings_markdown() -> str:
    config_module = _config_module()

    described = {key: (type_name, default) for key, type_name, default in config_module.describe_settings()}
    out: list[str] = []
    seen: set[str] = set()
    for section, cls in config_module.SECTION_CLASSES.items():
        summary = _clean(inspect.cleandoc(cls.__doc__ or "").split("\n\n")[0].replace("\n", " "))
        level = "##" if "." not in section else "###"
        anchor = section.replace(".", "-")
        out += [f"{level} `{section}`: {cls.__name__} {{#{anchor}}}", "", summary, ""]
        readers = _readers_line(section)
        if readers:
            out += [readers, ""]
        group: str | None = None
        table_open = False
        for doc in field_docs(cls):
            key = f"{section}.{doc.name}"
            if key in config_module.SECTION_CLASSES:
                continue  # a subsection: its own table follows
            if key not in described:
                log.warning("settings page: %s is a field of %s but describe_settings() does not list it",
                            key, cls.__name__)
                continue
            seen.add(key)
            if doc.group != group or not table_open:
                if doc.group != group and doc.group:
                    out += ["", f"**{doc.group}**", ""]
                group = doc.group
                out += ["| setting | type | default | what it does |", "|---|---|---|---|"]
                table_open = True
            type_name, default = described[key]
            out.append(f"| {_code(key)} | {_code(type_name)} | {_code(_value(default))} | {_cell(doc.description)} |")
        out.append("")
    for key in described:
        if key not in seen:
            log.warning("settings page: describe_settings() lists %s, which no config dataclass field documents", key)
    return "\n".join(out)


def _presets_dir() -> Path:
    from importlib import resources

    return Path(str(resources.files("drago") / "presets"))


def _read_preset(directory: Path, name: str) -> tuple[dict[str, dict[str, Any]], str | None]:
    import yaml

    data = yaml.safe_load((directory / f"{name}.yaml").read_text()) or {}
    base = data.pop("base", None)
    merged: dict[str, dict[str, Any]] = {}
    if base is not None:
        merged = {section: dict(values) for section, values in _read_preset(directory, base)[0].items()}
    for section, values in data.items():
        if isinstance(values, dict):
            merged.setdefault(section, {}).update(_flatten(values))
    return merged, base


def _flatten(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A section's settings with its subsections' under dotted names (``tdmpc.horizon``)."""
    out: dict[str, Any] = {}
    for name, value in values.items():
        if isinstance(value, dict) and name != "options":
            out.update(_flatten(value, f"{prefix}{name}."))
        else:
            out[f"{prefix}{name}"] = value
    return out


def presets_markdown() -> str:
    config_module = _config_module()

    directory = _presets_dir()
    names = sorted(p.stem for p in directory.glob("*.yaml"))
    if not names:
        log.warning("settings page: no preset YAML files found in %s", directory)
        return ""
    order = {"minigrid": 0, "minigrid-cpu": 1, "smoke": 2}
    names.sort(key=lambda n: (order.get(n, 3), n))
    defaults = {key: default for key, _, default in config_module.describe_settings()}
    resolved = {name: _read_preset(directory, name) for name in names}
    changed: dict[str, dict[str, Any]] = {}
    for name, (values, _) in resolved.items():
        for section, settings in values.items():
            for setting, value in settings.items():
                key = f"{section}.{setting}"
                if key not in defaults:
                    log.warning("settings page: preset %s sets unknown setting %s", name, key)
                    continue
                default = defaults[key]
                same = (list(value) == list(default)) if isinstance(default, tuple) and isinstance(value, list) \
                    else value == default
                if not same:
                    changed.setdefault(key, {})[name] = value
    keys = [key for key in defaults if key in changed]
    out = ["| setting | default | " + " | ".join(f"`{n}`" for n in names) + " |",
           "|---|---|" + "---|" * len(names)]
    out.append("| *based on* | | " + " | ".join(f"`{resolved[n][1]}`" if resolved[n][1] else "" for n in names) + " |")
    for key in keys:
        cells = [_code(_value(changed[key][n])) if n in changed[key] else "" for n in names]
        anchor = key.rpartition(".")[0].replace(".", "-")
        out.append(f"| [{_code(key)}](#{anchor}) | {_code(_value(defaults[key]))} | " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def on_config(config, **kwargs):
    # The hook imports drago; make the checkout importable even where it is not installed.
    root = str(Path(config.config_file_path).resolve().parent)
    if root not in sys.path:
        sys.path.insert(0, root)
    return config


def on_page_markdown(markdown: str, page, config, files, **kwargs) -> str:
    if page.file.src_uri != PAGE:
        return markdown
    for marker in (SETTINGS_MARKER, PRESETS_MARKER):
        if marker not in markdown:
            log.warning("settings page: %s lacks the marker %s", PAGE, marker)
    return (markdown.replace(SETTINGS_MARKER, settings_markdown())
            .replace(PRESETS_MARKER, presets_markdown()))
