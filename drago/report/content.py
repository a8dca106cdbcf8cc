"""A report's content as data: tables, figures and notes, built once and rendered to HTML and Markdown."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Table:
    key: str
    title: str
    caption: str
    columns: tuple[str, ...]
    rows: list[tuple[str, ...]]


@dataclass(frozen=True)
class Figure:
    key: str
    title: str
    caption: str
    png: bytes
    filename: str


@dataclass(frozen=True)
class Notes:
    key: str
    title: str
    caption: str
    items: list[str]


@dataclass
class Findings:
    """What the report could not show, and how it got what it shows."""

    missing: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


Section = Table | Figure | Notes
