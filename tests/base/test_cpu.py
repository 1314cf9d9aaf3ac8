"""The CPU's flags decide which precisions train and run at their own rate."""

from __future__ import annotations

from pathlib import Path

import pytest

from falsify.cpu import cpu_flags, has_bf16_units


def _cpuinfo(tmp_path: Path, flags: str) -> Path:
    p = tmp_path / "cpuinfo"
    p.write_text(f"processor\t: 0\nmodel name\t: Some CPU\nflags\t\t: {flags}\n\n")
    return p


def test_flags_are_read_and_bf16_units_recognised(tmp_path):
    cascade_lake = cpu_flags(_cpuinfo(tmp_path, "fpu sse avx512f avx512_vnni"))
    assert "avx512_vnni" in cascade_lake and has_bf16_units(cascade_lake) is False
    assert has_bf16_units({"avx512f", "avx512_bf16"}) is True
    assert has_bf16_units({"amx_bf16", "amx_int8"}) is True
    assert cpu_flags(tmp_path / "missing") == set()
    assert has_bf16_units(set()) is None   # unknown: the caller tries


def test_auto_precision_trains_in_fp32_without_bf16_units(monkeypatch):
    """oneDNN emulates bf16 on plain AVX-512 (slower than fp32): such a CPU trains in fp32."""
    pytest.importorskip("torch")
    import falsify.cpu
    from falsify.models.train import bf16_supported

    monkeypatch.setattr(falsify.cpu, "cpu_flags", lambda: {"avx512f", "avx512_vnni"})
    assert bf16_supported() is False
