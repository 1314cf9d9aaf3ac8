"""What a retraining experiment found: the records its stages keep in stages.json, the held-out
checks, the blind cells before and after, the issue's success criteria, and the summary's
terminal text."""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from falsify.errors import ConfigError
from falsify.results.store import open_run

MAX_CAR_IOU_DROP = 0.01      # the bound on a regression check (the paper: 60.8 -> 60.6)
MIN_BLIND_CELLS = 5          # the experiment needs at least this many blind cells before
MIN_FIXED_SHARE = 0.8        # of which at least this share must reach the threshold after
GRID_FIGURES = ("run", "samples", "ok", "invalid", "cells", "blind_spots", "mean_car_iou",
                "elapsed_s", "model_hash")

R = TypeVar("R")


def rounded(v: float | None) -> float | None:
    """4 decimals; None for None or NaN."""
    return None if v is None or (isinstance(v, float) and math.isnan(v)) else round(float(v), 4)


def read_record(cls: type[R], data: dict) -> R:
    """A stage's record from its JSON in stages.json (keys it does not know are passed over)."""
    names = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: v for k, v in data.items() if k in names})


def as_json(record: Any) -> Any:
    """A stage's record as stages.json keeps it: a dataclass as a dict in field order."""
    return asdict(record) if dataclasses.is_dataclass(record) else record


@dataclass(frozen=True)
class GridRecord:
    """A grid stage (before, rows, after): its run's figures from the run's summary."""

    run: str
    samples: int
    ok: int
    invalid: int
    cells: int
    blind_spots: int
    mean_car_iou: float | None
    elapsed_s: float | None
    model_hash: str | None

    @classmethod
    def of(cls, summary) -> GridRecord:
        return cls(*(getattr(summary, k) for k in GRID_FIGURES))


@dataclass(frozen=True)
class SelectedRecord:
    """The selected stage: V's blind cells, what chose R's scans, and how many were written."""

    cells: list[dict] = field(default_factory=list)   # V's blind cells: x, y, miou
    selection: str = "blind"
    control_cells: list[dict] | None = None   # control: the cells drawn instead
    rules: list[str] | None = None            # rules/random: explain's rules on V, as text
    region: list[int] | None = None           # rules/random: V's eval indices under the rules
    scans: int = 0
    folder: str = ""


@dataclass(frozen=True)
class FinetuneRecord:
    """The finetune stage: the fine-tuned model and what it was trained on."""

    model: str
    training_scans: int
    selected_scans: int
    oversample: int
    scans_per_epoch: int
    epochs: int
    stopped: Any
    epoch_reached: Any
    loss: Any
    log: str


@dataclass(frozen=True)
class Check:
    """Pooled car IoU of the model before and after fine-tuning on one held-out set."""

    name: str
    scans: int
    before: float | None
    after: float | None
    note: str = ""

    @property
    def change(self) -> float | None:
        return None if self.before is None or self.after is None else self.after - self.before

    @property
    def passed(self) -> bool | None:
        """Car IoU dropped by at most MAX_CAR_IOU_DROP (None when the set was not available)."""
        c = self.change
        return None if c is None else c >= -MAX_CAR_IOU_DROP - 1e-12

    def to_json(self) -> dict:
        return {**asdict(self), "change": rounded(self.change), "passed": self.passed}


@dataclass(frozen=True)
class CellChange:
    x: float
    y: float
    before: float
    after: float | None

    def to_json(self) -> dict:
        return {"x": self.x, "y": self.y, "miou_before": rounded(self.before),
                "miou_after": rounded(self.after)}


@dataclass(frozen=True)
class RetrainResult:
    """What the experiment found; `criteria` holds the issue's success criteria, each a bool."""

    out: str
    threshold: float
    selection: str                    # one of SELECTIONS
    computed: tuple[str, ...]         # stages run this time
    reused: tuple[str, ...]           # stages read back from stages.json
    cells: int
    blind_before: tuple[CellChange, ...]
    blind_after: int | None
    fixed: int | None
    retraining_scans: int
    mean_before: float | None
    mean_after: float | None
    training: dict
    checks: tuple[Check, ...]
    criteria: dict
    model_after: str | None
    report: str | None
    summary: str | None
    files: dict = field(default_factory=dict)
    region: dict | None = None        # rules/random: V's samples under the rules, before/after

    def to_json(self) -> dict:
        d = asdict(self)
        d["blind_before"] = [c.to_json() for c in self.blind_before]
        d["checks"] = [c.to_json() for c in self.checks]
        d["computed"], d["reused"] = list(self.computed), list(self.reused)
        return d


