"""The documentation site builds without a warning, and its settings reference covers every setting."""

from __future__ import annotations

import html
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from drago.config import describe_settings

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("mkdocs") is None,
    reason="mkdocs is not installed (it comes with the docs extra: pip install -e '.[docs]'; scripts/setup.sh installs it)",
)


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site built once with `mkdocs build --strict`: any warning (a broken link or anchor, a page
    missing from the nav, a docstring the API reference cannot render) fails the build."""
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    # No --quiet: it lowers the log level below the warnings that --strict counts, and a broken anchor passed.
    result = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict",
                             "--config-file", str(ROOT / "mkdocs.yml"), "--site-dir", str(out)],
                            cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, f"mkdocs build --strict failed:\n{result.stdout}\n{result.stderr}"
    return out


def _cells(page: Path) -> set[str]:
    """The text of every code span in a table cell of a built page."""
    text = page.read_text(encoding="utf-8")
    return {html.unescape(code) for code in re.findall(r"<td><code>(.*?)</code>", text)}


@pytest.mark.slow
def test_site_builds_strictly(site):
    for page in ("index.html", "getting-started.html", "results.html", "benchmarks.html",
                 "reference/settings.html", "reference/api.html"):
        assert (site / page).is_file(), page


@pytest.mark.slow
def test_settings_reference_lists_every_setting(site):
    cells = _cells(site / "reference" / "settings.html")
    missing = [key for key, _, _ in describe_settings() if key not in cells]
    assert not missing, f"settings missing from the generated settings page: {missing}"
    assert "spec §" not in (site / "reference" / "settings.html").read_text(encoding="utf-8")


@pytest.mark.slow
def test_settings_reference_shows_each_default(site):
    text = (site / "reference" / "settings.html").read_text(encoding="utf-8")
    rows = {html.unescape(m.group(1)): html.unescape(m.group(2))
            for m in re.finditer(r"<td><code>([a-z_]+(?:\.[a-z_]+)+)</code></td>\s*<td><code>.*?</code></td>\s*"
                                 r"<td><code>(.*?)</code></td>", text)}
    assert rows["agent.tdmpc.mlp_dim"] == "512"
    assert rows["env.tasks"] == "[room1, room2, room3, room4]"
    assert rows["agent.tdmpc.lr_final"] == "null"
    assert rows["agent.tdmpc.use_crelu"] == "true"


@pytest.mark.slow
def test_api_reference_renders_every_listed_module(site):
    text = (site / "reference" / "api.html").read_text(encoding="utf-8")
    listed = re.findall(r"^::: ([\w.]+)", (ROOT / "docs" / "reference" / "api.md").read_text(), re.M)
    assert listed
    for module in listed:
        assert f'id="{module}"' in text, module


def test_pages_cite_the_paper_not_an_internal_spec():
    pages = [p for p in (ROOT / "docs").rglob("*.md")] + [ROOT / "README.md"]
    offenders = [str(p.relative_to(ROOT)) for p in pages if re.search(r"spec §|DRAGO_SPEC", p.read_text())]
    assert not offenders, offenders


@pytest.mark.slow
def test_the_api_page_documents_each_name_once_per_object(site):
    """A name drago.api re-exports is documented under its own module only (Domain appeared twice)."""
    page = (site / "reference" / "api.html").read_text(encoding="utf-8")
    anchors = re.findall(r'id="(drago\.(?:api|config|envs)\.[A-Za-z_]+)"', page)
    names = [a.rsplit(".", 1)[1] for a in anchors]
    # load_config and plugin_problems are two functions each: drago.api's wraps the module's
    twice = {n for n in names if names.count(n) > 1} - {"load_config", "plugin_problems"}
    assert not twice, f"documented twice: {sorted(twice)}"
