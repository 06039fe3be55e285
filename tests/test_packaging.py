"""What pip installs: the distribution's name is ours (``retriever`` on PyPI is another project,
"Data Retriever"), and every install line the project prints or documents names it."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

from retriever.log.format import DISTRIBUTION, PACKAGES

ROOT = Path(__file__).resolve().parent.parent
#: `pip install 'NAME[extra]'` as written in prose, code and rich markup (`\[`)
INSTALL_WITH_EXTRA = re.compile(r"pip install '?([A-Za-z0-9_.-]+)\\*\[(\w+)")


def test_the_distribution_is_retriever_robotics_and_imports_as_retriever():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["name"] == DISTRIBUTION == "retriever-robotics"
    assert PACKAGES["retriever"] == DISTRIBUTION  # the version a log records is this distribution's


def test_every_install_line_with_an_extra_names_our_distribution_and_one_of_its_extras():
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    files = [ROOT / "README.md", *(ROOT / "docs").rglob("*.md"), *(ROOT / "benchmarks").rglob("*.md"),
             *(ROOT / "benchmarks").rglob("*.py"), *(ROOT / "retriever").rglob("*.py"), *(ROOT / "agents").rglob("*.py")]
    found = [(path.relative_to(ROOT), *m.groups()) for path in files
             for m in INSTALL_WITH_EXTRA.finditer(path.read_text(encoding="utf-8"))]
    assert len(found) >= 8, found  # README, docs/dora.md and the hints in retriever/
    assert [f for f in found if f[1] != DISTRIBUTION or f[2] not in extras] == []
