"""docs/wiring.md's examples run as shown: each ```python block on its own, its asserts checked."""

from __future__ import annotations

import re
import runpy
from pathlib import Path

import pytest

PAGE = Path(__file__).resolve().parent.parent / "docs" / "wiring.md"
BLOCKS = re.findall(r"```python\n(.*?)```", PAGE.read_text(encoding="utf-8"), re.S)


def test_the_page_has_its_examples():
    assert len(BLOCKS) >= 5


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_each_example_runs_as_shown(index, tmp_path):
    # from a file of its own, as a user's script: Retriever reads an untyped step's returns from its source
    script = tmp_path / f"wiring_example_{index}.py"
    script.write_text(BLOCKS[index], encoding="utf-8")
    runpy.run_path(str(script), run_name=f"wiring_example_{index}")
