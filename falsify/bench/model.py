"""`falsify bench model`: beside the network's variants, the machine's own matrix rates in each
precision (fp32 and int8 through ONNX Runtime, bf16 through torch), so that each variant reads as
a share of what the hardware does in its precision, measured in the same run.
"""

from __future__ import annotations

from collections.abc import Callable

from falsify.bench.machine import bf16_matmul_rate, matmul_rate
from falsify.cpu import BF16_UNITS, INT8_UNITS, cpu_flags


def model_bench_rates(progress: Callable[[str], None]) -> dict:
    """The machine's matrix rates on one thread, fp32 and int8 through ONNX Runtime and bf16
    through torch where the CPU has bf16 units, with the CPU's int8 and bf16 units named."""
    progress("bench model: the machine's fp32, int8 and bf16 matrix rates (1 thread)")
    flags = cpu_flags()
    return {"fp32": matmul_rate(1).to_json(), "int8": matmul_rate(1, kind="int8").to_json(),
            "bf16": bf16_matmul_rate(),
            "cpu_units": {"int8": sorted(flags & set(INT8_UNITS)),
                          "bf16": sorted(flags & set(BF16_UNITS))}}


def add_shares(rows: list[dict], flops: int, rates: dict) -> None:
    """Each variant's achieved giga-ops/s per thread (the fp32 graph's counted ops, the same
    work in every precision) and its share of the 1-core matrix rate of its precision."""
    peak = {"fp32": rates["fp32"]["gflops_1_core"], "int8": rates["int8"]["gops_1_core"],
            "bf16": rates["bf16"]["gflops_1_core"]}
    for r in rows:
        if "fps" not in r:
            continue
        achieved = flops * r["fps"] / r["threads"] / 1e9
        r["achieved_gops_per_thread"] = round(achieved, 2)
        rate = peak.get(r["precision"])
        r["share_of_matrix_rate"] = round(achieved / rate, 3) if rate else None
