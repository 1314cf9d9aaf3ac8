"""What the CPU is and offers in hardware, from /proc/cpuinfo: its name (a run records what it
computed on), and the flags that decide which precisions run at their own rate (int8 dot
products, bf16 products) rather than emulated."""

from __future__ import annotations

from pathlib import Path

# The flags that give a CPU integer dot products (int8) and bf16 products in hardware.
INT8_UNITS = ("avx512_vnni", "avx_vnni", "amx_int8")
BF16_UNITS = ("avx512_bf16", "amx_bf16")


def cpu_flags(cpuinfo: Path = Path("/proc/cpuinfo")) -> set[str]:
    """The CPU's feature flags (empty where there is no /proc/cpuinfo, e.g. not Linux)."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return set()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "flags":
            return set(value.split())
    return set()


def has_bf16_units(flags: set[str] | None = None) -> bool | None:
    """True where the CPU flags bf16 units, False where it flags none, None where no flags are
    known (not an x86 Linux machine): then the caller decides by trying."""
    flags = cpu_flags() if flags is None else flags
    if not flags:
        return None
    return bool(flags & set(BF16_UNITS))


def cpu_name(cpuinfo: Path = Path("/proc/cpuinfo")) -> str | None:
    """The CPU's model name with its family and model numbers (which tell generations apart
    where the name does not); None where there is no /proc/cpuinfo or it names no model."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return None
    fields: dict[str, str] = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    name = fields.get("model name")
    if name is None:
        return None
    return f"{name} (family {fields.get('cpu family', '?')}, model {fields.get('model', '?')})"
