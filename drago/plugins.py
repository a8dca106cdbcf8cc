"""Plug-ins from installed packages: the one loader behind every entry-point group drago reads.

A package lists its methods under the entry-point group ``drago.methods`` and its domains under
``drago.domains`` (docs: Extending drago). Each registry hands :func:`load_entry_points` its group and a
function that registers what one entry point loads. A plug-in that fails (its import raises, it loads the
wrong kind of object, its name is taken) is skipped with one warning line on stderr naming the entry point
and its package, and drago runs on with the rest; the registries keep the failures for ``drago list``.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from importlib import metadata
from typing import Any


def one_line(text: object, limit: int = 300) -> str:
    """``text`` on one line (whitespace runs collapsed), cut to ``limit`` characters."""
    line = " ".join(str(text).split())
    return line if len(line) <= limit else line[:limit - 3] + "..."


@dataclass(frozen=True)
class PluginProblem:
    """A plug-in that was skipped.

    Attributes:
        kind: What the group registers: ``"method"`` or ``"domain"``.
        entry_point: ``name = value`` of the entry point.
        package: The distribution package that declares it.
        error: What went wrong, one line.
    """

    kind: str
    entry_point: str
    package: str
    error: str

    def __str__(self) -> str:
        return f"{self.kind} plug-in '{self.entry_point}' of package '{self.package}' skipped: {self.error}"


def package_of(entry: Any) -> str:
    """The distribution that declares an entry point, or ``"unknown package"``."""
    dist = getattr(entry, "dist", None)
    return getattr(dist, "name", None) or "unknown package"


def load_entry_points(group: str, kind: str, register: Callable[[Any], None], *,
                      plain_errors: tuple[type[BaseException], ...] = (),
                      entries: Callable[..., Iterable[Any]] | None = None) -> list[PluginProblem]:
    """Call ``register(entry_point)`` for every entry point of ``group``; return and announce the failures.

    Args:
        group: The entry-point group, e.g. ``"drago.methods"``.
        kind: The word the warning uses for what the group holds (``"method"``).
        register: Loads one entry point and registers what it gives; raises on any problem.
        plain_errors: drago's own error types, whose message already says what to fix: shown without the
            exception's type name.
        entries: ``importlib.metadata.entry_points`` (looked up at call time, so tests may patch it).
    """
    problems: list[PluginProblem] = []
    try:
        listed = list((entries or metadata.entry_points)(group=group))
    except Exception as err:  # noqa: BLE001 - a broken metadata folder on sys.path must not stop drago
        listed = []
        problems.append(PluginProblem(kind, "(all)", "(metadata)",
                                      f"cannot list entry points: {type(err).__name__}: {one_line(err, 160)}"))
    for entry in listed:
        try:
            register(entry)
        except Exception as err:  # noqa: BLE001 - a plug-in's failure never takes drago down with it
            text = one_line(err, 200) if isinstance(err, plain_errors) else \
                f"{type(err).__name__}{': ' + one_line(err, 200) if str(err).strip() else ''}"
            problems.append(PluginProblem(kind, f"{entry.name} = {entry.value}", package_of(entry), text))
    for problem in problems:
        print(f"drago: warning: {problem}", file=sys.stderr, flush=True)
    return problems
