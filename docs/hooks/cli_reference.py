"""MkDocs hook: the command-line page, written from ``vpr-explorer``'s argparse parsers at build time.

``docs/cli.md`` holds an introduction and the line :data:`MARKER`; :func:`on_page_markdown`
replaces that line with :func:`cli_reference`, read from ``vpr_explorer.cli.parser.build_parser()``:

- a table of the commands, each with its one line of help (what ``vpr-explorer --help`` lists);
- one section per command (anchor ``#evaluate``), in the parser's order: its one line of
  help, its ``usage:`` line (as ``--help`` prints it, wrapped at :data:`USAGE_WIDTH` columns)
  and every argument in the parser's order, as a definition list: the argument as ``--help``
  spells it (anchor ``#evaluate--dataset``, ``#fetch-name`` for a positional one), its help,
  its choices and its default.

``-h/--help`` and the arguments ``--help`` hides (help ``argparse.SUPPRESS``) are left out. A
default is stated as the command's ``--help`` states it (``cli.common.HelpFormatter``): none
for a required option, a switch (listed as "off unless given") or an option whose default is
None (its help says what happens then), nor where the help itself writes ``%(default)s``.

Help texts are plain text with reStructuredText code (````vpr-explorer evaluate````) and
Markdown code (```demo```): both become Markdown code spans, as do option names
(``--hub-size``) and environment variables (``$VPR_EXPLORER_DATA``) in the text; every other
character that Markdown or HTML would read (``*``, ``_``, ``<``, ``[``, ``{``…) is escaped, so
a help text reads on the page as written, with its first letter a capital. A ``cli.md`` without the marker fails the build, so the page
cannot silently lose its reference.
"""

from __future__ import annotations

import argparse
import copy
import html
import re

from mkdocs.exceptions import PluginError

#: the line of ``docs/cli.md`` that the generated reference replaces
MARKER = "<!-- cli-reference -->"
#: the page the hook writes into, relative to ``docs_dir``
PAGE = "cli.md"
#: the width the ``usage:`` blocks are wrapped at (argparse's own wrapping, independent of the terminal)
USAGE_WIDTH = 100

#: a code span in a help text: ``reStructuredText`` or `Markdown`
_CODE = re.compile(r"``(.+?)``|`([^`]+)`")
#: the characters escaped in help text outside code spans (Python-Markdown's backslash escapes)
_MARKDOWN_SPECIAL = re.compile(r"([\\`*_{}\[\]()#+!|])")
#: in plain help text, an option (``--hub-size``) or an environment variable (``$VPR_EXPLORER_DATA``): shown as code
_NAME = re.compile(r"(?<![\w-])(--[a-z][a-z0-9-]*|\$[A-Z][A-Z0-9_]*)")


def on_page_markdown(markdown: str, page, config, files) -> str:
    """MkDocs ``on_page_markdown`` event: :data:`MARKER` in ``cli.md`` replaced by :func:`cli_reference`.

    Raises:
        PluginError: ``cli.md`` does not hold the marker on a line of its own.
    """
    if page.file.src_uri != PAGE:
        return markdown
    lines = markdown.splitlines()
    if lines.count(MARKER) != 1:
        raise PluginError(f"docs/{PAGE} must hold the line {MARKER!r} once, where the hook writes the "
                          "command reference; add it below the page's introduction")
    return "\n".join(cli_reference() if line == MARKER else line for line in lines) + "\n"


