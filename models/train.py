"""Train SqueezeSeg on a directory of ``*.npy`` scans (H, W, 6), resumable exactly.

    falsify train --data DIR --out DIR [--epochs N] [--batch B] [--resume]
        [--seed S] [--time-limit-min M] [--val-data DIR] [--precision auto|bf16|fp32]
        [--classes kitti4|semantickitti] [--device cpu|cuda]

``--classes kitti4`` (default) reads channel 5 as our four classes; ``semantickitti`` as
SemanticKITTI's 19 train ids (falsify.semantic; 0 unlabeled is ignored by the loss), as written
by ``falsify dataset --labels semantickitti``. bf16 autocast on a CUDA device where it has it.

Writes into --out: ``checkpoint.pt`` (every epoch and at the time limit: model, optimiser, epoch,
step, torch RNG (a GPU run: its generator too), precision, the log so far, the run's options),
epoch, rewritten from the checkpoint on --resume), and at the end ``squeezeseg.pt`` (weights
only), ``squeezeseg.onnx`` + ``squeezeseg.json``; each file whole or not at all. Real KITTI scans
must not be --data. An --out holding a run is continued only with --resume, and only with the
options that decide its weights unchanged (RESUME_KEYS and the precision trained at; --epochs may
grow).
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from falsify.checks import check_out_dir, check_range, check_seed
from falsify.data.range_npy import npy_files
from falsify.errors import FalsifyError
from falsify.models.spec import ALL_CHANNELS, DEFAULT_CHANNELS, normalise

CLASS_WEIGHTS = (1.0 / 15.0, 1.0, 10.0, 10.0)
CLASS_SETS = ("kitti4", "semantickitti")
WEIGHT_SCANS = 200   # scans whose label counts set the semantickitti class weights
# Adam's first step is lr / (1 - beta1) = 10 x lr: above this it overflows float32 in torch
LR_MAX = 1e37
CHECKPOINT = "checkpoint.pt"
LOG = "train_log.jsonl"
RUN_FILES = (CHECKPOINT, LOG, "squeezeseg.pt", "squeezeseg.onnx")   # what a run leaves in --out
# the options a resumed run must keep: they decide its weights (--epochs may grow)
RESUME_KEYS = ("data", "batch", "seed", "lr", "lr_decay", "weight_decay", "crf_iterations",
               "channels", "classes", "loss_on", "crf_only")


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
    files = npy_files(p)   # a retraining set's camera arrays lie beside its scans
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


def check_scans(files: list[Path], shape: tuple[int, int], option: str) -> None:
    """Every scan of an option's folder is an (H, W, 6) array of the training scans' H and W,
    read from the headers only: a bad one would otherwise stop the run after an epoch (a
    --val-data scan: once its checkpoint is written)."""
    for f in files:
        try:
            got = np.load(f, mmap_mode="r").shape
        except (OSError, ValueError) as e:
            raise FalsifyError(f"{option}: cannot read scan {f}: {e}") from e
        if got != (*shape, 6):
            raise FalsifyError(f"{option}: scan {f} has shape {got}, expected ({shape[0]}, "
                               f"{shape[1]}, 6) like the first --data scan")


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


def semantic_weights(files: list[Path], shape, option: str = "--data") -> np.ndarray:
    """SemanticKITTI class weights 1 / sqrt(frequency) over the first scans' labelled pixels,
    scaled to mean 1 over the classes seen (SalsaNext's inverse square root; unseen classes and
    unlabeled get 0, so the loss ignores them). FalsifyError naming `option` if no pixel is
    labelled: every weight would be 0 and the run would train nothing (or divide 0 by 0)."""
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
    if not seen.any():
        raise FalsifyError(f"{option} {files[0].parent}: no labelled pixel (train ids 1-{n - 1}) "
                           f"in its first {min(len(files), WEIGHT_SCANS)} scans; nothing to "
                           "train on")
    w[seen] = 1.0 / np.sqrt(counts[seen] / counts.sum())
    return w / w[seen].mean()


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
    """torch.save `obj` to `path` whole or not at all (a stop or kill mid-write leaves the
    previous file, and no temporary one but after a SIGKILL)."""
    import torch

    from falsify.fileio import atomic_path

    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


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
    import torch

    t_start = time.monotonic()
    out = Path(cfg.out)
    files, val_files, shape = _checked_inputs(cfg, torch)
    use_bf16 = _use_bf16(cfg, torch)

    def autocast():
        if use_bf16:
            return torch.autocast(cfg.device, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    model, opt, weights = _build(cfg, files, shape, torch)
    ckpt_path = out / CHECKPOINT
    precision = "bf16" if use_bf16 else "fp32"
    run = _Progress(*_restore(cfg, model, opt, ckpt_path, precision, torch))
    model.train(not cfg.crf_only)  # CRF-only: the frozen backbone runs as at inference
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)   # only once every input has been checked
    if cfg.resume:
        _write_log(out, run.log)   # a stop between checkpoint and log left the log behind

    def save(log: list[dict]) -> None:
        """Checkpoint the run as it stands, with its log records `log`, whole or not at all."""
        state = {"model": model.state_dict(), "optim": opt.state_dict(),
                 "epoch": run.epoch, "step": run.step, "torch_rng": torch.get_rng_state(),
                 "config": json.dumps(asdict(cfg)), "precision": precision,
                 "log": json.dumps(log), "data_path": str(Path(cfg.data).resolve())}
        if cfg.device == "cuda":   # dropout on a GPU draws from the device's own generator
            state["cuda_rng"] = torch.cuda.get_rng_state()
        _save_atomic(state, ckpt_path)

    limit = cfg.time_limit_min * 60.0 if cfg.time_limit_min else None
    while run.epoch < cfg.epochs and run.stopped == "done":
        try:
            losses, frames, batches, sec = _train_epoch(
                cfg, model, opt, weights, files, shape, autocast, run,
                lambda: limit is not None and time.monotonic() - t_start > limit)
        except (FalsifyError, KeyboardInterrupt):   # diverged or stopped: a folder made for
            if created and not any(out.iterdir()):    # this run and still empty goes
                out.rmdir()
            raise
        end_of_epoch = run.step >= batches
        if end_of_epoch:
            run.epoch, run.step = run.epoch + 1, 0
        record = _epoch_record(cfg, run, end_of_epoch, batches, losses, frames, sec, use_bf16)
        stop = {"stopped": run.stopped} if run.stopped != "done" else {}
        run.log.append({**record, **stop})
        # saved before validation, so that a stop during it loses no training; again after it
        save(run.log)
        _write_log(out, run.log)
        if val_files and (end_of_epoch or run.stopped != "done"):
            record.update(validate(model, val_files, cfg, shape, autocast))
            run.log[-1] = {**record, **stop}
            save(run.log)
            _write_log(out, run.log)
        run.last = run.log[-1]
        print(json.dumps(run.last), flush=True)

    if run.stopped == "max_steps":
        return {"stopped": run.stopped, "epoch": run.epoch, "step": run.step}
    return _finish(cfg, model, out, shape, run, torch)


@dataclass
class _Progress:
    """Where a training run stands: the epoch, the step in it, its log records, the steps run
    by this call, why it stopped ("done" while it runs on) and the last epoch's log record."""

    epoch: int
    step: int
    log: list[dict] = field(default_factory=list)   # every record so far (train_log.jsonl)
    steps_run: int = 0
    stopped: str = "done"
    last: dict = field(default_factory=dict)


