"""Train SqueezeSeg on a directory of ``*.npy`` scans (H, W, 6), resumable exactly.

    python -m falsify.models.train --data DIR --out DIR [--epochs N] [--batch B] [--resume]
        [--seed S] [--time-limit-min M] [--val-data DIR] [--precision auto|bf16|fp32]
        [--classes kitti4|semantickitti] [--device cpu|cuda]

``--classes kitti4`` (default) reads channel 5 as our four classes; ``semantickitti`` as
SemanticKITTI's 19 train ids (falsify.semantic; 0 unlabeled is ignored by the loss), as written
by ``falsify dataset --labels semantickitti``. bf16 autocast on a CUDA device where it has it.

Writes into --out: ``checkpoint.pt`` (every epoch and at the time limit: model, optimiser, epoch,
step, torch RNG), ``train_log.jsonl`` (one line per epoch), and at the end ``squeezeseg.pt``
(weights only), ``squeezeseg.onnx`` + ``squeezeseg.json``. Real KITTI scans must not be --data.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from falsify.models.spec import ALL_CHANNELS, DEFAULT_CHANNELS, normalise

from falsify.errors import FalsifyError

CLASS_WEIGHTS = (1.0 / 15.0, 1.0, 10.0, 10.0)
CLASS_SETS = ("kitti4", "semantickitti")
WEIGHT_SCANS = 200   # scans whose label counts set the semantickitti class weights
CHECKPOINT = "checkpoint.pt"
LOG = "train_log.jsonl"


@dataclass
class TrainConfig:
    """Everything that decides a training run (saved in the checkpoint)."""

    data: str
    out: str
    epochs: int = 30
    batch: int = 8
    seed: int = 0
    lr: float = 1e-3
    lr_decay: float = 0.95  # per epoch: lr * lr_decay ** epoch
    weight_decay: float = 1e-4
    crf_iterations: int = 3
    channels: tuple[str, ...] = field(default_factory=lambda: DEFAULT_CHANNELS)
    precision: str = "auto"  # auto | bf16 | fp32
    threads: int = 2
    time_limit_min: float | None = None
    val_data: str | None = None
    resume: bool = False
    max_steps: int | None = None  # stop (with a checkpoint) after this many steps: for tests
    loss_on: str = "backbone"  # backbone: CE on the pre-CRF logits; crf: on the CRF energies
    init: str | None = None  # start from these weights (checkpoint or state dict), new optimiser
    crf_only: bool = False  # train only the CRF's compatibility matrices (backbone frozen)
    export: bool = True
    classes: str = "kitti4"   # kitti4 | semantickitti
    device: str = "cpu"       # cpu | cuda
    holdout: tuple[str, ...] = ()   # split manifests: their held-out scans are refused


def list_scans(folder: str | Path, what: str = "--data") -> list[Path]:
    """Sorted ``*.npy`` files of a folder; FalsifyError if there are none."""
    p = Path(folder)
    if not p.is_dir():
        raise FalsifyError(f"{what} {p}: not a directory")
    files = sorted(p.glob("*.npy"))
    if not files:
        raise FalsifyError(f"{what} {p}: no *.npy scans found")
    return files


def load_scan(path: Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """One (H, W, 6) float32 scan; FalsifyError on a wrong layout or NaN."""
    try:
        a = np.load(path, mmap_mode="r")
    except (OSError, ValueError) as e:
        raise FalsifyError(f"cannot read scan {path}: {e}") from e
    if a.ndim != 3 or a.shape[2] != 6 or (shape is not None and a.shape[:2] != shape):
        want = f"({shape[0]}, {shape[1]}, 6)" if shape else "(H, W, 6)"
        raise FalsifyError(f"scan {path} has shape {a.shape}, expected {want}")
    a = np.asarray(a, dtype=np.float32)
    if not np.isfinite(a).all():
        raise FalsifyError(f"scan {path} holds NaN or inf")
    return a


def bf16_supported() -> bool:
    """True if this CPU runs bf16 autocast convolutions in hardware (AVX512-BF16 / AMX via
    oneDNN). oneDNN also emulates bf16 on plain AVX-512, slower than fp32, so a CPU whose flags
    show no bf16 units trains in fp32."""
    import torch

    from falsify.cpu import has_bf16_units

    if has_bf16_units() is False or not torch.backends.mkldnn.is_available():
        return False
    check = getattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", None)
    try:
        if check is not None and not check():
            return False
        with torch.autocast("cpu", dtype=torch.bfloat16):
            torch.nn.functional.conv2d(torch.ones(1, 2, 4, 4), torch.ones(2, 2, 3, 3))
        return True
    except Exception:
        return False


def batch_tensors(scans: np.ndarray, channels: Sequence[str]):
    """Scans (B,H,W,6) -> x, xyz, mask, labels (torch), with the spec's normalisation."""
    import torch
    from falsify.models.spec import INPUT_MEAN, INPUT_STD, SCAN_INDEX

    names = (*channels, "mask")
    mean = [INPUT_MEAN[SCAN_INDEX[c]] for c in channels] + [0.0]
    std = [INPUT_STD[SCAN_INDEX[c]] for c in channels] + [1.0]
    x, xyz, mask = normalise(scans, names, mean, std)
    labels = np.where(scans[..., 4] > 0, scans[..., 5], 0).astype(np.int64)
    return (torch.from_numpy(x), torch.from_numpy(xyz), torch.from_numpy(mask),
            torch.from_numpy(labels))


