"""Rendering a report's content: a self-contained HTML page (inline CSS, figures as data URIs) and Markdown."""

from __future__ import annotations

import base64
import html

from drago.report.content import Figure, Section, Table

REPORT_HTML = "report.html"
REPORT_MD = "report.md"


_CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 24px auto;
       max-width: 1240px; padding: 0 16px; color: #1d1d1f; line-height: 1.4; }
h1 { font-size: 26px; margin-bottom: 4px; } h2 { font-size: 19px; margin-top: 30px;
     border-bottom: 1px solid #ddd; padding-bottom: 4px; }
p.meta, p.caption { color: #555; font-size: 13px; margin: 4px 0 10px; }
nav a { margin-right: 14px; font-size: 14px; }
table { border-collapse: collapse; font-size: 13px; margin: 6px 0 8px; }
th, td { border: 1px solid #d6d6d6; padding: 3px 8px; text-align: left; white-space: nowrap; }
th { background: #eef1f5; } tr:nth-child(even) td { background: #fafafa; }
td.path { font-family: ui-monospace, Menlo, monospace; font-size: 12px; }
img { max-width: 100%; height: auto; border: 1px solid #e3e3e3; }
ul.notes li { font-size: 13px; margin: 3px 0; }
"""


# Lets a headless browser (and its test) see that every figure decoded and drew.
_IMAGES_LOADED_JS = """
window.addEventListener("load", function () {
  var images = Array.prototype.slice.call(document.images);
  document.body.dataset.imagesTotal = images.length;
  document.body.dataset.imagesLoaded =
    images.filter(function (img) { return img.complete && img.naturalWidth > 0; }).length;
});
"""


def render_html(title: str, meta: str, sections: list[Section]) -> str:
    e = html.escape
    parts = [f"<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>{e(title)}</title>",
             f"<style>{_CSS}</style>\n</head>\n<body>", f"<h1>{e(title)}</h1>", f"<p class=\"meta\">{e(meta)}</p>",
             "<nav>" + "".join(f"<a href=\"#{s.key}\">{e(s.title)}</a>" for s in sections) + "</nav>"]
    for section in sections:
        parts.append(f"<section id=\"{section.key}\">\n<h2>{e(section.title)}</h2>")
        parts.append(f"<p class=\"caption\">{e(section.caption)}</p>")
        if isinstance(section, Table) and not section.rows:
            parts.append("<p class=\"caption\"><em>No data in these runs yet.</em></p>")
        elif isinstance(section, Table):
            head = "".join(f"<th>{e(c)}</th>" for c in section.columns)
            body = "\n".join("<tr>" + "".join(
                f"<td class=\"path\">{e(v)}</td>" if c == "run directory" else f"<td>{e(v)}</td>"
                for c, v in zip(section.columns, row)) + "</tr>" for row in section.rows)
            parts.append(f"<table id=\"table-{section.key}\">\n<thead><tr>{head}</tr></thead>\n"
                         f"<tbody>\n{body}\n</tbody>\n</table>")
        elif isinstance(section, Figure):
            data = base64.b64encode(section.png).decode("ascii")
            parts.append(f"<img id=\"figure-{section.key}\" alt=\"{e(section.title)}\" "
                         f"src=\"data:image/png;base64,{data}\">")
        else:
            parts.append("<ul class=\"notes\">\n" + "\n".join(f"<li>{e(i)}</li>" for i in section.items) + "\n</ul>")
        parts.append("</section>")
    parts.append(f"<script>{_IMAGES_LOADED_JS}</script>\n</body>\n</html>\n")
    return "\n".join(parts)


def _md_cell(value: str) -> str:
    return value.replace("|", "\\|")


def render_markdown(title: str, meta: str, sections: list[Section]) -> str:
    lines = [f"# {title}", "", meta, ""]
    for section in sections:
        lines += [f"## {section.title}", "", section.caption, ""]
        if isinstance(section, Table) and not section.rows:
            lines.append("*No data in these runs yet.*")
        elif isinstance(section, Table):
            lines.append("| " + " | ".join(map(_md_cell, section.columns)) + " |")
            lines.append("|" + "|".join("---" for _ in section.columns) + "|")
            lines += ["| " + " | ".join(map(_md_cell, row)) + " |" for row in section.rows]
        elif isinstance(section, Figure):
            lines.append(f"![{section.title}]({section.filename})")
        else:
            lines += [f"- {item}" for item in section.items]
        lines.append("")
    return "\n".join(lines)
