"""A command that writes several files, killed between two of them (SIGKILL, or SIGTERM's clean
stop), leaves files of one run only: never a new file beside the last run's that a reader takes
as belonging with it. Each test runs the real command in a child process that sends itself the
signal just before a chosen file takes its final name (every write ends in os.replace), as
tests/cli/test_audit8_sigterm.py stops a command."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from falsify.errors import FalsifyError
from falsify.models.plausible import plausible_scans
from falsify.models.runners import WEIGHTS_DIR, load_segmenter

ROOT = Path(__file__).resolve().parents[2]

# argv: [names, n, signal, falsify's argv]: killed before the n-th rename onto one of `names`
KILLER = """
import json, os, sys, time
from pathlib import Path

names, nth, sig, argv = json.loads(sys.argv[1])
real, seen = os.replace, []

def replace(src, dst, *a, **k):
    if Path(dst).name in names:
        seen.append(str(dst))
        if len(seen) == nth:
            os.kill(os.getpid(), sig)
            time.sleep(60)
    return real(src, dst, *a, **k)

os.replace = replace
from falsify.cli import main
sys.exit(main(argv))
"""


def killed(argv: list[str], names: list[str], nth: int,
           sig: int = signal.SIGKILL) -> subprocess.CompletedProcess:
    """`falsify ARGV` in a child, sent `sig` just before its `nth` file of `names` is placed."""
    done = subprocess.run([sys.executable, "-c", KILLER, json.dumps([names, nth, sig, argv])],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert done.returncode == (-signal.SIGKILL if sig == signal.SIGKILL else 143), done.stderr
    return done


def falsify(argv: list[str]) -> str:
    done = subprocess.run([sys.executable, "-m", "falsify", *argv], capture_output=True,
                          text=True, timeout=300, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    return done.stdout


def visible(folder: Path) -> dict[str, bytes]:
    """Every file under `folder` (by relative path) but temporaries (hidden names)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not any(q.startswith(".") for q in p.relative_to(folder).parts)}


def none_of(before: dict[str, bytes], after: dict[str, bytes]) -> list[str]:
    """The files of `after` that are still the last run's (same bytes as in `before`)."""
    return [k for k, v in after.items() if before.get(k) == v]


# -- export: the spec records its files' hashes; a reader refuses a file that is not its own ---
def _copy_export(src: Path, dst: Path) -> None:
    dst.mkdir(parents=True, exist_ok=True)
    for ext in (".onnx", ".json", ".pt"):
        shutil.copyfile(src.with_suffix(ext), dst / f"m{ext}")


@pytest.fixture(scope="module")
def exports(tmp_path_factory) -> dict[str, Path]:
    """An earlier export (the bundled squeezeseg-v1, whose spec has no hashes: an older
    falsify's) and, for comparison, a whole new one of other weights under the same name."""
    pytest.importorskip("torch")
    if not (WEIGHTS_DIR / "squeezeseg-v1.pt").is_file():
        pytest.skip("the bundled weights are not installed")
    root = tmp_path_factory.mktemp("exports")
    _copy_export(WEIGHTS_DIR / "squeezeseg-v1.onnx", root / "old")
    falsify(["export", str(WEIGHTS_DIR / "squeezeseg.pt"), "--out", str(root / "new" / "m.onnx")])
    return {"old": root / "old", "new": root / "new"}


@pytest.mark.slow   # an export per stop (~6 s each)
@pytest.mark.parametrize(("nth", "sig"), [(2, signal.SIGKILL), (3, signal.SIGKILL),
                                          (3, signal.SIGTERM)])
