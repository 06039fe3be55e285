"""Development effort (paper Appendix F-A): the latency benchmark as a user writes it, counted.

    benchmarks/effort/retriever/latency.py     Retriever: one script (flows, graph, run)
    benchmarks/effort/dora/{pub.py, sub.py, dataflow.yml}   dora-rs, native Python API

Both do the same job: 100 payloads of each size from 64 B to 16 MiB at 20 Hz, from one process
to another, and a CSV row (size, one-way latency) per payload received (the paper's Listings 4-6
do this too; ours drop its unused parts). Lines of code are the lines left without blank lines,
``#`` comments and docstrings (as cloc counts Python); the paper's own counts are printed beside.

    .venv/bin/python benchmarks/effort.py
    # and each runs (a short sweep: POINTS=2):
    POINTS=2 BACKEND=zenoh .venv/bin/python benchmarks/effort/retriever/latency.py   # or BACKEND=dora, inproc
    cd benchmarks/effort/dora && POINTS=2 PATH=$PWD/../../../.venv/bin:$PATH dora run dataflow.yml
"""

from __future__ import annotations

import ast
import io
import tokenize
from pathlib import Path

HERE = Path(__file__).resolve().parent / "effort"
SCRIPTS = {
    "Retriever (ours)": ["retriever/latency.py"],
    "dora-rs (ours)": ["dora/pub.py", "dora/sub.py", "dora/dataflow.yml"],
}
#: the seed paper's Appendix F-A, as published (LoC; files)
PAPER = [("Retriever (paper, Listing 4)", "116", "1"), ("dora-rs (paper, Listings 5-6)", "32 + 53 = 85", "2 + YAML"),
         ("ROS 2 (paper)", "79 + 95 = 174", "4 with build config")]


def code_lines(path: Path) -> int:
    """Lines holding code: not blank, not only a comment, not part of a docstring."""
    text = path.read_text()
    if path.suffix != ".py":
        return sum(1 for line in text.splitlines() if line.strip() and not line.strip().startswith("#"))
    docstrings: set[int] = set()
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(getattr(first, "value", None), ast.Constant) \
                    and isinstance(first.value.value, str):
                docstrings.update(range(first.lineno, first.end_lineno + 1))
    code: set[int] = set()
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type not in (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT,
                            tokenize.ENDMARKER):
            code.update(range(tok.start[0], tok.end[0] + 1))
    return len(code - docstrings)


def main() -> int:
    print("The latency benchmark as a user script: lines of code (no blanks, comments or docstrings) and files")
    print(f"{'':32} {'LoC':>16} {'files':>20}")
    for name, files in SCRIPTS.items():
        counts = [code_lines(HERE / f) for f in files]
        print(f"{name:32} {' + '.join(map(str, counts)) + (f' = {sum(counts)}' if len(counts) > 1 else ''):>16} "
              f"{len(files):>20}")
    for name, loc, files in PAPER:
        print(f"{name:32} {loc:>16} {files:>20}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
