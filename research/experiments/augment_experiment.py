"""The seed paper's headline experiment: SqueezeSeg trained on real scans only, on real plus
synthetic scans, and on synthetic scans only, with one recipe and one budget, scored on
SemanticKITTI's evaluation split; with and without the intensity channel, over seeds.

    python research/experiments/augment_experiment.py --pack ROOT --out PACKED   # once, on CPU
    python research/experiments/augment_experiment.py --fit PACKED/fit.npz --eval PACKED/eval.npz \
        --synthetic DIR --out OUT [--seeds 0,1,2] [--steps 1000] [--device cuda]

FIT.npz / EVAL.npz hold `images` (B, 64, 512, 6) range images of the semantickitti-mini fit
sequences (01, 02, 04, 05, 07, 09, 10: the only real scans trained on) and evaluation sequences
(00, 03, 06, 08: only scored), read with the `kitti-hdl64e-front` preset, and `names` ("SS/NNNNNN").
DIR is a `falsify dataset` folder. Every run takes the same number of steps of the same batch
size from the same initialisation per seed; real + synthetic batches are half real, half
synthetic (21 real scans would vanish in thousands of synthetic ones otherwise). No CRF (the
loss is on the backbone in every arm). Car IoU is scored as `falsify predict` scores it: every
valid pixel, four classes, pooled over the scans. Writes OUT/results.json.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import json
import multiprocessing as mp
import time
from pathlib import Path

import numpy as np

ARMS = ("real", "real+synthetic", "synthetic")
CHANNELS = {"no intensity": ("x", "y", "z", "range"),
            "intensity": ("x", "y", "z", "intensity", "range")}


def load_synthetic(folder: Path) -> np.ndarray:
    return np.stack([np.load(p).astype(np.float32) for p in sorted(folder.glob("*.npy"))])


def car_iou(pred: np.ndarray, images: np.ndarray) -> dict:
    """Pooled car IoU, precision and recall over valid pixels (invalid: unknown both)."""
    valid = images[..., 4] > 0
    label = np.where(valid, images[..., 5], 0).astype(np.int64)
    p, t = (pred == 1) & valid, label == 1
    tp, fp, fn = int((p & t).sum()), int((p & ~t).sum()), int((~p & t).sum())
    return {"iou": tp / (tp + fp + fn) if tp + fp + fn else None,
            "precision": tp / (tp + fp) if tp + fp else None,
            "recall": tp / (tp + fn) if tp + fn else None, "tp": tp, "fp": fp, "fn": fn}


def run_one(arm: str, channels_name: str, seed: int, args: dict) -> dict:
    """Train one network and score it on the evaluation scans."""
    import torch

    from falsify.models.squeezeseg import SqueezeSeg
    from falsify.models.train import CLASS_WEIGHTS, batch_tensors, flip, masked_loss

    t0 = time.monotonic()
    torch.set_num_threads(1)
    fit = np.load(args["fit"])["images"].astype(np.float32)
    ev = np.load(args["eval"])
    ev_images, ev_names = ev["images"].astype(np.float32), ev["names"]
    syn = load_synthetic(Path(args["synthetic"])) if arm != "real" else None
    channels = CHANNELS[channels_name]
    device = args["device"]
    torch.manual_seed(seed)
    model = SqueezeSeg(channels, crf_iterations=0).to(device, memory_format=torch.channels_last)
    opt = torch.optim.AdamW(model.parameters(), lr=args["lr"], weight_decay=1e-4)
    weights = torch.tensor(CLASS_WEIGHTS, dtype=torch.float32, device=device)
    rng = np.random.default_rng([seed, 7])   # the same draws in every arm of a seed
    batch, steps = args["batch"], args["steps"]
    bf16 = device == "cuda" and torch.cuda.is_bf16_supported()
    model.train()
    for step in range(steps):
        for g in opt.param_groups:   # the trainer's decay, per tenth of the run
            g["lr"] = args["lr"] * 0.95 ** (10 * step / steps)
        if arm == "real":
            scans = fit[rng.integers(len(fit), size=batch)]
        elif arm == "synthetic":
            scans = syn[rng.integers(len(syn), size=batch)]
        else:
            half = batch // 2
            scans = np.concatenate([fit[rng.integers(len(fit), size=half)],
                                    syn[rng.integers(len(syn), size=batch - half)]])
        flips = rng.random(batch) < 0.5
        scans = np.stack([flip(s) if f else s for s, f in zip(scans, flips, strict=True)])
        x, _, mask, labels = (t.to(device) for t in batch_tensors(scans, channels))
        with torch.autocast(device, dtype=torch.bfloat16, enabled=bf16):
            logits = model.backbone(x.contiguous(memory_format=torch.channels_last))
        loss = masked_loss(logits, labels, mask, weights)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    model.eval()
    pred = _predict(model, ev_images, channels, device)
    seqs = np.array([str(n).split("/")[0] for n in ev_names])
    out = {"arm": arm, "channels": channels_name, "seed": seed, "loss": float(loss.detach()),
           "pooled": car_iou(pred, ev_images),
           # The fit scans are unseen by a synthetic-only run: a score a choice may read.
           "fit_pooled": (car_iou(_predict(model, fit, channels, device), fit)
                          if arm == "synthetic" else None),
           "per_sequence": {s: car_iou(pred[seqs == s], ev_images[seqs == s])["iou"]
                            for s in sorted(set(seqs))},
           "seconds": round(time.monotonic() - t0, 1)}
    print(json.dumps({k: out[k] for k in ("arm", "channels", "seed", "seconds")}
                     | {"car_iou": out["pooled"]["iou"]}), flush=True)
    return out


def _predict(model, images: np.ndarray, channels, device: str) -> np.ndarray:
    """Class per pixel of each image, four at a time."""
    import torch

    from falsify.models.train import batch_tensors

    preds = []
    with torch.inference_mode():
        for i in range(0, len(images), 4):
            x, _, _, _ = batch_tensors(images[i:i + 4], channels)
            preds.append(model(x.to(device)).float().argmax(1).cpu().numpy())
    return np.concatenate(preds)


def _mean_fit(runs: list[dict], arm: str, ch: str) -> float | None:
    """Mean pooled car IoU on the fit scans (synthetic-only runs), or None."""
    v = [r["fit_pooled"]["iou"] for r in runs if r["arm"] == arm and r["channels"] == ch
         and r.get("fit_pooled") and r["fit_pooled"]["iou"] is not None]
    return float(np.mean(v)) if v else None


def summarise(runs: list[dict]) -> list[dict]:
    """Mean, spread (sample std) and min..max of pooled car IoU per arm and channel set."""
    table = []
    for ch in CHANNELS:
        for arm in ARMS:
            v = [r["pooled"]["iou"] for r in runs if r["arm"] == arm and r["channels"] == ch]
            v = [x for x in v if x is not None]
            if v:
                table.append({"arm": arm, "channels": ch, "seeds": len(v),
                              "mean": float(np.mean(v)),
                              "std": float(np.std(v, ddof=1)) if len(v) > 1 else None,
                              "min": float(min(v)), "max": float(max(v)),
                              "fit_mean": _mean_fit(runs, arm, ch)})
    return table


SPLITS = {"fit": ("01", "02", "04", "05", "07", "09", "10"), "eval": ("00", "03", "06", "08")}


def pack(root: Path, out: Path) -> None:
    """FIT.npz and EVAL.npz from a SemanticKITTI root (semantickitti-mini): the front-view range
    images of each split, with our four classes from the .label files."""
    from falsify.data.velodyne import read_kitti
    from falsify.sensor.lidar import load_sensor
    from falsify.world.real_scans import label_file

    sensor = load_sensor("kitti-hdl64e-front")
    out.mkdir(parents=True, exist_ok=True)
    for split, seqs in SPLITS.items():
        bins = [b for s in seqs
                for b in sorted((root / "sequences" / s / "velodyne").glob("*.bin"))]
        missing = [str(b) for b in bins if label_file(b) is None]
        if not bins or missing:
            raise SystemExit(f"{root}: {split} split: " + (f"labels missing for {missing}"
                                                           if missing else "no scans found"))
        np.savez_compressed(out / f"{split}.npz",
                            images=np.stack([read_kitti(b, label_file(b), sensor).image
                                             for b in bins]),
                            names=np.array([f"{b.parent.parent.name}/{b.stem}" for b in bins]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--pack", type=Path, help="a SemanticKITTI root: write OUT/fit.npz, eval.npz")
    p.add_argument("--fit")
    p.add_argument("--eval")
    p.add_argument("--synthetic")
    p.add_argument("--out", required=True)
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--parallel", type=int, default=1, help="runs at once (processes)")
    p.add_argument("--arms", default=",".join(ARMS), help="comma list of " + ", ".join(ARMS))
    p.add_argument("--channels", default=",".join(CHANNELS),
                   help="comma list of " + ", ".join(CHANNELS))
    a = p.parse_args()
    if a.pack is not None:
        pack(a.pack, Path(a.out))
        return
    if not (a.fit and a.eval and a.synthetic):
        p.error("--fit, --eval and --synthetic are required (or --pack ROOT)")
    args = {"fit": a.fit, "eval": a.eval, "synthetic": a.synthetic, "device": a.device,
            "steps": a.steps, "batch": a.batch, "lr": a.lr}
    arms, chans = a.arms.split(","), a.channels.split(",")
    for v, allowed in ((arms, ARMS), (chans, tuple(CHANNELS))):
        if not set(v) <= set(allowed):
            p.error(f"{v}: allowed {', '.join(allowed)}")
    jobs = [(arm, ch, int(s)) for s in a.seeds.split(",") for ch in CHANNELS for arm in ARMS
            if arm in arms and ch in chans]
    with cf.ProcessPoolExecutor(a.parallel, mp_context=mp.get_context("spawn")) as pool:
        runs = list(pool.map(run_one, *zip(*jobs, strict=True), [args] * len(jobs)))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    doc = {"recipe": {k: v for k, v in args.items() if k not in ("fit", "eval", "synthetic")},
           "synthetic": Path(a.synthetic).name, "summary": summarise(runs), "runs": runs}
    (out / "results.json").write_text(json.dumps(doc, indent=1) + "\n")
    for row in doc["summary"]:
        print(json.dumps(row))


if __name__ == "__main__":
    main()