def test_export_stopped_between_its_files_is_refused_not_run_half_old(exports, tmp_path, nth,
                                                                      sig) -> None:
    """`falsify export W.pt --out m.onnx` over an earlier export, stopped between its files
    (before: .onnx, spec, .pt in turn, so a stop before the .pt left the old .pt beside the
    new spec, and `--backend torch` ran it). Now each runner loads its file only where the
    spec was written with it, else says to export again; both pairs load once finished."""
    d = tmp_path / "d"
    _copy_export(exports["old"] / "m.onnx", d)
    killed(["export", str(WEIGHTS_DIR / "squeezeseg.pt"), "--out", str(d / "m.onnx")],
           ["m.onnx", "m.json", "m.pt"], nth, sig)

    def origin(name: str) -> str:
        data = (d / name).read_bytes()
        runs = [k for k in ("old", "new") if (exports[k] / name).read_bytes() == data]
        assert len(runs) == 1, name   # a whole file of one export, never a half
        return runs[0]

    spec = origin("m.json")
    assert spec == "new"   # stopped after the spec: the state the order is chosen for
    mixed = False
    for backend, name in (("onnx", "m.onnx"), ("torch", "m.pt")):
        if origin(name) == spec:
            load_segmenter(d / "m.onnx", backend=backend, threads=1).predict(plausible_scans(1))
        else:
            mixed = True
            with pytest.raises(FalsifyError) as err:
                load_segmenter(d / "m.onnx", backend=backend, threads=1)
            msg = str(err.value)
            assert str(d / name) in msg and str(d / "m.json") in msg and "export again" in msg
            assert "\n" not in msg
    assert mixed
    if sig == signal.SIGTERM:   # the clean stop leaves no temporary either
        assert sorted(p.name for p in d.iterdir()) == ["m.json", "m.onnx", "m.pt"]


@pytest.mark.slow   # the export's graph is made before the stop (~14 s)
def test_export_int8_stopped_before_its_first_file_keeps_no_old_int8(tmp_path) -> None:
    """`falsify export W.pt --out m.onnx --int8 q.onnx` over an earlier export with its int8
    copy, stopped before its first file: the old q.onnx was kept beside what followed."""
    pytest.importorskip("torch")
    if not (WEIGHTS_DIR / "squeezeseg-int8.onnx").is_file():
        pytest.skip("the bundled weights are not installed")
    d = tmp_path / "d"
    _copy_export(WEIGHTS_DIR / "squeezeseg-v1.onnx", d)
    for ext in (".onnx", ".json"):
        shutil.copyfile(WEIGHTS_DIR / f"squeezeseg-int8{ext}", d / f"q{ext}")
    killed(["export", str(WEIGHTS_DIR / "squeezeseg.pt"), "--out", str(d / "m.onnx"), "--int8",
            str(d / "q.onnx"), "--calibration-scans", "1"], ["m.onnx", "m.json", "m.pt"], 1)
    assert sorted(visible(d)) == ["m.json", "m.onnx", "m.pt"]


def test_a_spec_without_hashes_still_loads_and_a_bad_hash_key_is_named(tmp_path) -> None:
    """Bundled and hand-written specs (no "sha256") load unchecked; a malformed one exits 2."""
    from falsify.models.spec import load_spec

    for f in sorted(WEIGHTS_DIR.glob("*.onnx")):
        assert not load_segmenter(f, threads=1).spec.sha256, f
    spec = json.loads((WEIGHTS_DIR / "squeezeseg.json").read_text())
    (tmp_path / "s.json").write_text(json.dumps({**spec, "sha256": {"tflite": "0" * 64}}))
    with pytest.raises(FalsifyError, match="key 'sha256' has unknown file 'tflite'; allowed: "
                       "onnx, pt"):
        load_spec(tmp_path / "s.json")
    (tmp_path / "s.json").write_text(json.dumps({**spec, "sha256": {"onnx": "abc"}}))
    with pytest.raises(FalsifyError, match="'onnx' must be 64 lowercase hex digits"):
        load_spec(tmp_path / "s.json")


