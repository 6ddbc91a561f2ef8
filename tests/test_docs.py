"""The generated reference in docs/cli.md and docs/api.md is current: the pages read as plain
Markdown (the README says so), so the text kept in them must be what the parsers and the OpenAPI
document give now (`make reference` writes it anew)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parent.parent / "docs"


def _reference():
    spec = importlib.util.spec_from_file_location("docs_reference", DOCS / "hooks" / "reference.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("page", ["cli.md", "api.md"])
def test_the_generated_reference_in_the_page_is_current(page):
    reference = _reference()
    text = (DOCS / page).read_text(encoding="utf-8")
    assert reference.PAGES[page] in text and reference.END in text  # the text is in the page itself
    assert reference.filled(text) == text, f"docs/{page} is stale: run `make reference`"
    generated = text.split(reference.PAGES[page], 1)[1]
    assert generated.count("\n") > 40  # and it is the reference, not an empty block


def test_the_api_page_says_how_hyperparameters_are_shaped():
    text = (DOCS / "api.md").read_text(encoding="utf-8")
    assert '"hyperparameters": {"mappo": {"lr": 0.0003' in text and "| masac | `episodes`" in text
