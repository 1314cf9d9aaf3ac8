"""Training: a tiny run writes checkpoints, logs and models; resume gives the same weights."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from falsify.cli import main as falsify_main  # noqa: E402
from falsify.errors import FalsifyError  # noqa: E402
from falsify.models.plausible import plausible_scans  # noqa: E402
from falsify.models.train import flip  # noqa: E402
from tests.models.conftest import copy_of  # noqa: E402

ARGS = ["--batch", "2", "--seed", "3", "--precision", "fp32", "--crf-iterations", "1"]


def main(argv: list[str]) -> int:
    """`falsify train ARGV`."""
    return falsify_main(["train", *argv])


def _weights(out):
    return torch.load(out / "squeezeseg.pt", weights_only=True)


@pytest.mark.slow
def test_train_writes_outputs_and_resume_is_exact(data, val, tmp_path):
    full = tmp_path / "full"
    assert main(["--data", str(data), "--out", str(full), "--epochs", "2",
                 "--val-data", str(val), *ARGS]) == 0
    for name in ("checkpoint.pt", "train_log.jsonl", "squeezeseg.pt", "squeezeseg.onnx",
                 "squeezeseg.json"):
        assert (full / name).is_file(), name
    log = [json.loads(line) for line in (full / "train_log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in log] == [1, 2]
    assert all(np.isfinite(r["loss"]) and 0 <= r["val_car_iou"] <= 1 for r in log)
    spec = json.loads((full / "squeezeseg.json").read_text())
    assert (spec["height"], spec["width"], spec["crf_iterations"]) == (64, 64, 1)
    # the .pt is written with the .onnx and hashed in their spec: torch never runs a .pt of
    # another training beside them (it was saved first and left out of the spec)
    from falsify.fileio import file_sha256
    assert spec["sha256"] == {"onnx": file_sha256(full / "squeezeseg.onnx"),
                              "pt": file_sha256(full / "squeezeseg.pt")}

    # interrupted after 3 of the 4 steps (mid epoch 2), then resumed
    part = tmp_path / "part"
    assert main(["--data", str(data), "--out", str(part), "--epochs", "2", "--max-steps", "3",
                 "--no-export", *ARGS]) == 0
    assert not (part / "squeezeseg.pt").exists()
    ck = torch.load(part / "checkpoint.pt", weights_only=True)
    assert (ck["epoch"], ck["step"]) == (1, 1)
    assert main(["--data", str(data), "--out", str(part), "--epochs", "2", "--resume",
                 "--no-export", *ARGS]) == 0
    a, b = _weights(full), _weights(part)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (torch.cuda."
                    "is_available() is False here)")
def test_resume_on_the_gpu_is_exact(data, tmp_path):
    """Dropout on a GPU draws from the device's generator: the checkpoint carries it, or the
    resumed epochs drop other units than the uninterrupted run."""
    gpu = [*ARGS, "--device", "cuda", "--no-export"]
    assert main(["--data", str(data), "--out", str(tmp_path / "full"), "--epochs", "2",
                 *gpu]) == 0
    part = tmp_path / "part"
    assert main(["--data", str(data), "--out", str(part), "--epochs", "2", "--max-steps", "3",
                 *gpu]) == 0
    assert main(["--data", str(data), "--out", str(part), "--epochs", "2", "--resume",
                 *gpu]) == 0
    a, b = _weights(tmp_path / "full"), _weights(part)
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_flip_negates_y_and_reverses_columns():
    s = plausible_scans(1, 8, 16, seed=0)[0]
    f = flip(s)
    np.testing.assert_array_equal(f[:, 0, 1], -s[:, -1, 1])
    np.testing.assert_array_equal(f[:, 0, [0, 2, 3, 4, 5]], s[:, -1, [0, 2, 3, 4, 5]])


def test_bad_data_dir_is_a_clear_error(tmp_path, capsys):
    assert main(["--data", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "no *.npy scans" in capsys.readouterr().err
    with pytest.raises(FalsifyError):
        from falsify.models.train import TrainConfig, train

        train(TrainConfig(data=str(tmp_path), out=str(tmp_path / "o")))


def test_unreadable_init_weights_exit_2_and_write_nothing(data, tmp_path, capsys):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    out = tmp_path / "o"
    assert main(["--data", str(data), "--out", str(out), "--init", str(bad), *ARGS]) == 2
    assert f"--init {bad}: cannot load weights" in capsys.readouterr().err
    assert not out.exists()


def test_crf_only_fine_tune_moves_only_the_compatibility(data, tmp_path):
    base = tmp_path / "base"
    assert main(["--data", str(data), "--out", str(base), "--epochs", "1", "--no-export",
                 *ARGS]) == 0
    tuned = tmp_path / "tuned"
    assert main(["--data", str(data), "--out", str(tuned), "--epochs", "1", "--no-export",
                 "--init", str(base / "squeezeseg.pt"), "--loss-on", "crf", "--crf-only",
                 "--lr", "0.05", *ARGS]) == 0
    a, b = _weights(base), _weights(tuned)
    changed = {k for k in a if not torch.equal(a[k], b[k])}
    assert changed and all(k.startswith("crf.") for k in changed)
    assert main(["--data", str(data), "--out", str(tmp_path / "x"), "--crf-only",
                 *ARGS]) == 2  # needs --loss-on crf


def _files(root) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


@pytest.mark.parametrize("argv, names", [
    (["--batch", "0"], "--batch"),
    (["--lr", "-1"], "--lr"),
    (["--lr", "nan"], "--lr"),
    (["--epochs", "0"], "--epochs"),
    (["--threads", "0"], "--threads"),
])
def test_bad_numbers_exit_2_and_write_nothing(data, tmp_path, capsys, argv, names):
    out = tmp_path / "o"
    assert main(["--data", str(data), "--out", str(out), *argv]) == 2
    assert names in capsys.readouterr().err
    assert not out.exists()


TRAINERS = pytest.mark.parametrize("trainer, args", [
    ("train", ARGS), ("train-pointnet", ["--batch", "2", "--points", "64", "--seed", "3"])])


@TRAINERS
def test_a_diverging_run_stops_with_exit_2_and_writes_nothing(data, tmp_path, capsys, trainer,
                                                              args):
    """A non-finite loss stops training before NaN weights are saved or exported."""
    out = tmp_path / "t"
    assert falsify_main([trainer, "--data", str(data), "--out", str(out), "--epochs", "2",
                         *args, "--lr", "1e12"]) == 2
    assert "epoch 1: the loss is nan, training diverged; lower --lr (now 1e+12)" in \
        capsys.readouterr().err
    assert not out.exists()


@TRAINERS
def test_out_an_existing_file_exits_2(data, tmp_path, capsys, trainer, args):
    afile = tmp_path / "afile"
    afile.write_text("mine\n")
    assert falsify_main([trainer, "--data", str(data), "--out", str(afile), *args]) == 2
    assert f"--out {afile}" in capsys.readouterr().err
    assert afile.read_text() == "mine\n"


def test_semantickitti_labels_need_classes_semantickitti(data, tmp_path, capsys):
    sk = copy_of(data, tmp_path / "sk", labels="semantickitti")
    out = tmp_path / "o"
    assert main(["--data", str(sk), "--out", str(out), *ARGS]) == 2
    err = capsys.readouterr().err
    assert f"--data {sk}" in err and "--classes semantickitti" in err
    assert not out.exists()


def test_out_holding_a_run_needs_resume_and_resume_keeps_the_options(data, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["--data", str(data), "--out", str(out), "--epochs", "1", "--max-steps", "1",
                 "--no-export", *ARGS]) == 0
    capsys.readouterr()
    before = {p: (out / p).read_bytes() for p in _files(out)}
    # without --resume: refused, the run untouched
    assert main(["--data", str(data), "--out", str(out), "--epochs", "1", *ARGS]) == 2
    err = capsys.readouterr().err
    assert f"--out {out} already holds a training run" in err and "--resume" in err
    # --resume with other options: refused naming the option and both values
    other = tmp_path / "other-scans"
    other.mkdir()
    for f in data.glob("*.npy"):
        (other / f.name).write_bytes(f.read_bytes())
    for argv, want in [(["--batch", "1"], "batch differs"), (["--lr", "0.01"], "lr differs"),
                       (["--seed", "4"], "seed differs"),
                       (["--channels", "x,y,z"], "channels differs")]:
        changed = dict(zip(ARGS[::2], ARGS[1::2], strict=True))
        changed.update(dict(zip(argv[::2], argv[1::2], strict=True)))
        flat = [v for kv in changed.items() for v in kv]
        assert main(["--data", str(data), "--out", str(out), "--epochs", "1", "--resume",
                     *flat]) == 2, argv
        err = capsys.readouterr().err
        assert want in err and f"the run in {out}" in err, err
    assert main(["--data", str(other), "--out", str(out), "--epochs", "1", "--resume",
                 *ARGS]) == 2
    assert "data differs" in capsys.readouterr().err
    assert {p: (out / p).read_bytes() for p in _files(out)} == before
    # more epochs with the same options is a resume
    assert main(["--data", str(data), "--out", str(out), "--epochs", "2", "--resume",
                 "--max-steps", "1", "--no-export", *ARGS]) == 0
