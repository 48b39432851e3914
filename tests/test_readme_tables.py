"""The ``$ vpr-explorer evaluate`` and ``acceptance`` tables of README.md and docs/*.md are what the command prints now, digit for digit.

The checking is ``tests/readme_tables.py``'s (which also rewrites the pages:
``python tests/readme_tables.py --write``). Each command runs in a subprocess that inherits
the session's descriptor cache, filled first by ``gp_effnet`` and ``gp_pixels``; a command
shown on several pages runs once.
"""

from __future__ import annotations

import pytest

import readme_tables

COMMANDS = [command for path in readme_tables.pages()
            for command in readme_tables.find_commands(path.read_text(), readme_tables.page_name(path))]


def _texts(page: str) -> list[str]:
    return [c.text for c in COMMANDS if c.page == page]


def test_the_readme_shows_the_headline_tables():
    texts = _texts("README.md")
    assert all(c.output for c in COMMANDS), [c.text for c in COMMANDS if not c.output]
    assert any(t.startswith("vpr-explorer evaluate") and "GardensPointWalking" in t and "--protocol" not in t
               for t in texts), texts
    assert any("--protocol open-set" in t for t in texts), texts
    assert any(t.startswith("vpr-explorer acceptance") for t in texts), texts


def test_the_docs_show_every_table():
    results, acceptance, layouts = _texts("docs/results.md"), _texts("docs/acceptance.md"), _texts("docs/layouts.md")
    assert len(results) >= 5 and any("--cross-condition" in t for t in results), results
    assert any("--protocol open-set" in t for t in results) and any("Nordland_64x32" in t for t in results), results
    assert len(acceptance) >= 4 and all(t.startswith("vpr-explorer acceptance") for t in acceptance), acceptance
    assert len(layouts) >= 4 and all(c.setup for c in COMMANDS if c.page == "docs/layouts.md"), layouts


@pytest.mark.realdata
@pytest.mark.parametrize("command", COMMANDS, ids=[f"{c.page}:{c.line}" for c in COMMANDS])
def test_readme_table_is_what_the_command_prints(command, data_root, gp_effnet, gp_pixels):
    problems = readme_tables.compare(command, readme_tables.run(command, data_root))
    assert not problems, (
        "\n".join(problems) + "\nIf the new numbers are right: python tests/readme_tables.py --write, "
        "then update the prose that quotes them"
    )


# --------------------------------------------------------------------------- the checker itself, on made-up output

PRINTED = """protocol: open-set  (dataset=demo, places=15 places)

method                   R@1  accepted
--------------------  ------  --------
image-level baseline    97.1     100.0
global θ, automatic      0.0       0.0

threshold                 k or θ     known R@1
------------------------  ------  ------------
θ_p(k) weighted (margin)   +0.00   98.3 ±  3.9
θ_p(k) weighted (margin)   +1.00   98.1 ±  3.7
global θ, automatic (raw)  1.030    0.0 ±  0.0

(1.2 s)
"""

WHOLE = """\
method                   R@1  accepted
--------------------  ------  --------
image-level baseline    97.1     100.0
global θ, automatic      0.0       0.0"""

EXCERPT = """\
  threshold                 k or θ     known R@1
  θ_p(k) weighted (margin)   +1.00   98.1 ±  3.7
  global θ, automatic (raw)  1.027    0.0 ±  0.0"""


def readme(*blocks: str) -> str:
    return "intro\n\n" + "\n\n".join(f"```\n{b}\n```" for b in blocks) + "\n"


def test_commands_are_found_with_their_lines_indentation_and_setup():
    text = readme("$ vpr-explorer evaluate --dataset demo\n" + WHOLE,
                  "$ python -m prepare --out /tmp/x\n  $ vpr-explorer evaluate --dataset /tmp/x\n" + EXCERPT)
    first, second = readme_tables.find_commands(text)
    assert (first.line, first.text, first.indent, first.setup) == (4, "vpr-explorer evaluate --dataset demo", "", ())
    assert list(first.output) == [5, 6, 7, 8] and first.output[7].startswith("image-level baseline")
    assert second.setup == ("python -m prepare --out /tmp/x",) and second.indent == "  "
    assert second.output[15] == "θ_p(k) weighted (margin)   +1.00   98.1 ±  3.7"


