"""History lives in CHANGELOG.md only: the code's words and the documentation say what is, not how it came to be.

Scanned, with where each hit is:

* the documentation: ``README.md`` and every ``docs/**/*.md`` but ``docs/changelog.md`` (which
  shows ``CHANGELOG.md``);
* the code: every docstring (a string statement: module, class, function and attribute
  docstrings, read with :mod:`ast`), every comment (consecutive comment lines read as one
  text, with :mod:`tokenize`) and every ``help=``, ``description=`` and ``epilog=`` string
  literal of ``vpr_explorer/``, ``app.py``, ``pages/`` and ``benchmarks/``;
* the command line: the ``vpr-explorer`` parsers built from ``vpr_explorer.cli.parser``,
  every action's help and every parser's description and epilog (defaults filled in, as
  ``--help`` prints them).

A hit is one of:

* a work-item number: "issue N", "stop N", "§N";
* a commit of this repository: a hex string of 7 to 40 characters that git resolves to a
  commit in this checkout (an upstream repository's commit, which it does not, is fine);
* talk of what changed when (:data:`HISTORY`): "as before", "no longer", "previously",
  "before this change", "the pass now runs", "a helper added", ... The list keeps to
  phrasings the code's own subject does not use: Streamlit *sessions* and *helper*
  functions are the code's words, so only "previous session", "session 3" and "a helper
  wrote" are hits.
"""

from __future__ import annotations

import argparse
import ast
import io
import re
import subprocess
import tokenize
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: folders whose Python files are scanned (with ``app.py``)
CODE_FOLDERS = ("vpr_explorer", "pages", "benchmarks")
#: the one Markdown file that may tell history: the site's page that shows CHANGELOG.md
CHANGELOG_PAGE = Path("docs") / "changelog.md"
#: keyword arguments whose string literals are help texts (argparse's and the benchmarks' parsers)
HELP_KEYWORDS = ("help", "description", "epilog")


def _phrase(words: str) -> str:
    """A phrase as a pattern that matches it across line breaks and indentation."""
    return r"\b" + r"\s+".join(words.split()) + r"\b"


#: work-item numbers: name -> pattern (case-insensitive)
NUMBERS = {
    "issue N": r"\bissues?\s*#?\s*\d+",
    "stop N": r"\bstop\s*#?\s*\d+|\bstops\s+\d+\s*(?:[-–]|and|to)\s*\d+",
    "§N": r"§\s*\d+",
}

#: talk of what changed when: name -> pattern (case-insensitive). "session" and "helper" alone
#: are the code's words (Streamlit sessions, helper functions), so only their history senses are here.
HISTORY = {
    "as before": _phrase("as before"),
    "as at stop/commit": r"\bas\s+at\s+(?:stop|commit|issue)\b",
    "previously": _phrase("previously"),
    "formerly": _phrase("formerly"),
    "no longer": _phrase("no longer"),
    "used to": r"\b(?:it|they|this|that|which|we|what)\s+used\s+to\b|\bused\s+to\s+be\b",
    "was fixed": r"\b(?:was|were|got|has\s+been|have\s+been)\s+fixed\b",
    "we changed": r"\bwe\s+(?:added|fixed|changed|removed|renamed|moved|rewrote|replaced|dropped|introduced|made)\b",
    "a helper did": r"\bhelpers?\s+(?:wrote|added|fixed|found|changed|measured|moved|removed|rewrote|ran)\b"
                    r"|\bhelper\s+sessions?\b",
    "an earlier session": r"\b(?:previous|earlier|last|prior)\s+sessions?\b|\bsession\s+\d+\b",
    "this stop": r"\b(?:this|that|previous|earlier|last|next)\s+stop\b",
    "before/after this change": r"\b(?:before|after|since)\s+(?:this|that)\s+(?:change|stop|commit|session|fix)\b",
    "the old code": r"\b(?:the\s+)?(?:previous|old|earlier)\s+code\b|\bthe\s+code\s+before\b"
                    r"|\bthe\s+old\s+(?:path|sample|behaviou?r|version|default|name|format)\b",
    "until now": r"\b(?:until|till|up\s+to)\s+now\b",
    "since then": _phrase("since then"),
    "now does": r"\bnow\s+(?!and\b)[a-z]+s\b|\bnow\s+with\b",
    "was renamed": r"\b(?:was|were)\s+renamed\b|\brenamed\s+from\b",
}

#: a hex string that could abbreviate a commit (lower case, as git prints them)
HEX = re.compile(r"(?<![0-9A-Za-z_])[0-9a-f]{7,40}(?![0-9A-Za-z_])")