def flip(scan: np.ndarray) -> np.ndarray:
    """Horizontal flip of a range image: reverse the columns and negate y."""
    f = scan[:, ::-1].copy()
    f[..., 1] *= -1.0
    return f


def masked_loss(logits, labels, mask, weights):
    """Class-weighted cross-entropy over valid pixels, / number of valid pixels (official)."""
    import torch.nn.functional as F

    ce = F.cross_entropy(logits.float(), labels, reduction="none")  # (B,H,W)
    m = mask[:, 0]
    return (ce * weights[labels] * m).sum() / m.sum().clamp(min=1.0)


def semantic_weights(files: list[Path], shape) -> np.ndarray:
    """SemanticKITTI class weights 1 / sqrt(frequency) over the first scans' labelled pixels,
    scaled to mean 1 over the classes seen (SalsaNext's inverse square root; unseen classes and
    unlabeled get 0, so the loss ignores them)."""
    from falsify.semantic import TRAIN_CLASSES

    n = len(TRAIN_CLASSES)
    counts = np.zeros(n, np.float64)
    for f in files[:WEIGHT_SCANS]:
        scan = load_scan(f, shape)
        lab = np.where(scan[..., 4] > 0, scan[..., 5], 0).astype(np.int64).ravel()
        counts += np.bincount(lab, minlength=n)[:n]
    counts[0] = 0.0
    w = np.zeros(n)
    seen = counts > 0
    w[seen] = 1.0 / np.sqrt(counts[seen] / counts.sum())
    return w / w[seen].mean() if seen.any() else w


def validate(model, files: list[Path], cfg: TrainConfig, shape, autocast) -> dict:
    """Pooled TP/FP/FN IoU per class over a validation folder (invalid pixels = unknown)."""
    import torch

    n = num_classes(cfg)
    tp = np.zeros(n, np.int64)
    fp = np.zeros(n, np.int64)
    fn = np.zeros(n, np.int64)
    model.eval()
    with torch.inference_mode():
        for i in range(0, len(files), cfg.batch):
            scans = np.stack([load_scan(f, shape) for f in files[i:i + cfg.batch]])
            x, xyz, mask, labels = batch_tensors(scans, cfg.channels)
            dev = [t.to(cfg.device) for t in (x, xyz, mask)]
            with autocast():
                out = model(dev[0].contiguous(memory_format=torch.channels_last), dev[1], dev[2])
            pred = out.float().argmax(1).cpu().numpy()
            pred[scans[..., 4] <= 0] = 0
            lab = labels.numpy()
            if cfg.classes == "semantickitti":   # SemanticKITTI's scoring ignores unlabeled
                pred, lab = pred[lab != 0], lab[lab != 0]
            for c in range(n):
                p, t = pred == c, lab == c
                tp[c] += int((p & t).sum())
                fp[c] += int((p & ~t).sum())
                fn[c] += int((~p & t).sum())
    model.train(not cfg.crf_only)
    denom = tp + fp + fn
    iou = [float(tp[c] / denom[c]) if denom[c] else None for c in range(n)]
    out = {"val_car_iou": iou[1], "val_iou": iou, "val_scans": len(files)}
    if cfg.classes == "semantickitti":
        present = [v for v in iou[1:] if v is not None]
        out["val_miou"] = float(np.mean(present)) if present else None
    return out


