"""The documentation site: ``mkdocs build --strict`` succeeds, and what it builds is whole.

The site is built once per module (``python -m mkdocs build --strict`` into a temporary
folder; ``mkdocs.yml`` makes a page missing from the nav, a broken link or a missing anchor a
warning, so a failure there). Then:

- every page of the nav exists under ``docs/``, and every page under ``docs/`` is in the nav;
- the command-line page, written by ``docs/hooks/cli_reference.py``, has a section for every
  command of ``vpr_explorer.cli.parser.build_parser()`` and an entry for every argument of
  each, read from the parsers here, so an option added without reaching the page fails; the
  arguments ``--help`` hides are not on it;
- every ``href`` and ``src`` of every built page but ``404.html`` (whose links start at the
  server's root, since it is shown at any depth) is an http(s) address, an anchor, or a
  relative path to a file inside the site;
- every picture under ``docs/screenshots/`` is shown by the README or a page of the docs.
"""

from __future__ import annotations

import argparse
import html
import importlib.util
import os
import re
import subprocess
import sys
import time
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "mkdocs.yml"
DOCS = ROOT / "docs"


def _hook():
    """``docs/hooks/cli_reference.py`` as a module (it is loaded by MkDocs, not installed)."""
    spec = importlib.util.spec_from_file_location("cli_reference", DOCS / "hooks" / "cli_reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _nav_pages(nav) -> list[str]:
    """The page paths of a MkDocs nav (a list of ``{title: path}`` or ``{title: [sections]}``), in order."""
    pages = []
    for item in nav:
        value = next(iter(item.values())) if isinstance(item, dict) else item
        pages += _nav_pages(value) if isinstance(value, list) else [value]
    return pages


@pytest.fixture(scope="module")
def config():
    from mkdocs.config import load_config

    return load_config(str(CONFIG))


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site as ``mkdocs build --strict`` writes it, in a temporary folder."""
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    start = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(CONFIG),
                          "--site-dir", str(out)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, f"mkdocs build --strict failed:\n{res.stderr[-6000:]}"
    print(f"mkdocs build --strict: {time.perf_counter() - start:.1f} s")
    return out


def test_every_nav_page_exists_and_every_page_is_in_the_nav(config):
    pages = _nav_pages(config.nav)
    assert pages and pages[0] == "index.md" and "cli.md" in pages and "changelog.md" in pages
    assert not [p for p in pages if not (DOCS / p).is_file()]
    on_disk = sorted(str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md"))
    assert sorted(set(pages)) == on_disk
    assert len(pages) == len(set(pages))


def test_the_site_builds_strict(site):
    pages = {p.parent.name for p in site.glob("*/index.html")}
    assert (site / "index.html").is_file() and {"cli", "changelog", "development"} <= pages
    assert not (site / "hooks").exists()  # the hook is the build's code, not a page


def test_the_changelog_page_is_the_changelog(site):
    text = _text((site / "changelog" / "index.html").read_text(encoding="utf-8"))
    lines = [line.strip() for line in (ROOT / "CHANGELOG.md").read_text(encoding="utf-8").splitlines()]
    heading = next(line.lstrip("# ") for line in lines if line.startswith("## "))
    assert heading.replace("[", "").replace("]", "") in text


def test_the_cli_page_lists_every_command_and_argument(site):
    from vpr_explorer.cli.parser import build_parser

    page = (site / "cli" / "index.html").read_text(encoding="utf-8")
    sections = _sections(page)
    (subparsers,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    assert len(subparsers.choices) >= 11
    missing = []
    for name, parser in subparsers.choices.items():
        if name not in sections:
            missing.append(f"section {name}")
            continue
        terms = [_text(t) for t in re.findall(r"<dt\b[^>]*>(.*?)</dt>", sections[name], flags=re.S)]
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            if action.help == argparse.SUPPRESS:
                hidden = [t for t in terms for option in action.option_strings if _names(t, option)]
                assert not hidden, f"{name}: {action.option_strings} is hidden from --help but on the page"
                continue
            if action.option_strings:
                missing += [f"{name} {option}" for option in action.option_strings
                            if not any(_names(t, option) for t in terms)]
            else:
                shown = action.metavar or action.dest
                if not any(re.search(rf"\b{re.escape(str(shown))}\b", t) for t in terms):
                    missing.append(f"{name} {shown}")
    assert not missing, f"not on the command-line page: {missing}"


def test_the_cli_page_shows_code_as_code(site):
    article = _article((site / "cli" / "index.html").read_text(encoding="utf-8"))
    assert "``" not in _text(article)  # reStructuredText code became <code>
    assert "<code>vpr-explorer datasets</code>" in article  # fetch NAME's help: `vpr-explorer datasets`
    assert "<code>--hub-size</code>" in article and "<code>$VPR_EXPLORER_CACHE</code>" in article


def test_help_text_becomes_markdown():
    hook = _hook()
    assert hook.markdown_text("run ``vpr-explorer evaluate --help`` first") == \
        "Run `vpr-explorer evaluate --help` first"
    assert hook.markdown_text("a `demo` route") == "A `demo` route"
    assert hook.markdown_text("with --ray ADDRESS|local") == "With `--ray` ADDRESS\\|local"
    assert hook.markdown_text("DIR/<dataset> (x_y*)") == "DIR/&lt;dataset&gt; \\(x\\_y\\*\\)"
    assert hook.markdown_text("under $VPR_EXPLORER_DATA, 100%") == "Under `$VPR_EXPLORER_DATA`, 100%"
    assert hook.markdown_text("``a `b` c``") == "``a `b` c``"  # a code span holding backticks keeps them


def test_the_cli_page_needs_its_marker():
    from mkdocs.exceptions import PluginError

    hook = _hook()

    class Page:
        class file:
            src_uri = "cli.md"

    with pytest.raises(PluginError, match="cli-reference"):
        hook.on_page_markdown("# Command line\n", Page, None, None)
    text = hook.on_page_markdown(f"# Command line\n\n{hook.MARKER}\n", Page, None, None)
    assert "## evaluate" in text and hook.MARKER not in text


def test_no_page_links_outside_the_site(site):
    bad = []
    # 404.html is the exception by design: a server shows it at any depth, so its links start at the root
    for page in sorted(p for p in site.rglob("*.html") if p != site / "404.html"):
        parser = _Links()
        parser.feed(page.read_text(encoding="utf-8"))
        for link in parser.links:
            parts = urlsplit(link)
            if parts.scheme in ("http", "https") or (not parts.scheme and not parts.netloc and not parts.path):
                continue  # an address on the web, or an anchor on the same page
            if parts.scheme or parts.netloc or parts.path.startswith("/"):
                bad.append(f"{page.relative_to(site)}: {link}")
                continue
            target = (page.parent / unquote(parts.path)).resolve()
            if target.is_dir():
                target = target / "index.html"
            if not target.is_relative_to(site.resolve()) or not target.is_file():
                bad.append(f"{page.relative_to(site)}: {link}")
    assert not bad, bad


def test_every_screenshot_is_shown_somewhere():
    shown = "\n".join(p.read_text(encoding="utf-8") for p in [ROOT / "README.md", *DOCS.rglob("*.md")])
    pictures = sorted((DOCS / "screenshots").rglob("*.png"))
    assert pictures
    unshown = [str(p.relative_to(DOCS)) for p in pictures if f"{p.relative_to(DOCS).as_posix()})" not in shown]
    assert not unshown, f"no page shows {unshown}: show them, or save them with shoot(..., for_docs=False)"


class _Links(HTMLParser):
    """Every ``href`` and ``src`` of an HTML page."""

    def __init__(self) -> None:
        super().__init__()
        self.links: list[str] = []

    def handle_starttag(self, tag, attrs) -> None:
        self.links += [value for name, value in attrs if name in ("href", "src") and value is not None]


def _names(term: str, option: str) -> bool:
    """Whether a definition term (``-o, --out DIR``) names ``option``."""
    return re.search(rf"(^|, ){re.escape(option)}( |,|$)", term) is not None


def _article(page: str) -> str:
    """The page's content: its ``<article>`` element."""
    return page[page.index("<article"):page.index("</article>")]


def _sections(page: str) -> dict[str, str]:
    """The ``<h2 id=...>`` sections of a page's content, by id."""
    parts = re.split(r'<h2 id="([^"]+)"', _article(page))
    return dict(zip(parts[1::2], parts[2::2]))


def _text(fragment: str) -> str:
    """HTML without its tags, entities decoded, whitespace collapsed."""
    return " ".join(html.unescape(re.sub(r"<[^>]+>", " ", fragment)).split())