@dataclass(frozen=True)
class Text:
    """One scanned text: where it is (a file and the line it starts on, or a ``--help``) and its words."""

    where: str
    line: int
    text: str

    def at(self, offset: int) -> str:
        """Where the character at ``offset`` is: ``file:line``."""
        return f"{self.where}:{self.line + self.text.count(chr(10), 0, offset)}" if self.line else self.where


# --------------------------------------------------------------------------- what is scanned


def code_files() -> list[Path]:
    """``app.py`` and every Python file under :data:`CODE_FOLDERS`."""
    files = [ROOT / "app.py"]
    for folder in CODE_FOLDERS:
        files += sorted((ROOT / folder).rglob("*.py"))
    return [f for f in files if f.is_file() and "__pycache__" not in f.parts]


def doc_files() -> list[Path]:
    """``README.md`` and every ``docs/**/*.md`` but the changelog's page."""
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return [f for f in files if f.is_file() and f.relative_to(ROOT) != CHANGELOG_PAGE]


def python_texts(path: Path, root: Path = ROOT) -> Iterator[Text]:
    """The docstrings, comment blocks and help literals of one Python file (named from ``root``)."""
    name = str(path.relative_to(root))
    source = path.read_text(encoding="utf-8")
    block: list[str] = []
    start = last = 0
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type != tokenize.COMMENT:
            continue
        row = token.start[0]
        if block and row != last + 1:
            yield Text(name, start, "\n".join(block))
            block = []
        if not block:
            start = row
        block.append(token.string.lstrip("#:").strip())
        last = row
    if block:
        yield Text(name, start, "\n".join(block))
    for node in ast.walk(ast.parse(source, filename=name)):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            yield Text(name, node.lineno, node.value.value)
        elif isinstance(node, ast.Call):
            for keyword in node.keywords:
                if keyword.arg in HELP_KEYWORDS:
                    for part in ast.walk(keyword.value):
                        if isinstance(part, ast.Constant) and isinstance(part.value, str):
                            yield Text(name, part.lineno, part.value)


def help_texts() -> Iterator[Text]:
    """Every text ``vpr-explorer [COMMAND] --help`` prints, one per parser, as it prints it."""
    from vpr_explorer.cli.parser import build_parser

    def walk(parser: argparse.ArgumentParser, name: str) -> Iterator[Text]:
        parts = [parser.format_help(), parser.description or "", parser.epilog or ""]
        parts += [action.help for action in parser._actions if isinstance(action.help, str)]
        yield Text(f"{name} --help", 0, "\n".join(parts))
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for choice in action._choices_actions:  # the command list's one-line helps
                    yield Text(f"{name} --help", 0, choice.help or "")
                for command, sub in action.choices.items():
                    yield from walk(sub, f"{name} {command}")

    yield from walk(build_parser(), "vpr-explorer")


def code_texts() -> list[Text]:
    """Every scanned text of the code and the command line."""
    return [t for path in code_files() for t in python_texts(path)] + list(help_texts())


def doc_texts() -> list[Text]:
    """Every scanned Markdown file, whole."""
    return [Text(str(path.relative_to(ROOT)), 1, path.read_text(encoding="utf-8")) for path in doc_files()]


# --------------------------------------------------------------------------- what is a hit


def pattern_hits(texts: Iterable[Text], patterns: dict[str, str]) -> list[str]:
    """``where: [name] …context…`` for every match of every pattern, case-insensitive."""
    compiled = {name: re.compile(p, re.IGNORECASE) for name, p in patterns.items()}
    hits = []
    for t in texts:
        for name, pattern in compiled.items():
            for m in pattern.finditer(t.text):
                context = " ".join(t.text[max(0, m.start() - 60):m.end() + 60].split())
                hits.append(f"{t.at(m.start())}: [{name}] …{context}…")
    return sorted(set(hits))


def git_commits(candidates: Iterable[str]) -> set[str]:
    """The candidates that git resolves to a commit of this checkout (``<hex>^{commit}``)."""
    candidates = sorted(set(candidates))
    if not candidates:
        return set()
    out = subprocess.run(["git", "cat-file", "--batch-check"], cwd=ROOT, capture_output=True, text=True,
                         input="".join(f"{c}^{{commit}}\n" for c in candidates), check=True).stdout.splitlines()
    assert len(out) == len(candidates), out
    return {c for c, line in zip(candidates, out) if line.endswith(" commit") or " commit " in line}


def hash_hits(texts: Iterable[Text]) -> list[str]:
    """``where: [commit] …context…`` for every hex string that is a commit of this repository."""
    texts = list(texts)
    found = [(t, m) for t in texts for m in HEX.finditer(t.text)]
    commits = git_commits(m.group() for _, m in found)
    return sorted({f"{t.at(m.start())}: [commit {m.group()}] …{' '.join(t.text[max(0, m.start() - 60):m.end() + 60].split())}…"
                   for t, m in found if m.group() in commits})


