"""A CPU and a CUDA result of falsify side by side (gpu_cuda_paths.sh): two grid runs row by
row, or two trained state dicts tensor by tensor.

    python research/experiments/gpu_compare.py grids RUN_A RUN_B   (RUN.json: grid --json)
    python research/experiments/gpu_compare.py weights A.pt B.pt
"""
import json
import sys

import numpy as np


def grids(a: str, b: str) -> None:
    from falsify.results.store import read_frame
    fa, fb = read_frame(a).set_index("sample_key"), read_frame(b).set_index("sample_key")
    fb = fb.loc[fa.index]
    d = np.abs(fa["car_iou"].astype(float) - fb["car_iou"].astype(float))
    sa, sb = (json.load(open(p)) for p in (f"{a}.json", f"{b}.json"))
    out = {"rows": [len(fa), len(fb)], "status_equal": bool((fa.status == fb.status).all()),
           "car_iou_max_abs_diff": float(np.nanmax(d)),
           "car_iou_mean_abs_diff": float(np.nanmean(d)),
           "rows_differing_over_0.01": int((d > 0.01).sum()),
           "car_points_max_abs_diff": int(np.abs(fa.car_points - fb.car_points).max()),
           "mean_car_iou": [sa["mean_car_iou"], sb["mean_car_iou"]],
           "blind_spots": [sa["blind_spots"], sb["blind_spots"]],
           "blind_cells_equal": sa["blind_spot_cells"] == sb["blind_spot_cells"],
           "elapsed_s": [sa["elapsed_s"], sb["elapsed_s"]]}
    print(json.dumps(out, indent=1))


def weights(a: str, b: str) -> None:
    import torch
    sa, sb = (torch.load(p, map_location="cpu", weights_only=True) for p in (a, b))
    sa, sb = sa.get("model", sa), sb.get("model", sb)
    diffs = {k: float((sa[k].float() - sb[k].float()).abs().max()) for k in sa}
    print(json.dumps({"tensors": len(diffs), "identical": sum(v == 0 for v in diffs.values()),
                      "max_abs_diff": max(diffs.values())}))


if __name__ == "__main__":
    {"grids": grids, "weights": weights}[sys.argv[1]](*sys.argv[2:])
