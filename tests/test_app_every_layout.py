"""Every page on every layout: GardensPoint as traversal folders and in each layout ``example_layouts`` writes.

One dataset value reaches every page whatever the layout, so each page runs on each with
no error and no exception, and none says it shows only some layouts.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from streamlit.testing.v1 import AppTest

from test_app import assert_clean, fresh_caches, navigation_mode, page  # noqa: F401
from vpr_explorer.app import ENTRY
from vpr_explorer.data.example_layouts import write_gardens_point_layouts

pytestmark = pytest.mark.realdata

TIMEOUT = 180
PAGES = ("places", "thresholds", "inspector", "evaluation", "sweep", "playback")
LAYOUTS = ("traversals", "database-queries", "vpr-bench", "traversal-positions", "manifest")


@pytest.fixture(scope="module")
def sources(data_root, tmp_path_factory) -> dict[str, Path]:
    written = write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path_factory.mktemp("every_layout"))
    return {"traversals": data_root / "GardensPointWalking", **written}


def opened(source: Path) -> AppTest:
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)
    at.query_params.update(source=str(source), descriptor="pixels")
    return at.run()


def _said(at: AppTest) -> str:
    return " ".join(str(x.value) for x in [*at.warning, *at.info, *at.markdown, *at.caption])


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("name", PAGES)
def test_every_page_opens_every_layout(sources, layout, name):
    at = opened(sources[layout])
    assert_clean(at)
    at = page(at, name)
    assert_clean(at)
    said = _said(at)
    for refusal in ("shows aligned traversal", "supports traversal", "only for traversal", "open it"):
        assert refusal not in said, said
