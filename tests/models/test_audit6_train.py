"""Training, adjust and export at the extremes: a stop at any point loses no finished step and
leaves no half-written file, the log survives a stop, bad input exits 2 naming it before anything
is written, and batches or data without a labelled pixel neither train nonsense nor read as a
diverged run."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from falsify.cli import main as falsify_main  # noqa: E402
from falsify.cli.signals import Terminated  # noqa: E402
from falsify.models import train as train_module  # noqa: E402
from falsify.models.spec import DEFAULT_CHANNELS  # noqa: E402
from falsify.models.squeezeseg import SqueezeSeg  # noqa: E402

ARGS = ["--batch", "2", "--seed", "3", "--precision", "fp32", "--crf-iterations", "1"]
PN_ARGS = ["--batch", "1", "--points", "64", "--seed", "3"]


@pytest.fixture(autouse=True)
def _no_holdout_from_env(monkeypatch):
    monkeypatch.delenv("FALSIFY_HOLDOUT", raising=False)


def _train(argv: list[str]) -> int:
    return falsify_main(["train", *argv])


def _log(out) -> list[dict]:
    return [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]


def _relabelled(data, folder, zero: list[int]):
    """A copy of `data` whose scans number `zero` (sorted) hold no labelled pixel."""
    folder.mkdir()
    for i, f in enumerate(sorted(data.glob("*.npy"))):
        scan = np.load(f)
        if i in zero:
            scan[..., 5] = 0
        np.save(folder / f.name, scan)
    return folder


@pytest.fixture
def weights(tmp_path):
    """A seeded SqueezeSeg state dict of our four classes."""
    torch.manual_seed(0)
    path = tmp_path / "w.pt"
    torch.save(SqueezeSeg(DEFAULT_CHANNELS, crf_iterations=1).state_dict(), path)
    return path


@pytest.mark.parametrize("int8", ["m.onnx", "m.pt"])
def test_export_int8_onto_the_fp32_files_is_refused(weights, tmp_path, capsys, int8):
    """--int8 naming --out (or its weights .pt) silently replaced the fp32 model by the int8."""
    out = tmp_path / "d" / "m.onnx"
    assert falsify_main(["export", str(weights), "--out", str(out), "--int8",
                         str(tmp_path / "d" / int8), "--calibration-scans", "1"]) == 2
    assert "--int8" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()


def test_export_beside_its_own_input_is_refused(weights, tmp_path, capsys):
    """`export RUN/checkpoint.pt --out RUN/checkpoint.onnx` wrote the weights-only .pt over the
    training checkpoint it read: the run could no longer resume."""
    before = weights.read_bytes()
    out = weights.with_suffix(".onnx")
    assert falsify_main(["export", str(weights), "--out", str(out)]) == 2
    assert f"which is the input {weights}" in capsys.readouterr().err
    assert weights.read_bytes() == before and not out.exists()


@pytest.mark.parametrize("command", ["export", "adjust"])
def test_weights_of_another_class_set_are_named_as_such(tmp_path, capsys, data, command):
    path = tmp_path / "sk.pt"
    torch.save(SqueezeSeg(DEFAULT_CHANNELS, num_classes=20).state_dict(), path)
    argv = ["--out", str(tmp_path / "m.onnx")] if command == "export" else \
        ["--val", str(data), "--out", str(tmp_path / "a.pt"), "--alphas", "0"]
    assert falsify_main([command, str(path), *argv]) == 2
    err = capsys.readouterr().err
    assert f"{path}: SqueezeSeg weights for 20 classes" in err and "needs 4 classes" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sk.pt"]


def test_adjust_out_a_directory_exits_2(weights, data, tmp_path, capsys):
    out = tmp_path / "x.pt"
    out.mkdir()
    assert falsify_main(["adjust", str(weights), "--val", str(data), "--out", str(out),
                         "--alphas", "0"]) == 2
    assert f"--out {out}: is a directory" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w.pt", "x.pt"]


def test_a_failing_write_leaves_no_half_file(weights, data, tmp_path, monkeypatch):
    """An export or a final weights file stopped mid-write leaves nothing at its path."""
    def half_export(model, args, f, **kw):
        with open(f, "wb") as fh:
            fh.write(b"half")
        raise Terminated()

    monkeypatch.setattr(torch.onnx, "export", half_export)
    out = tmp_path / "e" / "m.onnx"
    assert falsify_main(["export", str(weights), "--out", str(out)]) == 143
    assert sorted(p.name for p in out.parent.iterdir()) == []
    monkeypatch.undo()

    save = torch.save

    def half_save(obj, f, *a, **kw):
        if "squeezeseg" in str(f):
            with open(f, "wb") as fh:
                fh.write(b"half")
            raise Terminated()
        return save(obj, f, *a, **kw)

    monkeypatch.setattr(torch, "save", half_save)
    run = tmp_path / "run"
    with pytest.raises(Terminated):
        train_module.train(train_module.TrainConfig(
            data=str(data), out=str(run), epochs=1, batch=4, seed=3, precision="fp32",
            crf_iterations=1, export=False))
    assert sorted(p.name for p in run.iterdir()) == ["checkpoint.pt", "train_log.jsonl"]


def test_a_stop_during_validation_keeps_the_epoch_and_its_log_line(data, val, tmp_path, capsys,
                                                                     monkeypatch):
    """The checkpoint was written before validation, the log line after it: a SIGTERM while
    validating kept the epoch but lost its line for good."""
    full, part = tmp_path / "full", tmp_path / "part"
    argv = ["--data", str(data), "--epochs", "2", "--val-data", str(val), "--no-export", *ARGS]
    assert _train(["--out", str(full), *argv]) == 0
    validate = train_module.validate
    calls = []

    def stop_first(*a, **kw):
        calls.append(1)
        if len(calls) == 1:
            raise Terminated()
        return validate(*a, **kw)

    monkeypatch.setattr(train_module, "validate", stop_first)
    capsys.readouterr()
    assert _train(["--out", str(part), *argv]) == 143
    assert "saved in" in capsys.readouterr().err
    assert torch.load(part / "checkpoint.pt", weights_only=True)["epoch"] == 1
    assert [r["epoch"] for r in _log(part)] == [1]
    assert _train(["--out", str(part), *argv, "--resume"]) == 0
    assert [r["epoch"] for r in _log(part)] == [1, 2]
    assert [r["loss"] for r in _log(part)] == [r["loss"] for r in _log(full)]
    assert (part / "squeezeseg.pt").read_bytes() == (full / "squeezeseg.pt").read_bytes()
    assert not list(part.glob("*.tmp"))


def test_a_stop_before_the_first_checkpoint_leaves_nothing_and_says_so(data, tmp_path, capsys,
                                                                        monkeypatch):
    def stop(*a, **kw):
        raise Terminated()

    monkeypatch.setattr(train_module, "_train_epoch", stop)
    out = tmp_path / "run"
    assert _train(["--data", str(data), "--out", str(out), "--epochs", "1", *ARGS]) == 143
    err = capsys.readouterr().err
    assert "no checkpoint was saved" in err and "--resume" not in err, err
    assert not out.exists()


@pytest.mark.parametrize("trainer, args", [("train", ARGS), ("train-pointnet", PN_ARGS)])
def test_an_lr_beyond_float32_exits_2(data, tmp_path, capsys, trainer, args):
    """Adam's first step (10 x lr) overflowed float32: a RuntimeError traceback."""
    out = tmp_path / "o"
    assert falsify_main([trainer, "--data", str(data), "--out", str(out), *args,
                         "--lr", "1e39"]) == 2
    assert "--lr: 1e+39 must be a number > 0 and <= 1e+37" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("trainer, args", [
    ("train", [*ARGS, "--classes", "semantickitti"]), ("train-pointnet", PN_ARGS)])
