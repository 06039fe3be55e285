"""Hashes of flow modules' files (retriever/code.py): found the way the import system would load
them, without running anything."""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path

import pytest

from retriever.code import code_hashes, code_mismatches, module_file


@pytest.fixture
def package(tmp_path: Path, monkeypatch):
    """``trap_pkg.flows`` on sys.path, whose package raises if it is ever executed."""
    (tmp_path / "trap_pkg").mkdir()
    (tmp_path / "trap_pkg" / "__init__.py").write_text("raise RuntimeError('imported')\n")
    (tmp_path / "trap_pkg" / "flows.py").write_text("raise RuntimeError('imported')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path / "trap_pkg"
    assert "trap_pkg" not in sys.modules and "trap_pkg.flows" not in sys.modules


def test_a_module_of_a_package_is_found_and_hashed_without_running_it(package: Path):
    assert module_file("trap_pkg.flows") == str(package / "flows.py")
    assert code_hashes(["trap_pkg.flows", "trap_pkg"]) == {
        "trap_pkg": hashlib.sha256((package / "__init__.py").read_bytes()).hexdigest(),
        "trap_pkg.flows": hashlib.sha256((package / "flows.py").read_bytes()).hexdigest()}


def test_a_module_that_is_not_there_has_no_file_and_no_hash(package: Path):
    assert module_file("trap_pkg.nothing") is None
    assert module_file("no_such_top_level") is None
    assert code_hashes(["trap_pkg.nothing", "__main__"]) == {}


def test_mismatches_name_the_module_and_both_hashes(package: Path):
    here = hashlib.sha256((package / "flows.py").read_bytes()).hexdigest()
    assert code_mismatches({"trap_pkg.flows": here}) == []
    assert code_mismatches({"trap_pkg.flows": "0" * 64, "trap_pkg.gone": "1" * 64}) == [
        f"the code of module trap_pkg.flows differs from the run's (run sha256 {'0' * 64}, here {here} "
        f"in {package / 'flows.py'})",
        f"module trap_pkg.gone is not found here (the run's has sha256 {'1' * 64})"]
