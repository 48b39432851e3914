"""The tables of the README and the docs are what ``vpr-explorer evaluate`` and ``vpr-explorer acceptance`` print, digit for digit.

Every fenced block of README.md and of each ``docs/*.md`` page (``pages()``) that holds
lines starting with ``$ vpr-explorer evaluate`` or ``$ vpr-explorer acceptance`` is read as
commands, each followed by the lines it printed (up to a blank line, the next ``$`` line or
the end of the block). Each command is run with ``python -m vpr_explorer.cli``
(``$VPR_EXPLORER_DATA`` substituted), after the block's other ``$ python …`` lines above it
(e.g. the one that writes the example layouts), and the page's lines are compared with
what it prints:

- a table with its ``----`` separator line is a whole table: header, separator and every
  row, in order, exactly as printed;
- a table without one is an excerpt: each row shown (and the header, when shown) must equal
  the printed row of the same label. A row's label is its first cell, or its first two
  (``θ_p(k) weighted (margin)  +1.00``) where the first alone repeats in the printed table;
- a line outside the tables (a dataset's description) must equal the printed line that
  starts with the same word.

Printed lines a page leaves out (the ``protocol:`` line, notes, timings) are not looked at.
A command shown on several pages runs once.

Run as a script it checks every page (exit 1 on a difference); ``--write`` rewrites those
lines of each page with what the commands print now, keeping excerpts as excerpts::

    VPR_EXPLORER_DATA=../shared/datasets python tests/readme_tables.py [--write]

``tests/test_readme_tables.py`` runs the check under pytest.
"""

from __future__ import annotations

import argparse
import functools
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
PROMPTS = ("$ vpr-explorer evaluate", "$ vpr-explorer acceptance")
DATA_VARIABLE = "$VPR_EXPLORER_DATA"
_SEPARATOR = re.compile(r"^-+(  +-+)*$")
# Columns are joined by two spaces or more, and a label cell holds single spaces only. Data
# cells such as "97.1 ±  3.3" split in two, but only the label cells, which come first, are keys.
_CELL_GAP = re.compile(r"\s{2,}")


def cells(line: str) -> list[str]:
    return _CELL_GAP.split(line.strip())


@dataclass
class Command:
    """One ``$ vpr-explorer evaluate`` (or ``acceptance``) line of a page and the output lines shown under it.

    ``line`` is the command's 1-based line number in ``page`` (a path relative to the
    repository root, e.g. ``docs/results.md``); ``output`` maps each shown line's 1-based
    number to its text, without the block's indentation; ``setup`` are the block's other
    ``$`` commands above it.
    """

    line: int
    text: str
    indent: str
    setup: tuple[str, ...] = ()
    output: dict[int, str] = field(default_factory=dict)
    page: str = "README.md"


@dataclass
class Table:
    """A table the command printed: its header, separator and row lines."""

    header: str
    separator: str
    rows: list[str]

    def keyed_rows(self) -> dict[tuple[str, ...], str]:
        """Each row by its label: its first cell, or first two cells where the first repeats."""
        firsts = [cells(r)[0] for r in self.rows]
        return {tuple(cells(r)[: 1 if firsts.count(f) == 1 else 2]): r for r, f in zip(self.rows, firsts)}


def pages() -> list[Path]:
    """The pages whose tables are checked: README.md, then every ``docs/*.md`` by name."""
    return [README, *sorted(DOCS.glob("*.md"))]


def page_name(path: Path) -> str:
    """``path`` as messages name it: relative to the repository root."""
    return path.relative_to(ROOT).as_posix()


