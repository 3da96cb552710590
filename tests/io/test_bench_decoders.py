"""The decoder benchmark runs and writes its table (quick mode; no timing asserted)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_decoders.py"


def test_bench_decoders_quick(tmp_path) -> None:
    spec = importlib.util.spec_from_file_location("bench_decoders", BENCH)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "decoders.md"
    assert mod.main(["--quick", "--out", str(out)]) == 0
    text = out.read_text()
    assert "| serial, clean, 64-byte reads |" in text and "| CAN (cantools, DBC) |" in text
    assert text.count("x |") == 6