def _checked_inputs(cfg: TrainConfig, torch) -> tuple[list[Path], list[Path], tuple[int, int]]:
    """The training and validation scans and the scans' (H, W), once every option has been
    checked; sets torch's threads and deterministic algorithms on the way, as training needs."""
    _check_numbers(cfg)
    check_out_dir(cfg.out)
    files = list_scans(cfg.data)
    first = load_scan(files[0])
    shape = first.shape[:2]
    val_files = list_scans(cfg.val_data, "--val-data") if cfg.val_data else []
    check_scans(files, shape, "--data")
    check_scans(val_files, shape, "--val-data")
    from falsify.data.holdout import check_apart, check_not_held_out
    check_not_held_out(files, cfg.holdout, "--data (trained on)")
    check_not_held_out(val_files, cfg.holdout, "--val-data (chooses the checkpoint)")
    check_apart(files, val_files, "--val-data")
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
    check_labels(cfg.data, cfg.classes, "--data")
    if cfg.val_data:
        check_labels(cfg.val_data, cfg.classes, "--val-data")
    _check_out(cfg, torch)
    return files, val_files, shape


def check_run_numbers(cfg: Any) -> None:
    """The numbers every trainer takes (epochs, batch, seed, lr, time limit): a zero batch or a
    negative rate fails deep in torch, and zero epochs would write untrained weights."""
    check_range(cfg.epochs, "--epochs", 1)
    check_range(cfg.batch, "--batch", 1)
    check_seed(cfg.seed)
    if not (math.isfinite(cfg.lr) and 0 < cfg.lr <= LR_MAX):
        raise FalsifyError(f"--lr: {cfg.lr} must be a number > 0 and <= {LR_MAX:g}")
    if cfg.time_limit_min is not None and not cfg.time_limit_min > 0:
        raise FalsifyError(f"--time-limit-min: {cfg.time_limit_min} must be > 0")