def result_of(out: Path, selection: str, thr: float, done: dict, computed: tuple[str, ...],
              reused: tuple[str, ...]) -> RetrainResult:
    """The result from the stages' records in `done` (those done so far)."""
    sel = read_record(SelectedRecord, done.get("selected", {}))
    blind_cells = sel.cells
    after_map = None
    if "after" in done:
        after_map = open_run(out / "after").cell_map()
    lookup = {}
    if after_map is not None:
        for j, y in enumerate(after_map.b_values):
            for i, x in enumerate(after_map.a_values):
                lookup[(float(x), float(y))] = float(after_map.miou[j, i])
    changes = tuple(CellChange(c["x"], c["y"], c["miou"],
                               lookup.get((float(c["x"]), float(c["y"]))))
                    for c in blind_cells)
    fixed = None if after_map is None else sum(
        1 for c in changes if c.after is not None and c.after >= thr)
    checks = tuple(Check(**c) for c in done.get("checks", {}).get("checks", []))
    mean_b = _cell_mean(open_run(out / "before").cell_map()) if "before" in done else None
    mean_a = None if after_map is None else _cell_mean(after_map)
    criteria = {
        f"at_least_{MIN_BLIND_CELLS}_blind_cells_before": len(blind_cells) >= MIN_BLIND_CELLS,
        f"at_least_{int(MIN_FIXED_SHARE * 100)}pct_fixed": None if fixed is None or
        not blind_cells else fixed >= MIN_FIXED_SHARE * len(blind_cells),
        "mean_not_dropping": None if mean_a is None or mean_b is None
        else mean_a >= mean_b - 1e-9,
        f"held_out_drops_at_most_{MAX_CAR_IOU_DROP}": None if not checks else
        (all(c.passed for c in checks if c.passed is not None)
         if any(c.passed is not None for c in checks) else None),
    }
    files = done.get("report", {}).get("files", {})
    region = None
    if sel.region is not None:
        region = {"rules": sel.rules, "samples": len(sel.region),
                  **{f"{k}_{when}": v for when in ("before", "after") if when in done
                     for k, v in region_figures(open_run(out / when), sel.region,
                                                thr).items()}}
    return RetrainResult(
        out=str(out), threshold=thr, selection=selection, computed=computed,
        reused=reused,
        cells=int(read_record(GridRecord, done["before"]).cells) if "before" in done else 0,
        blind_before=changes,
        blind_after=None if after_map is None else len(after_map.blind_spots(thr)),
        fixed=fixed, retraining_scans=int(sel.scans),
        mean_before=rounded(mean_b), mean_after=rounded(mean_a),
        training=done.get("finetune", {}), checks=checks, criteria=criteria,
        model_after=(read_record(FinetuneRecord, done["finetune"]).model
                     if "finetune" in done else None),
        report=files.get("report"), summary=files.get("summary"), files=files,
        region=region)


def region_figures(run, region: Sequence[int], threshold: float) -> dict:
    """Mean score and samples below the threshold of a run's valid samples in `region`
    (eval indices): the region's state before or after fine-tuning."""
    ok = run.ok
    score = ok[run.score_column][ok["eval_index"].isin(region)]
    return {"mean": rounded(float(score.mean())) if len(score) else None,
            "below": int((score < threshold).sum())}


def _cell_mean(cmap) -> float | None:
    """Mean of the cell mIoUs (every cell weighs the same, as in the paper's map)."""
    v = cmap.miou[np.isfinite(cmap.miou)]
    return float(v.mean()) if v.size else None


def read_summary(path: Path, option: str) -> dict:
    """A `falsify retrain` summary.json; FalsifyError naming the option and file otherwise."""
    try:
        summary = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{option} {path}: not a readable summary ({exc})") from None
    if not isinstance(summary, dict) or "blind_before" not in summary:
        raise ConfigError(f"{option} {path}: not a `falsify retrain` summary.json")
    return summary


WHERE = {"blind": "at the blind cells",
         "control": "control: at as many random cells that are not blind",
         "rules": "under the rules explain finds on V's failing samples",
         "random": "control: as many of R's samples as the rules take, drawn at random"}


def result_text(r: RetrainResult) -> str:
    """The result as a few lines for the terminal."""
    lines = [f"retraining experiment in {r.out} (threshold {r.threshold}; stages run now: "
             f"{', '.join(r.computed) or 'none'}; reused: {', '.join(r.reused) or 'none'})",
             f"blind cells before: {len(r.blind_before)} of {r.cells}; retraining scans: "
             f"{r.retraining_scans} ({WHERE[r.selection]})"]
    if r.fixed is not None:
        lines.append(f"after: {r.fixed} of {len(r.blind_before)} at or above the threshold, "
                     f"{r.blind_after} blind cells; mean cell mIoU {r.mean_before} -> "
                     f"{r.mean_after}")
    if r.region is not None:
        lines.append(f"region under the rules ({'; '.join(r.region['rules'] or []) or 'none'}):"
                     f" {r.region['samples']} of V's samples, mean {r.region.get('mean_before')}"
                     f" -> {r.region.get('mean_after')}, below the threshold "
                     f"{r.region.get('below_before')} -> {r.region.get('below_after')}")
    for c in r.checks:
        if c.before is None:
            lines.append(f"check {c.name}: {c.note}")
        else:
            lines.append(f"check {c.name} ({c.scans} scans): car IoU {c.before:.4f} -> "
                         f"{c.after:.4f} ({c.change:+.4f})")
    lines.append("criteria: " + ", ".join(f"{k}={v}" for k, v in r.criteria.items()))
    if r.report:
        lines.append(f"report: {r.report}")
    return "\n".join(lines)