def test_a_whole_table_equal_to_the_output_passes_and_a_changed_digit_is_named():
    (command,) = readme_tables.find_commands(readme("$ vpr-explorer evaluate --dataset demo\n" + WHOLE))
    assert readme_tables.compare(command, PRINTED) == []
    (moved,) = readme_tables.compare(command, PRINTED.replace("97.1", "97.2"))
    assert moved.startswith("README.md:7: the page shows") and "97.2" in moved


def test_a_whole_table_missing_a_printed_row_fails_and_write_adds_it():
    text = readme("$ vpr-explorer evaluate --dataset demo\n" + WHOLE)
    (command,) = readme_tables.find_commands(text)
    longer = PRINTED.replace("global θ, automatic      0.0       0.0",
                             "global θ, automatic      0.0       0.0\nglobal θ, oracle        97.1     100.0")
    (problem,) = readme_tables.compare(command, longer)
    assert problem.startswith("README.md:8:") and "global θ, oracle" in problem
    expected, _ = readme_tables.expected_lines(command, longer)
    fixes = {n: p for n, p in expected.items() if [command.output[n]] != p}
    assert readme_tables.rewrite(text, fixes) == text.replace("0.0       0.0\n", "0.0       0.0\n"
                                                               "global θ, oracle        97.1     100.0\n")


def test_an_excerpt_compares_its_rows_by_label_and_write_keeps_it_an_excerpt():
    text = readme("  $ vpr-explorer evaluate --dataset demo\n" + EXCERPT)
    (command,) = readme_tables.find_commands(text)
    (problem,) = readme_tables.compare(command, PRINTED)  # the automatic θ moved: 1.027 -> 1.030
    assert problem.startswith("README.md:7:") and "1.030" in problem
    expected, problems = readme_tables.expected_lines(command, PRINTED)
    assert problems == [] and expected[6] == ["θ_p(k) weighted (margin)   +1.00   98.1 ±  3.7"]  # not the +0.00 row
    fixes = {n: ["  " + p for p in printed] for n, printed in expected.items() if [command.output[n]] != printed}
    assert readme_tables.rewrite(text, fixes) == text.replace("1.027", "1.030")


def test_a_row_the_command_no_longer_prints_is_named():
    text = readme("$ vpr-explorer evaluate --dataset demo\n" + EXCERPT.replace("+1.00", "+2.00"))
    (command,) = readme_tables.find_commands(text)
    problems = readme_tables.compare(command, PRINTED)
    assert problems[0].startswith("README.md:6: no printed row or line") and "+2.00" in problems[0]


def test_a_docs_pages_problem_names_the_page_and_the_same_command_runs_once(monkeypatch, tmp_path):
    text = readme("$ vpr-explorer evaluate --dataset demo\n" + WHOLE)
    (command,) = readme_tables.find_commands(text, "docs/results.md")
    assert command.page == "docs/results.md"
    (moved,) = readme_tables.compare(command, PRINTED.replace("97.1", "97.2"))
    assert moved.startswith("docs/results.md:7: the page shows")
    calls = []
    monkeypatch.setattr(readme_tables, "_stdout", lambda args, where: calls.append(where) or PRINTED)
    (again,) = readme_tables.find_commands(text, "README.md")
    assert readme_tables.run(command, tmp_path) == readme_tables.run(again, tmp_path) == PRINTED
    assert calls == [f"docs/results.md:4: `{command.text}`"]


def test_the_pages_are_the_readme_and_every_docs_page():
    pages = readme_tables.pages()
    assert pages[0] == readme_tables.README and readme_tables.ROOT / "docs" / "architecture.md" in pages
    assert [readme_tables.page_name(p) for p in pages[1:]] == sorted(
        f"docs/{p.name}" for p in (readme_tables.ROOT / "docs").glob("*.md"))