def _check_numbers(cfg: TrainConfig) -> None:
    """SqueezeSeg's numbers: every trainer's, its threads and its rate's decay."""
    check_run_numbers(cfg)
    check_range(cfg.threads, "--threads", 1)
    if not (math.isfinite(cfg.lr_decay) and 0 < cfg.lr_decay <= 1):
        raise FalsifyError(f"--lr-decay: {cfg.lr_decay} must be in (0, 1]")


def check_labels(folder: str, classes: str, option: str, fix: str | None = None) -> None:
    """The label set a `falsify dataset` folder's index.json records (our four classes when it
    names none) is `classes`: other ids fail mid-run or train nonsense. `fix`: what to do
    instead (default: pass --classes to match)."""
    path = Path(folder) / "index.json"
    try:
        index = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return   # not a `falsify dataset` folder: nothing records its labels
    labels = index.get("labels", "kitti4") if isinstance(index, dict) else "kitti4"
    if labels in CLASS_SETS and labels != classes:
        raise FalsifyError(f"{option} {folder}: its scans hold {labels} labels ({path}), not "
                           f"{classes}; {fix or f'pass --classes {labels}'}")


def _same_path(a: str | None, b: str | None) -> bool:
    """Two option values naming the same file or folder (as written, or once resolved)."""
    if a is None or b is None:
        return a == b
    return a == b or Path(a).resolve() == Path(b).resolve()


# An option only one trainer has, and that trainer: tells whose checkpoint an --out holds.
TRAINER_KEYS = {"crf_iterations": "falsify train", "points": "falsify train-pointnet"}


