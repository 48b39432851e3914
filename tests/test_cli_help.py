"""``vpr-explorer [COMMAND] --help`` as a newcomer reads it: plain text, and each default said in full.

Every command's help is printed through ``run_command`` (argparse exits 0 after printing);
help strings may share reStructuredText with docstrings, and the terminal shows it with
single backticks. ``--cache-dir`` says both where the cache is without it: the variable and,
when that is unset too, ``settings.cache_root()``'s folder.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from vpr_explorer.cli.common import HelpFormatter
from vpr_explorer.cli.parser import COMMANDS, run_command
from vpr_explorer.settings import CACHE_ENV, cache_root

#: reStructuredText a terminal should not show: a double-backtick literal or a role such as :func:`x`
RST = re.compile(r"``|:[a-z]+(?::[a-z]+)?:`")
COMMAND_NAMES = [name for name, _, _ in COMMANDS]


def help_text(capsys, *argv: str) -> str:
    """What ``vpr-explorer ARGV --help`` prints, whitespace runs as one space."""
    with pytest.raises(SystemExit) as exit_:
        run_command([*argv, "--help"])
    assert exit_.value.code == 0
    return " ".join(capsys.readouterr().out.split())


@pytest.mark.parametrize("argv", [[], *([name] for name in COMMAND_NAMES)], ids=["vpr-explorer", *COMMAND_NAMES])
def test_help_prints_no_restructuredtext(capsys, argv):
    text = help_text(capsys, *argv)
    assert text.startswith("usage: vpr-explorer")
    markup = RST.search(text)
    assert markup is None, text[max(0, markup.start() - 80):markup.start() + 120]


def test_the_formatter_prints_literals_and_roles_with_single_backticks():
    parser = argparse.ArgumentParser(prog="x", formatter_class=HelpFormatter,
                                     description="Run ``vpr-explorer evaluate --help`` first.",
                                     epilog="See :func:`~vpr_explorer.pipeline.run_protocol` and :mod:`vpr_explorer`.")
    parser.add_argument("--k", type=int, default=3, help="the ``k`` of :data:`RUNS`")
    text = " ".join(parser.format_help().split())
    assert "Run `vpr-explorer evaluate --help` first." in text
    assert "See `vpr_explorer.pipeline.run_protocol` and `vpr_explorer`." in text
    assert "the `k` of `RUNS` (default: 3)" in text
    assert not RST.search(text)


def test_cache_dir_help_names_the_variable_and_the_folder_without_it(capsys, monkeypatch):
    monkeypatch.delenv(CACHE_ENV, raising=False)
    fallback = "~/" + cache_root().relative_to(Path.home()).as_posix()  # settings' folder when the variable is unset
    with_option = 0
    for name in COMMAND_NAMES:
        text = help_text(capsys, name)
        if "--cache-dir" not in text:
            continue
        with_option += 1
        said = re.search(r"--cache-dir CACHE_DIR (.*?\))", text.split("options:")[-1]).group(1)
        assert f"${CACHE_ENV}" in said and fallback in said, (name, said)
    assert with_option >= 5  # evaluate, acceptance, failures, record, sweep, bench, extract take it
