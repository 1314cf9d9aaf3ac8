"""`--no-retrain`: a run (a CI gate's) writes its maps, report and summary but not the
retraining set, which for a network with blind spots is hundreds of MB of scans (661 scans,
499 MB for `squeezeseg-v1` on the paper grid); an earlier finish's retrain/ goes with it."""

from __future__ import annotations

import json

from falsify.cli import main
from tests.runfixture import SMOKE


def test_no_retrain_leaves_the_set_out_and_says_so(tmp_path, capsys) -> None:
    run = tmp_path / "run"
    base = ["grid", str(SMOKE), "--out", str(run), "--quiet", "--threshold", "0.99"]
    assert main([*base, "--json"]) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["blind_spots"] == 4 and first["retraining_samples"] == 8
    assert "retraining_skipped" not in first
    assert len(list((run / "retrain").glob("*.npy"))) == 8

    # the same run finished again without the set: the last one's scans are not left beside
    assert main([*base, "--resume", "--no-retrain"]) == 0
    text = capsys.readouterr().out
    assert "retraining set: not written (--no-retrain)" in text
    assert not (run / "retrain").exists()
    summary = json.loads((run / "summary.json").read_text())
    assert summary["retraining_samples"] == 0 and summary["retraining_skipped"] is True
    assert summary["blind_spots"] == 4 and (run / "report.html").exists()
    assert main(["gate", str(run), "--max-blind-spots", "4"]) == 0


def test_no_retrain_with_what_shapes_the_set_is_refused_before_any_file(tmp_path,
                                                                         capsys) -> None:
    for extra, named in ((["--camera"], "--camera"),
                         (["--retrain-format", "semantickitti"], "--retrain-format")):
        out = tmp_path / "r"
        assert main(["grid", str(SMOKE), "--out", str(out), "--quiet", "--no-retrain",
                     *extra]) == 2
        err = capsys.readouterr().err
        assert f"{named} shapes the retraining set, which --no-retrain leaves unwritten" in err
        assert not out.exists()