def _check_out(cfg: Any, torch, keys: Sequence[str] = RESUME_KEYS,
               run_files: Sequence[str] = RUN_FILES) -> None:
    """--out without a training run in it (`run_files`), or (with --resume) one of the same run:
    the options in `keys` as stored in its checkpoint, and --epochs no fewer than it has trained
    (a dataclass `cfg` with out, resume and epochs: train-pointnet's too)."""
    out = Path(cfg.out)
    if not cfg.resume:
        held = [n for n in run_files if (out / n).exists()]
        if held:
            raise FalsifyError(f"--out {out} already holds a training run ({held[0]}); pass "
                               "--resume to continue it or choose another --out")
        return
    ckpt_path = out / CHECKPOINT
    if not ckpt_path.is_file():
        raise FalsifyError(f"--resume: no checkpoint {ckpt_path}")
    ck = _load(ckpt_path, "--resume", torch)
    try:
        old = json.loads(ck["config"])
    except (KeyError, TypeError, ValueError):
        raise FalsifyError(f"--resume {ckpt_path}: holds no run options (not a training "
                           "checkpoint of falsify)") from None
    now = json.loads(json.dumps(asdict(cfg)))   # tuples as lists, as stored
    for key, trainer in TRAINER_KEYS.items():   # both trainers write checkpoint.pt
        if key in old and key not in now:
            raise FalsifyError(f"--resume {ckpt_path}: a checkpoint of `{trainer}`, not of "
                               f"this trainer; continue it with `{trainer} --resume`")
    for key in keys:
        there, here = old.get(key), now[key]
        same = there == here
        if key == "data":   # a relative --data names the same folder from another directory
            same = _same_path(ck.get("data_path", there), here)
        if not same:
            raise FalsifyError(f"--resume: {key} differs from the run in {out} ({there!r} "
                               f"there, {here!r} now)")
    if cfg.epochs < int(ck.get("epoch", 0)):
        raise FalsifyError(f"--resume --epochs {cfg.epochs}: the run in {out} has trained "
                           f"{ck.get('epoch')} epochs already; give --epochs {ck.get('epoch')} "
                           "or more")


def _use_bf16(cfg: TrainConfig, torch) -> bool:
    """Whether to train under bf16 autocast: asked for, or auto where the device has bf16."""
    use_bf16 = cfg.precision == "bf16" or (cfg.precision == "auto" and bf16_supported())

    if cfg.device == "cuda" and cfg.precision == "auto":
        use_bf16 = torch.cuda.is_bf16_supported()
    return use_bf16


def _build(cfg: TrainConfig, files: list[Path], shape, torch):
    """A seeded SqueezeSeg on the device, its optimiser and the loss's class weights."""
    from falsify.models.squeezeseg import SqueezeSeg

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
    return model, opt, weights


def _restore(cfg: TrainConfig, model, opt, ckpt_path: Path, precision: str,
             torch) -> tuple[int, int, list[dict]]:
    """--resume: the checkpoint's model, optimiser and RNG, and its (epoch, step, log records),
    refused if it trained at another `precision` (bf16 or fp32: its weights would differ);
    --init: the weights only, from (0, 0); neither: (0, 0)."""
    epoch, step, log = 0, 0, []
    if cfg.resume:   # the checkpoint is there and of this run (_check_out)
        ck = _load(ckpt_path, "--resume", torch)
        if ck.get("precision", precision) != precision:
            raise FalsifyError(f"--resume: precision differs from the run in {cfg.out} "
                               f"({ck['precision']!r} there, {precision!r} now); pass "
                               f"--precision {ck['precision']}")
        try:
            model.load_state_dict(ck["model"])
            opt.load_state_dict(ck["optim"])
            epoch, step = int(ck["epoch"]), int(ck["step"])
            torch.set_rng_state(ck["torch_rng"])
            if cfg.device == "cuda" and "cuda_rng" in ck:
                torch.cuda.set_rng_state(ck["cuda_rng"])
            log = json.loads(ck["log"]) if "log" in ck else _read_log(Path(cfg.out))
        except (KeyError, RuntimeError, TypeError, ValueError) as exc:
            what = f"no {exc}" if isinstance(exc, KeyError) else str(exc).splitlines()[0]
            raise FalsifyError(f"--resume {ckpt_path}: not a whole training checkpoint of this "
                               f"run ({what}); train again into another --out") from None
    elif cfg.init:
        ck = _load(Path(cfg.init), "--init", torch)
        try:
            model.load_state_dict(ck.get("model", ck))
        except RuntimeError as exc:
            raise FalsifyError(f"--init {cfg.init}: not SqueezeSeg weights for these channels "
                               f"({str(exc).splitlines()[0]})") from exc
    return epoch, step, log


def _read_log(out: Path) -> list[dict]:
    """The records of train_log.jsonl (a checkpoint written before the log was kept in it)."""
    try:
        lines = (out / LOG).read_text(encoding="utf-8").splitlines()
    except OSError:
        return []
    log = []
    for line in lines:
        with contextlib.suppress(ValueError):
            log.append(json.loads(line))
    return log


