"""What `faithfulness --instances` says of the instances it skips holds on its own numbers.

A car of 3.04 m across was reported as "its points span 3.9 x 3.0 m, more than one car (7.0 x
3.0)": rounded to one decimal, the span no longer exceeded the limit it was skipped for.
"""

from __future__ import annotations

import json
import re

import pytest

from falsify.cli import main
from tests.conftest import FIT_SEQUENCES, MINI

SPAN = re.compile(r"its points span ([\d.]+) x ([\d.]+) m, more than one \w+ \(([\d.]+) x "
                  r"([\d.]+)\)")


@pytest.mark.skipif(not MINI.is_dir(), reason=f"SemanticKITTI mini scans not found at {MINI}")
def test_a_skipped_instances_span_as_printed_exceeds_the_limit(capsys) -> None:
    assert "05" in FIT_SEQUENCES   # fit data only
    assert main(["faithfulness", "--instances", str(MINI), "--sequences", "05", "--json"]) == 0
    skipped = json.loads(capsys.readouterr().out)["skipped"]
    spans = [SPAN.search(reason) for *_, reason in skipped]
    spans = [m for m in spans if m]
    assert spans, "sequence 05 holds an instance skipped for its span"
    for m in spans:
        length, width, max_length, max_width = (float(v) for v in m.groups())
        assert length > max_length or width > max_width, m.group(0)