def find_commands(text: str, page: str = "README.md") -> list[Command]:
    """Every ``$ vpr-explorer evaluate`` (or ``acceptance``) line inside a fenced block of ``page``, with the output lines below it."""
    commands: list[Command] = []
    in_block, current, setup = False, None, []
    for number, raw in enumerate(text.splitlines(), start=1):
        stripped = raw.strip()
        if stripped.startswith("```"):
            in_block, current, setup = not in_block, None, []
        elif not in_block:
            continue
        elif stripped.startswith(PROMPTS):
            current = Command(number, stripped[2:], raw[: len(raw) - len(raw.lstrip())], tuple(setup), page=page)
            commands.append(current)
        elif stripped.startswith("$ "):
            setup.append(stripped[2:])
            current = None
        elif not stripped:
            current = None
        elif current is not None:
            current.output[number] = raw[len(current.indent):]
    return commands


def argv(command: str, data_root: Path) -> list[str]:
    """A page's command as arguments for this interpreter, ``$VPR_EXPLORER_DATA`` replaced.

    ``vpr-explorer …`` becomes ``python -m vpr_explorer.cli …`` and ``python …`` this
    interpreter; nothing else is run.
    """
    words = shlex.split(command.replace(DATA_VARIABLE, str(data_root)), comments=True)
    if words[0] == "vpr-explorer":
        return [sys.executable, "-m", "vpr_explorer.cli", *words[1:]]
    if words[0] in ("python", "python3"):
        return [sys.executable, *words[1:]]
    raise ValueError(f"command {command!r}: only vpr-explorer and python commands are run")


def _stdout(args: list[str], where: str) -> str:
    r = subprocess.run(args, capture_output=True, text=True, timeout=900, env=dict(os.environ))
    if r.returncode != 0:
        raise RuntimeError(f"{where} exited {r.returncode}:\n{r.stderr[-2000:]}")
    return r.stdout


@functools.cache
def _set_up(command: str, data_root: Path) -> None:
    """Run a block's preparing command once per process."""
    _stdout(argv(command, data_root), f"setup `{command}`")


_PRINTED: dict[tuple[str, tuple[str, ...], Path], str] = {}


def run(command: Command, data_root: Path) -> str:
    """What the command prints on stdout (progress bars go to stderr), its block's setup run first.

    The same command with the same setup runs once per process, whichever page shows it.
    """
    key = (command.text, command.setup, Path(data_root))
    if key not in _PRINTED:
        for setup in command.setup:
            _set_up(setup, data_root)
        _PRINTED[key] = _stdout(argv(command.text, data_root), f"{command.page}:{command.line}: `{command.text}`")
    return _PRINTED[key]


def printed_tables(stdout: str) -> list[Table]:
    """The tables in a command's output: a header line, a ``----`` line, then rows up to a blank line."""
    lines = stdout.splitlines()
    tables = []
    for i, line in enumerate(lines):
        if i and _SEPARATOR.match(line):
            rows = []
            for row in lines[i + 1:]:
                if not row.strip():
                    break
                rows.append(row)
            tables.append(Table(lines[i - 1], line, rows))
    return tables