def test_data_without_a_labelled_pixel_exits_2(data, tmp_path, capsys, trainer, args):
    """All class weights were 0: SqueezeSeg trained on a loss of 0 and exited 0, PointNet
    called it a divergence ('lower --lr')."""
    bare = _relabelled(data, tmp_path / "bare", [0, 1, 2, 3])
    out = tmp_path / "o"
    assert falsify_main([trainer, "--data", str(bare), "--out", str(out), "--epochs", "1",
                         *args]) == 2
    err = capsys.readouterr().err
    assert f"--data {bare}: no labelled pixel" in err and "lower --lr" not in err
    assert not out.exists()


def test_pointnet_skips_a_batch_without_a_labelled_point(data, tmp_path, capsys):
    """One scan without labels, batch 1: its step's loss was 0 / 0, read as a divergence."""
    some = _relabelled(data, tmp_path / "some", [0])
    out = tmp_path / "o"
    assert falsify_main(["train-pointnet", "--data", str(some), "--out", str(out), "--epochs",
                         "1", *PN_ARGS, "--json"]) == 0
    assert np.isfinite(json.loads(capsys.readouterr().out)["loss"])
    state = torch.load(out / "pointnet.pt", weights_only=True)
    assert all(bool(torch.isfinite(v).all()) for v in state.values())


def test_a_bad_validation_scan_is_refused_before_training(data, tmp_path, capsys):
    """It failed after the first epoch, its checkpoint written."""
    val = tmp_path / "val"
    val.mkdir()
    np.save(val / "a.npy", np.load(next(data.glob("*.npy")))[:, :32])
    out = tmp_path / "o"
    assert _train(["--data", str(data), "--val-data", str(val), "--out", str(out), *ARGS]) == 2
    assert f"--val-data: scan {val / 'a.npy'} has shape (64, 32, 6)" in capsys.readouterr().err
    assert not out.exists()


def test_resume_at_another_precision_is_refused(data, tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["--data", str(data), "--out", str(out), "--epochs", "1", "--max-steps", "1",
            "--no-export", *ARGS]
    assert _train(argv) == 0
    before = (out / "checkpoint.pt").read_bytes()
    capsys.readouterr()
    assert _train([*argv, "--resume", "--precision", "bf16"]) == 2
    assert "precision differs" in capsys.readouterr().err
    assert (out / "checkpoint.pt").read_bytes() == before


def test_train_json_is_one_document(data, tmp_path, capsys):
    out = tmp_path / "run"
    assert _train(["--data", str(data), "--out", str(out), "--epochs", "1", "--max-steps",
                   "1", "--no-export", "--json", *ARGS]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out) == {"stopped": "max_steps", "epoch": 0, "step": 1}
    assert json.loads(captured.err.splitlines()[0])["stopped"] == "max_steps"


@pytest.mark.parametrize("trainer", ["train", "train-pointnet"])
def test_a_checkpoint_missing_a_part_exits_2_naming_it(data, tmp_path, capsys, trainer):
    """A checkpoint whose options match but whose optimiser state is gone: a KeyError."""
    out = tmp_path / "run"
    argv = [trainer, "--data", str(data), "--out", str(out), "--epochs", "1", *(
        ["--max-steps", "1", "--no-export", *ARGS] if trainer == "train" else PN_ARGS)]
    assert falsify_main(argv) == 0
    ck = torch.load(out / "checkpoint.pt", weights_only=True)
    del ck["optim"]
    torch.save(ck, out / "checkpoint.pt")
    capsys.readouterr()
    assert falsify_main([*argv, "--resume"]) == 2
    assert f"--resume {out / 'checkpoint.pt'}: not a whole training checkpoint" in \
        capsys.readouterr().err