def num_classes(cfg: TrainConfig) -> int:
    from falsify.semantic import TRAIN_CLASSES

    return len(TRAIN_CLASSES) if cfg.classes == "semantickitti" else len(CLASS_WEIGHTS)


def _save_atomic(obj, path: Path) -> None:
    import torch

    tmp = path.with_suffix(".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _load(path: Path, option: str, torch) -> dict:
    """A checkpoint or state dict; FalsifyError naming the option and file if it is not one."""
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # OSError, RuntimeError, pickle.UnpicklingError, ...
        raise FalsifyError(f"{option} {path}: cannot load weights "
                           f"({str(exc).splitlines()[0]})") from exc
    if not isinstance(ck, dict):
        raise FalsifyError(f"{option} {path}: not a state dict or checkpoint")
    return ck


def train(cfg: TrainConfig) -> dict:
    """Run (or resume) training; returns a summary dict. See the module docstring for files."""
    import contextlib

    import torch
    from falsify.models.export import export_onnx
    from falsify.models.squeezeseg import SqueezeSeg

    t_start = time.monotonic()
    out = Path(cfg.out)
    files = list_scans(cfg.data)
    first = load_scan(files[0])
    shape = first.shape[:2]
    val_files = list_scans(cfg.val_data, "--val-data") if cfg.val_data else []
    from falsify.data.holdout import check_not_held_out
    check_not_held_out(files, cfg.holdout, "--data (trained on)")
    check_not_held_out(val_files, cfg.holdout, "--val-data (chooses the checkpoint)")
    bad = [c for c in cfg.channels if c not in ALL_CHANNELS]
    if bad:
        raise FalsifyError(f"--channels: unknown {bad}; choose from {list(ALL_CHANNELS)}")

    if cfg.classes not in CLASS_SETS:
        raise FalsifyError(f"--classes: {cfg.classes!r}; allowed: {', '.join(CLASS_SETS)}")
    if cfg.device not in ("cpu", "cuda"):
        raise FalsifyError(f"--device: {cfg.device!r}; allowed: cpu, cuda")
    if cfg.device == "cuda" and not torch.cuda.is_available():
        raise FalsifyError("--device cuda: torch sees no CUDA device here (a CPU build of torch, "
                           "or no GPU); use --device cpu")
    torch.set_num_threads(cfg.threads)
    # cuDNN has no deterministic kernels for every op: a GPU run is repeatable to float
    # tolerance, not bit for bit (a CPU run is exact).
    torch.use_deterministic_algorithms(True, warn_only=cfg.device == "cuda")
    if cfg.crf_only and (cfg.loss_on != "crf" or cfg.crf_iterations == 0):
        raise FalsifyError("--crf-only trains the CRF: it needs --loss-on crf and CRF iterations")
    if cfg.loss_on not in ("backbone", "crf"):
        raise FalsifyError(f"--loss-on must be backbone or crf, got {cfg.loss_on!r}")
    if cfg.init and not Path(cfg.init).is_file():
        raise FalsifyError(f"--init {cfg.init}: no such file")
    if cfg.precision not in ("auto", "bf16", "fp32"):
        raise FalsifyError(f"--precision must be auto, bf16 or fp32, got {cfg.precision!r}")
    use_bf16 = cfg.precision == "bf16" or (cfg.precision == "auto" and bf16_supported())

    if cfg.device == "cuda" and cfg.precision == "auto":
        use_bf16 = torch.cuda.is_bf16_supported()

    def autocast():
        if use_bf16:
            return torch.autocast(cfg.device, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    torch.manual_seed(cfg.seed)
    model = SqueezeSeg(cfg.channels, crf_iterations=cfg.crf_iterations,
                       num_classes=num_classes(cfg))
    model = model.to(cfg.device, memory_format=torch.channels_last)
    if cfg.crf_only:
        for name, p in model.named_parameters():
            p.requires_grad_(name.startswith("crf."))
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=0.0 if cfg.crf_only
                            else cfg.weight_decay)
    weights = torch.tensor(CLASS_WEIGHTS if cfg.classes == "kitti4"
                           else semantic_weights(files, shape), dtype=torch.float32).to(cfg.device)
    epoch, step = 0, 0
    ckpt_path = out / CHECKPOINT
    if cfg.resume:
        if not ckpt_path.is_file():
            raise FalsifyError(f"--resume: no checkpoint {ckpt_path}")
        ck = _load(ckpt_path, "--resume", torch)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optim"])
        epoch, step = int(ck["epoch"]), int(ck["step"])
        torch.set_rng_state(ck["torch_rng"])
    elif cfg.init:
        ck = _load(Path(cfg.init), "--init", torch)
        try:
            model.load_state_dict(ck.get("model", ck))
        except RuntimeError as exc:
            raise FalsifyError(f"--init {cfg.init}: not SqueezeSeg weights for these channels "
                               f"({str(exc).splitlines()[0]})") from exc
    model.train(not cfg.crf_only)  # CRF-only: the frozen backbone runs as at inference
    out.mkdir(parents=True, exist_ok=True)   # only once every input has been checked

    def checkpoint(e: int, s: int) -> None:
        _save_atomic({"model": model.state_dict(), "optim": opt.state_dict(), "epoch": e,
                      "step": s, "torch_rng": torch.get_rng_state(),
                      "config": json.dumps(asdict(cfg))}, ckpt_path)

    def log(rec: dict) -> None:
        with open(out / LOG, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(rec) + "\n")

    limit = cfg.time_limit_min * 60.0 if cfg.time_limit_min else None
    steps_run, stopped, last = 0, "done", {}
    n = len(files)
    while epoch < cfg.epochs and stopped == "done":
        rng = np.random.default_rng([cfg.seed, epoch])  # order and flips depend on epoch only
        perm = rng.permutation(n)
        flips = rng.random(n) < 0.5
        for g in opt.param_groups:
            g["lr"] = cfg.lr * cfg.lr_decay**epoch
        batches = [perm[i:i + cfg.batch] for i in range(0, n, cfg.batch)]
        losses, t_epoch, frames = [], time.monotonic(), 0
        while step < len(batches):
            idx = batches[step]
            scans = np.stack([flip(s) if flips[i] else s
                              for i, s in ((i, load_scan(files[i], shape)) for i in idx)])
            x, xyz, mask, labels = (t.to(cfg.device) for t in batch_tensors(scans, cfg.channels))
            if cfg.classes == "semantickitti":
                mask = mask * (labels != 0)[:, None]   # unlabeled pixels are not scored
            with autocast():
                xc = x.contiguous(memory_format=torch.channels_last)
                # The CRF's energies live in [0, ~1.2] (softmax + small messages, as in the
                # official code), so a cross-entropy on them cannot saturate and the class
                # weights swamp the unknown class; the backbone's logits train cleanly and the
                # CRF keeps its published initialisation at inference.
                logits = model.backbone(xc) if cfg.loss_on == "backbone" else model(xc, xyz, mask)
            loss = masked_loss(logits, labels, mask, weights)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
            frames += len(idx)
            step += 1
            steps_run += 1
            if cfg.max_steps is not None and steps_run >= cfg.max_steps:
                stopped = "max_steps"
            elif limit is not None and time.monotonic() - t_start > limit:
                stopped = "time_limit"
            if stopped != "done":
                break
        sec = time.monotonic() - t_epoch
        end_of_epoch = step >= len(batches)
        if end_of_epoch:
            epoch, step = epoch + 1, 0
        checkpoint(epoch, step)
        last = {"epoch": epoch if end_of_epoch else epoch + step / len(batches),
                "loss": float(np.mean(losses)) if losses else None,
                "lr": cfg.lr * cfg.lr_decay**(epoch - 1 if end_of_epoch else epoch),
                "seconds": round(sec, 2),
                "ms_per_frame_step": round(1e3 * sec / max(frames, 1), 1),
                "precision": "bf16" if use_bf16 else "fp32"}
        if val_files and (end_of_epoch or stopped != "done"):
            last.update(validate(model, val_files, cfg, shape, autocast))
        if stopped != "done":
            last["stopped"] = stopped
        log(last)
        print(json.dumps(last), flush=True)

    if stopped == "max_steps":
        return {"stopped": stopped, "epoch": epoch, "step": step}
    final = model.to("cpu", memory_format=torch.contiguous_format).eval()
    state = {k: v.contiguous() for k, v in final.state_dict().items()}
    torch.save(state, out / "squeezeseg.pt")
    summary = {"stopped": stopped, "epoch": epoch, "step": step, **{
        k: last.get(k) for k in ("loss", "val_car_iou")}}
    if cfg.export:
        export_onnx(final, out / "squeezeseg.onnx", H=shape[0], W=shape[1], name="squeezeseg",
                    classes=None if cfg.classes == "kitti4" else "semantickitti",
                    trained_epochs=epoch, seed=cfg.seed, data=Path(cfg.data).name,
                    val_car_iou=last.get("val_car_iou"))
        # the .pt gets the same spec as the .onnx (same stem): load_segmenter(out/'x.pt', 'torch')
    return summary


def parse_args(argv: Sequence[str] | None) -> TrainConfig:
    """CLI -> TrainConfig."""
    p = argparse.ArgumentParser(prog="python -m falsify.models.train",
                                description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="folder of *.npy scans (H, W, 6)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--time-limit-min", type=float, default=None)
    p.add_argument("--val-data", default=None, help="folder of *.npy scans for car IoU")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--lr-decay", type=float, default=0.95)
    p.add_argument("--crf-iterations", type=int, default=3, choices=range(4))
    p.add_argument("--channels", default=",".join(DEFAULT_CHANNELS),
                   help=f"comma list from {','.join(ALL_CHANNELS)}")
    p.add_argument("--precision", default="auto", choices=["auto", "bf16", "fp32"])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--max-steps", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--no-export", action="store_true", help="skip the ONNX export at the end")
    p.add_argument("--loss-on", default="backbone", choices=["backbone", "crf"],
                   help="train on the pre-CRF logits (default) or on the CRF's energies")
    p.add_argument("--init", default=None, help="start from these weights (fresh optimiser)")
    p.add_argument("--crf-only", action="store_true",
                   help="train only the CRF compatibility matrices, the backbone frozen")
    p.add_argument("--classes", default="kitti4", choices=CLASS_SETS,
                   help="what channel 5 holds: our four classes or SemanticKITTI's train ids")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--holdout", action="append", default=[], metavar="SPLITS_TOML",
                   help="a split manifest whose held-out scans --data and --val-data may not "
                   "hold (also $FALSIFY_HOLDOUT and a splits.toml beside the data)")
    a = p.parse_args(argv)
    return TrainConfig(
        data=a.data, out=a.out, epochs=a.epochs, batch=a.batch, seed=a.seed, lr=a.lr,
        lr_decay=a.lr_decay, crf_iterations=a.crf_iterations,
        channels=tuple(c.strip() for c in a.channels.split(",") if c.strip()),
        precision=a.precision, threads=a.threads, time_limit_min=a.time_limit_min,
        val_data=a.val_data, resume=a.resume, max_steps=a.max_steps, export=not a.no_export,
        loss_on=a.loss_on, init=a.init, crf_only=a.crf_only, classes=a.classes,
        device=a.device, holdout=tuple(a.holdout))


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry point; returns the exit code (2 on a FalsifyError)."""
    try:
        summary = train(parse_args(argv))
    except FalsifyError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
