"""Every benchmark writes its report atomically (the guide: "nothing half-written is left behind (write to a
temporary file, then rename)"): a ``.write_text`` / ``.write_bytes`` in ``benchmarks/*.py`` whose target names the
reports folder (``OUT``) or an output argument (``args.out``, ``a.json``, ``args.write``, ``out``, ``dst``, ``path``)
must go through ``prt_torch.io.atomic_write_text`` instead. Writes into temporary folders (C sources, child
configs, a ``tmp`` renamed into place by hand) are not reports and pass."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
REPORT_TARGET = re.compile(r"\bOUT\b|\b(?:args|a)\.(?:out|write|json|md)\b|^(?:out|dst|path|report)\b")


def direct_report_writes(src: str) -> list[tuple[int, str]]:
    """``(line, target)`` of each ``.write_text`` / ``.write_bytes`` call on a report target in ``src``."""
    hits = []
    for n in ast.walk(ast.parse(src)):
        if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr in ("write_text", "write_bytes"):
            target = ast.get_source_segment(src, n.func.value) or ""
            if REPORT_TARGET.search(target.strip("() ")):
                hits.append((n.lineno, target))
    return hits


def test_the_rule_finds_a_direct_report_write_and_passes_temporary_ones():
    bad = 'OUT = 1\n(OUT / "x.md").write_text("t")\nPath(args.out).write_text("t")\nout.with_suffix(".json").write_text("t")\n'
    assert [ln for ln, _ in direct_report_writes(bad)] == [2, 3, 4]
    ok = 'Path(tmp).write_text("t")\n(work / "main.c").write_text("t")\natomic_write_text(OUT / "x.md", "t")\n'
    assert direct_report_writes(ok) == []


@pytest.mark.parametrize("script", sorted(p.name for p in BENCH.glob("*.py")))
def test_benchmark_reports_are_written_atomically(script):
    hits = direct_report_writes((BENCH / script).read_text())
    assert not hits, (f"benchmarks/{script}: report written in place at line(s) "
                      f"{', '.join(f'{ln} ({t})' for ln, t in hits)}; use prt_torch.io.atomic_write_text")
