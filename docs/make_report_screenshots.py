"""Screenshots of a study report's sections, as a reader's browser shows them, for the docs pages.

Builds the report from committed records (``drago report RECORDS``), keeps the chosen sections of its HTML
page (the page's own styles, tables and figures, nothing redrawn), renders each selection in headless
Chromium and crops the blank margin below it:

    .venv/bin/python docs/make_report_screenshots.py --records results/grid [--methods drago continual ...]
        [--only NAME ...] [--in-fresh-clone]

writes ``docs/report-records-top.png`` (the report's top: its runs and final returns) and
``docs/report-records-components.png`` (which part forgot, task × stage; the swap test; what each method stores and
spends); ``--only NAME ...`` writes only those. With ``--in-fresh-clone`` it first clones the repository's
committed state into a temporary folder, sets it up there with ``scripts/setup.sh`` and draws from that
clone's records: the report a new user gets from the committed records alone, nothing of this working tree.
Needs ``chromium`` on the PATH (``scripts/setup.sh`` installs Debian's package).
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

DOCS = Path(__file__).resolve().parent
#: file name -> (the report's section ids, in order; whether the page's title and summary line come first)
SHOTS = {
    "report-records-top.png": (("runs", "returns"), True),
    "report-records-components.png": (("components-figure", "swap-test", "costs"), False),
}
# Wide enough for the widest table, which may overflow the page's text column; the margin is cropped.
WIDTH, MAX_HEIGHT, MARGIN = 2000, 6000, 24


def sections_page(html: str, ids: tuple[str, ...], with_title: bool) -> str:
    """The report page with only the sections ``ids`` in its body (and its title and summary line if asked)."""
    head = html[:html.index("<body>") + len("<body>")]
    found = {m.group(1): m.group(0) for m in re.finditer(r'<section id="([^"]+)">.*?</section>', html, re.S)}
    missing = [i for i in ids if i not in found]
    if missing:
        raise SystemExit(f"the report has no section {', '.join(missing)}: are the records' diagnostics there?")
    title = ""
    if with_title:
        title = re.search(r"<h1>.*?</h1>\s*<p class=\"meta\">.*?</p>", html, re.S).group(0)
    return head + title + "".join(found[i] for i in ids) + "</body></html>"


def screenshot(page: Path, out: Path, browser: str, profile: Path) -> None:
    raw = page.with_suffix(".png")
    subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    f"--user-data-dir={profile}", "--virtual-time-budget=5000", f"--screenshot={raw}",
                    f"--window-size={WIDTH},{MAX_HEIGHT}", page.resolve().as_uri()],
                   capture_output=True, timeout=180, check=True)
    image = Image.open(raw).convert("RGB")
    ink = (np.asarray(image) < 250).any(axis=2)
    rows, columns = np.flatnonzero(ink.any(axis=1)), np.flatnonzero(ink.any(axis=0))
    if rows.size == 0:
        raise SystemExit(f"{out.name}: the browser drew a blank page")
    box = (max(0, columns[0] - MARGIN), 0, min(image.width, columns[-1] + MARGIN), min(image.height, rows[-1] + MARGIN))
    image.crop(box).save(out, optimize=True)
    print(f"wrote {out} ({box[2] - box[0]}x{box[3]})")


def in_fresh_clone(args: argparse.Namespace) -> int:
    """This script, run in a fresh clone of the repository's committed state, writing into ``args.out``."""
    root = DOCS.parent
    try:
        records = args.records.resolve().relative_to(root)
    except ValueError:
        raise SystemExit(f"--in-fresh-clone draws committed records: {args.records} is outside the repository")
    with tempfile.TemporaryDirectory() as tmp:
        clone = Path(tmp) / "drago"
        subprocess.run(["git", "clone", "--quiet", str(root), str(clone)], check=True)
        subprocess.run(["bash", "scripts/setup.sh"], cwd=clone, check=True)
        argv = [".venv/bin/python", "docs/make_report_screenshots.py", "--records", str(records),
                "--out", str(args.out.resolve()), "--only", *args.only]
        if args.methods:
            argv += ["--methods", *args.methods]
        return subprocess.run(argv, cwd=clone).returncode


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", type=Path, default=DOCS.parent / "results" / "grid",
                        help="folder of records (default results/grid)")
    parser.add_argument("--methods", nargs="+", default=None,
                        help="only these methods' records (RECORDS/METHOD), in this order (default: all)")
    parser.add_argument("--out", type=Path, default=DOCS, help="folder of the screenshots (default docs/)")
    parser.add_argument("--only", nargs="+", choices=sorted(SHOTS), default=sorted(SHOTS), metavar="NAME",
                        help=f"write only these screenshots (default all: {', '.join(sorted(SHOTS))})")
    parser.add_argument("--in-fresh-clone", action="store_true",
                        help="clone the repository's committed state, set it up and draw from the clone's records")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.in_fresh_clone:
        return in_fresh_clone(args)
    sources = [args.records] if args.methods is None else [args.records / method for method in args.methods]
    missing = [str(source) for source in sources if not source.is_dir()]
    if missing:
        raise SystemExit(f"no records folder {', '.join(missing)}: check --records and --methods")
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        raise SystemExit("no chromium on the PATH: run scripts/setup.sh, or install Debian's chromium package")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        subprocess.run([sys.executable, "-m", "drago", "report", *map(str, sources), "--out", str(folder / "report")],
                       check=True, stdout=subprocess.DEVNULL)
        html = (folder / "report" / "report.html").read_text(encoding="utf-8")
        for name in args.only:
            ids, with_title = SHOTS[name]
            page = folder / f"{Path(name).stem}.html"
            page.write_text(sections_page(html, ids, with_title), encoding="utf-8")
            screenshot(page, args.out / name, browser, folder / "profile")
    return 0


if __name__ == "__main__":
    sys.exit(main())
