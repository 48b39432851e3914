"""The page scripts hold no bare expression Streamlit would draw: its "magic" writes any string (or value) standing
alone as a statement on the page, so an attribute docstring in a page script shows above the page's title."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PAGES = sorted((Path(__file__).resolve().parents[1] / "vpr_explorer" / "app" / "pages").glob("*.py"))


def bare_values(tree: ast.Module) -> list[int]:
    """Line numbers of expression statements that are not calls, at the top level or in its with/if/for/try blocks
    (Streamlit runs those; a function's body is not drawn), the module docstring excepted."""
    body = tree.body[1:] if ast.get_docstring(tree) is not None else tree.body
    found: list[int] = []

    def walk(statements: list[ast.stmt]) -> None:
        for node in statements:
            if isinstance(node, ast.Expr) and not isinstance(node.value, (ast.Call, ast.Await, ast.Yield)):
                found.append(node.lineno)
            elif not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                for field in ("body", "orelse", "finalbody"):
                    walk(getattr(node, field, []) or [])
                for handler in getattr(node, "handlers", []) or []:
                    walk(handler.body)

    walk(body)
    return found


def test_a_stray_string_is_found():
    tree = ast.parse('"""Doc."""\nimport streamlit as st\nX = 1\n"""About X."""\nst.title("t")\n'
                     'with st.sidebar:\n    X\ndef f():\n    """Not drawn."""\n')
    assert bare_values(tree) == [4, 7]


def test_every_page_script_is_read():
    assert {p.stem for p in PAGES} >= {"home", "places", "thresholds", "inspector", "evaluation", "playback", "sweep"}


@pytest.mark.parametrize("script", PAGES, ids=[p.stem for p in PAGES])
def test_no_page_script_draws_a_stray_value(script):
    lines = bare_values(ast.parse(script.read_text(encoding="utf-8")))
    assert not lines, f"{script.name}: lines {lines} stand alone and Streamlit would draw them; make them comments"