def _write_log(out: Path, log: list[dict]) -> None:
    """train_log.jsonl, one line per record, written whole and atomically."""
    from falsify.fileio import write_text

    write_text(out / LOG, "".join(json.dumps(r) + "\n" for r in log))


def _train_epoch(cfg: TrainConfig, model, opt, weights, files: list[Path], shape, autocast,
                 run: _Progress, out_of_time) -> tuple[list[float], int, int, float]:
    """Train `run.epoch` from `run.step` to its end, or until --max-steps or the time limit
    (`out_of_time()`) stops it (`run.stopped`); returns its losses, frames, batches and
    seconds."""
    import torch

    n = len(files)
    rng = np.random.default_rng([cfg.seed, run.epoch])  # order and flips depend on epoch only
    perm = rng.permutation(n)
    flips = rng.random(n) < 0.5
    for g in opt.param_groups:
        g["lr"] = cfg.lr * cfg.lr_decay**run.epoch
    batches = [perm[i:i + cfg.batch] for i in range(0, n, cfg.batch)]
    losses, t_epoch, frames = [], time.monotonic(), 0
    while run.step < len(batches):
        idx = batches[run.step]
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
        if not math.isfinite(losses[-1]):
            raise diverged(cfg.out, cfg.lr, run.epoch + 1, f"the loss is {losses[-1]}")
        frames += len(idx)
        run.step += 1
        run.steps_run += 1
        if cfg.max_steps is not None and run.steps_run >= cfg.max_steps:
            run.stopped = "max_steps"
        elif out_of_time():
            run.stopped = "time_limit"
        if run.stopped != "done":
            break
    return losses, frames, len(batches), time.monotonic() - t_epoch


def diverged(out: str | Path, lr: float, epoch: int, what: str) -> FalsifyError:
    """The error that stops a diverged run (epoch counted from 1) before its NaN weights are
    saved: the epochs finished before it stay in --out's checkpoint."""
    kept = f"; epochs 1-{epoch - 1} stay in {out}" if epoch > 1 else ""
    return FalsifyError(f"epoch {epoch}: {what}, training diverged; lower --lr (now "
                        f"{lr:g}){kept}")


def _epoch_record(cfg: TrainConfig, run: _Progress, end_of_epoch: bool, batches: int,
                  losses: list[float], frames: int, sec: float, use_bf16: bool) -> dict:
    """The log line of an epoch (or of its part run before a stop)."""
    return {"epoch": run.epoch if end_of_epoch else run.epoch + run.step / batches,
            "loss": float(np.mean(losses)) if losses else None,
            "lr": cfg.lr * cfg.lr_decay**(run.epoch - 1 if end_of_epoch else run.epoch),
            "seconds": round(sec, 2),
            "ms_per_frame_step": round(1e3 * sec / max(frames, 1), 1),
            "precision": "bf16" if use_bf16 else "fp32"}


def _finish(cfg: TrainConfig, model, out: Path, shape, run: _Progress, torch) -> dict:
    """Write the final weights (and, unless --no-export, the ONNX model and its spec); the run's
    summary."""
    from falsify.models.export import export_onnx

    last = run.last
    final = model.to("cpu", memory_format=torch.contiguous_format).eval()
    summary = {"stopped": run.stopped, "epoch": run.epoch, "step": run.step, **{
        k: last.get(k) for k in ("loss", "val_car_iou")}}
    if cfg.export:   # the .pt beside the .onnx, both hashed in their one spec
        export_onnx(final, out / "squeezeseg.onnx", H=shape[0], W=shape[1], name="squeezeseg",
                    classes=None if cfg.classes == "kitti4" else "semantickitti",
                    weights=True, trained_epochs=run.epoch, seed=cfg.seed,
                    data=Path(cfg.data).name, val_car_iou=last.get("val_car_iou"))
    else:
        _save_atomic({k: v.contiguous() for k, v in final.state_dict().items()},
                     out / "squeezeseg.pt")
    return summary