def in_git_checkout() -> bool:
    try:
        return subprocess.run(["git", "rev-parse", "--verify", "--quiet", "HEAD^{commit}"], cwd=ROOT,
                              capture_output=True).returncode == 0
    except OSError:
        return False


# --------------------------------------------------------------------------- the checks

AREAS = {"code": code_texts, "docs": doc_texts}


@pytest.mark.parametrize("area", AREAS)
def test_no_issue_stop_or_section_numbers(area):
    hits = pattern_hits(AREAS[area](), NUMBERS)
    assert not hits, "work-item numbers belong in CHANGELOG.md:\n" + "\n".join(hits)


@pytest.mark.parametrize("area", AREAS)
def test_no_talk_of_what_changed_when(area):
    hits = pattern_hits(AREAS[area](), HISTORY)
    assert not hits, "say what is; what changed belongs in CHANGELOG.md:\n" + "\n".join(hits)


@pytest.mark.parametrize("area", AREAS)
def test_no_commit_of_this_repository(area):
    if not in_git_checkout():
        pytest.skip("not a git checkout: no commits to look the hex strings up in")
    hits = hash_hits(AREAS[area]())
    assert not hits, "this repository's commits belong in CHANGELOG.md (or nowhere):\n" + "\n".join(hits)


# --------------------------------------------------------------------------- the scanner itself


@pytest.mark.parametrize("text, kind", [
    ("the columns headed SkylakeX, stop 20", "stop N"),
    ("Stop 20 (library change 4.11 → 1.78 s)", "stop N"),
    ("in stops 18–20", "stop N"),
    ("(issue 7)", "issue N"),
    ("see issue #12", "issue N"),
    ("as §3 says", "§N"),
    ("read as before", "as before"),
    ("the pass no\n    longer computes", "no longer"),
    ("a run of the code before this stop", "this stop"),
    ("before this change, the counts", "before/after this change"),
    ("which stats._centred_gram now uses too", "now does"),
    ("`--phases` runs, now with the automatic θ's work", "now does"),
    ("ran while this helper session's tests", "a helper did"),
    ("the previous session measured", "an earlier session"),
    ("it used to score pairs", "used to"),
    ("keeps the old sample", "the old code"),
    ("Since then, with the same arithmetic", "since then"),
])
def test_the_scanner_finds_history(text, kind):
    hits = pattern_hits([Text("x.py", 1, text)], {**NUMBERS, **HISTORY})
    assert any(f"[{kind}]" in h for h in hits), hits


@pytest.mark.parametrize("text", [
    "Two first callers (two Streamlit sessions) wait for one build",
    "a session's link overrides it; the session's runs, oldest first",
    "Streamlit helpers of the explorer app; public helpers",
    "meets 1e-6 in ~50 steps and 300 stops 22 of 1,117 early",
    "the descriptors used to rank the database; the seed used to draw the splits",
    "every image now a cache hit; a core idle now and then",
    "a new dataset drops the descriptor file of the old one",
    "an earlier commit of this repository, as the benchmark's argument",
    "the last line does not cancel",
])
def test_the_scanner_spares_the_codes_own_words(text):
    assert pattern_hits([Text("x.py", 1, text)], {**NUMBERS, **HISTORY}) == []


def test_the_scanner_reads_comments_docstrings_and_help(tmp_path):
    path = tmp_path / "m.py"
    path.write_text('"""Module: as before."""\n'
                    "x = 1  # the pass no\n"
                    "# longer runs (stop 3)\n"
                    "def f():\n"
                    '    """Issue 4."""\n'
                    "p.add_argument('--a', help='e.g. ' 'previously')\n"
                    "s = 'stop 9 in a plain string is no docstring'\n")
    hits = pattern_hits(python_texts(path, tmp_path), {**NUMBERS, **HISTORY})
    assert [h.split(" …")[0] for h in hits] == ["m.py:1: [as before]", "m.py:2: [no longer]", "m.py:3: [stop N]",
                                               "m.py:5: [issue N]", "m.py:6: [previously]"], hits


def test_the_scanner_knows_this_repositorys_commits():
    if not in_git_checkout():
        pytest.skip("not a git checkout")
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout.strip()
    upstream = "31fc6d1d7f8f155c3029d8f85b931ecc0c7bbfaf"  # a commit of rerun-io/rerun, not of this repository
    texts = [Text("x.md", 1, f"built at {head[:7]}; full {head}; upstream {upstream}; file alexnet-owt-7be5be79.pth")]
    assert {h.split(": ")[1].split("]")[0] for h in hash_hits(texts)} == {f"[commit {head[:7]}", f"[commit {head}"}