def _hashed_copy(tmp_path: Path, onnx_hash: str | None = None) -> Path:
    """The bundled network and its spec copied, the spec recording `onnx_hash` (default: the
    copy's own) and its .pt's."""
    from falsify.fileio import file_sha256

    m = tmp_path / "m.onnx"
    tmp_path.mkdir(parents=True)
    shutil.copyfile(WEIGHTS_DIR / "squeezeseg.onnx", m)
    shutil.copyfile(WEIGHTS_DIR / "squeezeseg.pt", m.with_suffix(".pt"))
    spec = json.loads((WEIGHTS_DIR / "squeezeseg.json").read_text())
    spec["sha256"] = {"onnx": onnx_hash or file_sha256(m), "pt": file_sha256(m.with_suffix(".pt"))}
    m.with_suffix(".json").write_text(json.dumps(spec))
    return m


def test_every_reader_of_a_model_and_its_spec_checks_the_pair(tmp_path) -> None:
    """The runners, realism's encoder and the fp16 / int8 converters refuse an .onnx that is
    not the one its spec was exported with; a converted model's spec records its own hash."""
    from falsify.fileio import file_sha256
    from falsify.jobs.realism import EncoderFeatures
    from falsify.models.export import convert_fp16
    from falsify.models.spec import load_spec

    pytest.importorskip("onnx")
    good = _hashed_copy(tmp_path / "good")
    fp16 = convert_fp16(good, tmp_path / "h" / "m16.onnx")
    assert load_spec(fp16.with_suffix(".json")).sha256 == {"onnx": file_sha256(fp16)}
    load_segmenter(fp16, threads=1)
    EncoderFeatures(good)
    bad = _hashed_copy(tmp_path / "bad", "0" * 64)
    for read in (lambda: load_segmenter(bad, threads=1), lambda: EncoderFeatures(bad),
                 lambda: convert_fp16(bad, tmp_path / "b16.onnx")):
        with pytest.raises(FalsifyError, match="export again"):
            read()
    assert not (tmp_path / "b16.onnx").exists()


