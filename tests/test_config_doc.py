"""docs/CONFIG.md lists every option of every section, generated from the config's own field docs."""

import dataclasses
from pathlib import Path

from formation.config import GameConfig
from formation.recipe.config import SECTIONS, field_docs, markdown

DOC = Path(__file__).resolve().parent.parent / "docs" / "CONFIG.md"
REGENERATE = "python -m formation.recipe.config --markdown > docs/CONFIG.md"


def test_docs_config_md_is_in_sync_with_the_config():
    assert DOC.read_text() == markdown(), f"docs/CONFIG.md is out of date; regenerate it: {REGENERATE}"


def test_every_option_of_every_section_has_a_doc():
    for kind in (GameConfig, *SECTIONS.values()):
        docs = field_docs(kind)
        assert set(docs) == {f.name for f in dataclasses.fields(kind)}
        undocumented = [name for name, doc in docs.items() if not doc]
        assert not undocumented, f"{kind.__name__}: {undocumented} have no comment to document them"