def commands() -> list[tuple[str, str, argparse.ArgumentParser]]:
    """``vpr-explorer``'s commands in the parser's order: ``(name, one line of help, its parser)``."""
    from vpr_explorer.cli.parser import build_parser

    parser = build_parser()
    (subparsers,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    helps = {action.dest: action.help or "" for action in subparsers._choices_actions}
    return [(name, helps.get(name, ""), sub) for name, sub in subparsers.choices.items()]


def documented_arguments(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The arguments of ``parser`` the page lists: all but ``-h/--help`` and those ``--help`` hides."""
    return [a for a in parser._actions
            if not isinstance(a, argparse._HelpAction) and a.help != argparse.SUPPRESS]


def anchor(command: str, action: argparse.Action) -> str:
    """The page anchor of a command's argument: ``evaluate--dataset``, or ``fetch-name`` for a positional one."""
    if action.option_strings:
        return command + max(action.option_strings, key=len)
    return f"{command}-{action.dest.replace('_', '-')}"


def markdown_text(text: str) -> str:
    """A help text as Markdown: its code spans, options and ``$VARIABLES`` as Markdown code, every other
    special character escaped, the first letter a capital."""
    if text[:1].islower():
        text = text[0].upper() + text[1:]
    out, end = [], 0
    for match in _CODE.finditer(text):
        out.append(_plain(text[end:match.start()]))
        out.append(_code(match.group(1) if match.group(1) is not None else match.group(2)))
        end = match.end()
    out.append(_plain(text[end:]))
    return "".join(out)


def cli_reference() -> str:
    """The generated Markdown: the table of commands, then one section per command."""
    rows = commands()
    out = ["| command | what it does |", "|---|---|"]
    out += [f"| [`{name}`](#{name}) | {markdown_text(help)} |" for name, help, _ in rows]
    for name, help, parser in rows:
        out += ["", f"## {name}", "", markdown_text(help) + ".", "", "```text", _usage(parser).rstrip(), "```", ""]
        arguments = documented_arguments(parser)
        if not arguments:
            out.append("No options besides `-h`, `--help`.")
            continue
        for action in arguments:
            out += [f"`{_invocation(parser, action)}` {{ #{anchor(name, action)} }}",
                    ":   " + _description(parser, action), ""]
    return "\n".join(out)


def _plain(text: str) -> str:
    """Text outside a code span: its option and variable names as code, the rest escaped."""
    parts = _NAME.split(text)  # odd items are the names
    return "".join(_code(part) if i % 2 else _escaped(part) for i, part in enumerate(parts))


def _escaped(text: str) -> str:
    """Plain text that Markdown and HTML show as written."""
    return _MARKDOWN_SPECIAL.sub(r"\\\1", html.escape(text, quote=False))


def _code(text: str) -> str:
    """``text`` as one Markdown code span, fenced by more backticks than it holds in a row."""
    fence = "`" * (max((len(r) for r in re.findall(r"`+", text)), default=0) + 1)
    pad = " " if text.startswith("`") or text.endswith("`") else ""
    return f"{fence}{pad}{text}{pad}{fence}"


def _usage(parser: argparse.ArgumentParser) -> str:
    """``parser``'s ``usage:`` line as ``--help`` prints it, wrapped at :data:`USAGE_WIDTH`."""
    formatter = parser.formatter_class(prog=parser.prog, width=USAGE_WIDTH)
    formatter.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups)
    return formatter.format_help()


def _invocation(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    """How ``--help`` spells the argument, with the placeholder name where it would list the choices."""
    formatter = argparse.HelpFormatter(prog=parser.prog)
    shown = copy.copy(action)
    if shown.choices is not None and shown.metavar is None:
        shown.metavar = shown.dest.upper()
    if not shown.option_strings:
        return formatter._format_args(shown, shown.dest)
    if shown.nargs == 0:
        return ", ".join(shown.option_strings)
    args = formatter._format_args(shown, shown.dest.upper())
    return ", ".join(f"{option} {args}" for option in shown.option_strings)


def _description(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    """The argument's help (``%(default)s`` and the like filled in), its choices and its default, as Markdown."""
    from vpr_explorer.cli.common import shown

    text = argparse.HelpFormatter(prog=parser.prog)._expand_help(action) if action.help else ""
    parts = [markdown_text(text.rstrip(".")) + "." if text else ""]
    if action.choices is not None:
        parts.append("One of " + ", ".join(_code(str(c)) for c in action.choices) + ".")
    if action.required and action.option_strings:
        parts.append("Required.")
    elif action.nargs == 0 and action.default is False:
        parts.append("Off unless given.")
    elif (action.default is not None and action.default is not argparse.SUPPRESS and action.option_strings
          and "%(default)" not in (action.help or "")):
        parts.append("Default: " + _code(shown(action.default)) + ".")
    return " ".join(p for p in parts if p)