def expected_lines(command: Command, stdout: str) -> tuple[dict[int, list[str]], list[str]]:
    """``(line number -> the printed lines it should be, problems)`` for the page's lines under ``command``.

    Each shown line should be one printed line, except in a whole table of another length than
    printed: its surplus lines should be none, and its last line carries the rows it lacks.
    A problem is a shown line with no single counterpart in the output.
    """
    tables = printed_tables(stdout)
    in_tables = {line for t in tables for line in (t.header, t.separator, *t.rows)}
    others = [line for line in stdout.splitlines() if line.strip() and line not in in_tables]
    shown = list(command.output.items())
    header_at = next((i for i, (_, line) in enumerate(shown)
                      if any(cells(line)[0] == cells(t.header)[0] for t in tables)), None)
    candidates = tables
    if header_at is not None:
        candidates = [t for t in tables if cells(t.header)[0] == cells(shown[header_at][1])[0]]
    expected: dict[int, list[str]] = {}
    problems: list[str] = []

    def missing(n: int, what: str, line: str) -> None:
        problems.append(f"{command.page}:{n}: {what} of `{command.text}` carries the label of {line.strip()!r}")

    whole = any(_SEPARATOR.match(line.strip()) for _, line in shown)
    if whole and (header_at is None or len(candidates) != 1):
        problems.append(f"{command.page}:{command.line}: a whole table under `{command.text}` whose header matches "
                        f"{len(candidates) if header_at is not None else 'no'} printed tables")
        return expected, problems
    for i, (n, line) in enumerate(shown):
        if whole and i >= header_at:
            break
        if i == header_at:
            expected[n] = [candidates[0].header]
            continue
        rows = [row for t in candidates for key, row in t.keyed_rows().items() if tuple(cells(line)[: len(key)]) == key]
        if len(rows) == 1:
            expected[n] = rows
            continue
        if rows:
            missing(n, f"more than one printed row ({len(rows)})", line)
            continue
        first = line.split()[0]
        same = [o for o in others if o.split()[0] == first]
        if not same:
            missing(n, "no printed row or line", line)
            continue
        expected[n] = [max(same, key=lambda o: len(os.path.commonprefix([o, line])))]
    if whole:
        table = candidates[0]
        printed = [table.header, table.separator, *table.rows]
        numbers = [n for n, _ in shown[header_at:]]
        expected.update({n: [p] for n, p in zip(numbers, printed)})
        expected.update({n: [] for n in numbers[len(printed):]})  # the page's lines beyond the printed table
        expected[numbers[-1]] = expected[numbers[-1]] + printed[len(numbers):]  # printed rows the page lacks
    return expected, problems


def compare(command: Command, stdout: str) -> list[str]:
    """One message per line of the page under ``command`` that is not what it printed."""
    expected, problems = expected_lines(command, stdout)
    for n, printed in expected.items():
        if [command.output[n]] != printed:
            now = "\n    ".join(map(repr, printed)) or "(nothing: the printed table is shorter)"
            problems.append(f"{command.page}:{n}: the page shows\n    {command.output[n]!r}\n"
                            f"where `{command.text}` prints\n    {now}")
    return problems


def rewrite(text: str, fixes: dict[int, list[str]]) -> str:
    """``text`` with each 1-based line number in ``fixes`` replaced by its lines (none: removed)."""
    lines = [[line] for line in text.split("\n")]
    for n, new in fixes.items():
        lines[n - 1] = new
    return "\n".join(line for group in lines for line in group)


def main(argv_: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true",
                        help="rewrite the output lines of README.md and docs/*.md with what is printed now")
    parser.add_argument("--data", type=Path, default=os.environ.get("VPR_EXPLORER_DATA"),
                        help="the datasets folder (default $VPR_EXPLORER_DATA)")
    args = parser.parse_args(argv_)
    if args.data is None:
        parser.error("set VPR_EXPLORER_DATA or pass --data")
    problems: list[str] = []
    status = 0
    for path in pages():
        name = page_name(path)
        text = path.read_text()
        fixes: dict[int, list[str]] = {}
        for command in find_commands(text, name):
            print(f"{name}:{command.line}: {command.text}", file=sys.stderr)
            stdout = run(command, args.data)
            expected, unmatched = expected_lines(command, stdout)
            problems += unmatched if args.write else compare(command, stdout)
            fixes.update({n: [command.indent + p for p in printed] for n, printed in expected.items()
                          if [command.output[n]] != printed})
        if args.write and fixes:
            old = text.splitlines()
            for n in sorted(fixes):
                print(f"{name}:{n}:\n  - {old[n - 1].strip()}" + "".join(f"\n  + {p.strip()}" for p in fixes[n]))
            if path.read_text() != text:
                print(f"{path} changed while the commands ran: nothing written; run again")
                status = 1
                continue
            path.write_text(rewrite(text, fixes))
            print(f"rewrote {len(fixes)} lines of {path}")
    for problem in problems:
        print(problem)
    return 1 if problems else status


if __name__ == "__main__":
    sys.exit(main())