# -- realism: realism.json and realism.html -------------------------------------------------------
@pytest.fixture(scope="module")
def scan_sets(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("sets")
    out = {}
    for name, seed in (("syn", 1), ("real", 2)):
        out[name] = root / name
        out[name].mkdir()
        for i, s in enumerate(plausible_scans(2, seed=seed)):
            np.save(out[name] / f"{i:06d}.npy", s)
    return out


def test_realism_stopped_between_its_files_keeps_none_of_the_last_runs(scan_sets,
                                                                        tmp_path) -> None:
    """Before: realism.json, then realism.html; killed between them, the new json stood beside
    the last run's page."""
    out = tmp_path / "out"
    argv = ["realism", str(scan_sets["syn"]), "--real", str(scan_sets["real"]), "--out",
            str(out)]
    falsify(argv)
    before = visible(out)
    assert sorted(before) == ["realism.html", "realism.json"]
    killed([*argv, "--scans", "1"], ["realism.json", "realism.html"], 2)
    assert none_of(before, visible(out)) == []


# -- scan: scan.npy, .png, .bin, .label ---------------------------------------------------------
@pytest.mark.parametrize("nth", [2, 4])
def test_scan_stopped_between_its_files_keeps_none_of_the_last_sample(tmp_path, nth) -> None:
    """Before: the new scan.npy stood beside the last sample's scan.bin and .label."""
    out, config = tmp_path / "out", str(ROOT / "configs" / "smoke.toml")
    falsify(["scan", config, "--out", str(out), "--set", "x=2", "--set", "y=8"])
    before = visible(out)
    names = ["scan.npy", "scan.png", "scan.bin", "scan.label"]
    assert sorted(before) == sorted([*names, "scan-files.json"])
    killed(["scan", config, "--out", str(out), "--set", "x=-2", "--set", "y=10"], names, nth)
    after = visible(out)
    assert none_of(before, after) == [] and len(after) == nth   # with the list of this run's
    # the stopped scan's own files are listed, so the rerun replaces them and is not refused
    falsify(["scan", config, "--out", str(out), "--set", "x=-2", "--set", "y=10"])
    assert sorted(visible(out)) == sorted([*names, "scan-files.json"])


# -- predict: X.pred.npy and X.png per scan ------------------------------------------------------
def test_predict_stopped_between_its_files_keeps_none_of_the_last_runs(tmp_path) -> None:
    """Before: each scan's .pred.npy and .png were replaced in turn, so a stop left the new
    prediction beside the last run's picture and other scans' old outputs; a run on fewer
    scans kept the others' outputs too."""
    scans = tmp_path / "scans"
    scans.mkdir()
    for i, s in enumerate(plausible_scans(2, seed=3)):
        np.save(scans / f"s{i}.npy", s)
    out = tmp_path / "out"
    falsify(["predict", str(scans), "--out", str(out), "--model", "squeezeseg"])
    before = visible(out)
    assert sorted(before) == ["s0.png", "s0.pred.npy", "s1.png", "s1.pred.npy"]
    again = ["predict", str(scans / "s0.npy"), "--out", str(out), "--model", "squeezeseg-v1"]
    killed(again, ["s0.pred.npy", "s0.png"], 2)
    assert none_of(before, visible(out)) == [] and sorted(visible(out)) == ["s0.pred.npy"]
    falsify(again)
    assert sorted(visible(out)) == ["s0.png", "s0.pred.npy"]


# -- tradeoff: tradeoff.csv, .json, .html and OUT/models/ ----------------------------------------
@pytest.mark.slow   # two trade-off runs and a stopped one (~40 s)
def test_tradeoff_keeps_no_file_of_the_last_run(tmp_path) -> None:
    """Before: a run killed between its files left the new csv beside the last run's json, html
    and models, and a run with fewer knobs kept the last one's models in OUT/models/."""
    pytest.importorskip("torch")   # the CRF knob's models are exported
    from tests.bench.test_tradeoff import CONFIG

    config = tmp_path / "tiny.toml"
    config.write_text(CONFIG)
    out = tmp_path / "out"
    falsify(["tradeoff", str(config), "--out", str(out), "--knobs", "crf", "--limit", "1"])
    before = visible(out)
    assert "models/squeezeseg-crf0.onnx" in before
    (out / "models" / "notes.txt").write_text("mine")   # a user's file stays
    again = ["tradeoff", str(config), "--out", str(out), "--knobs", "lod", "--limit", "1"]
    killed(again, ["tradeoff.csv", "tradeoff.json", "tradeoff.html"], 2)
    assert none_of(before, visible(out)) == []
    assert sorted(visible(out)) == ["models/notes.txt", "tradeoff.csv"]
    falsify(again)
    assert sorted(visible(out)) == ["models/notes.txt", "tradeoff.csv", "tradeoff.html",
                                    "tradeoff.json"]
    assert json.loads((out / "tradeoff.json").read_text())["knobs"] == ["lod"]


# -- grid: a resume at another threshold killed while finishing leaves no stale summary -------
@pytest.mark.skipif(not (WEIGHTS_DIR / "squeezeseg.onnx").exists(), reason="no bundled model")
def test_a_grid_finishing_again_leaves_no_summary_of_the_last_threshold(tmp_path: Path) -> None:
    """`grid --resume --threshold T` redraws a finished run's outputs at T; killed before its
    maps, it left the last summary.json and report.html (another threshold's blind spots)
    beside what it wrote; they go first now, and the summary comes last."""
    run = tmp_path / "run"
    argv = ["grid", "configs/smoke.toml", "--out", str(run), "--quiet"]
    falsify(argv)
    assert json.loads((run / "summary.json").read_text())["threshold"] == 0.65
    killed([*argv, "--resume", "--threshold", "0.99"], ["miou_x_y.csv"], 1)
    assert not (run / "summary.json").exists() and not (run / "report.html").exists()
    killed([*argv, "--resume", "--threshold", "0.99"], ["summary.json"], 1)
    assert (run / "report.html").exists() and not (run / "summary.json").exists()
    falsify([*argv, "--resume", "--threshold", "0.99"])
    summary = json.loads((run / "summary.json").read_text())
    assert summary["threshold"] == 0.99 and "report" not in summary
