"""`bench search` refuses a budget too small for an NLopt algorithm before any run: it found out
only after the dense grid and the algorithms before it had run."""

from __future__ import annotations

from pathlib import Path

from falsify.cli import main
from tests.conftest import CONFIGS


def test_a_budget_below_nlopts_combinations_is_refused_first(tmp_path: Path, capsys) -> None:
    out = tmp_path / "bench"
    assert main(["bench", "search", "--config", str(CONFIGS / "smoke.toml"), "--out",
                 str(out)]) == 2
    err = capsys.readouterr().err
    assert "a budget of 1 evaluation is smaller than the 2 combinations" in err
    assert "--fraction of at least 0.25" in err
    assert not out.exists()
