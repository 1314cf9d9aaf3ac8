"""Robustness in the field's own terms: per effect and severity the network's mean score, and
the corruption error and resilience rate against a reference network (mCE, mRR).

Definitions as Robo3D gives them (Kong et al., "Robo3D: Towards Robust and Reliable 3D
Perception against Corruptions", ICCV 2023, Sec. 3.2), after ImageNet-C (Hendrycks and
Dietterich, ICLR 2019), with the score s (an IoU) at each severity l of effect e:

    CE_e = sum_l (1 - s_{e,l}) / sum_l (1 - s^ref_{e,l})        mCE = mean_e CE_e
    RR_e = sum_l s_{e,l} / (L_e * s_clean)                      mRR = mean_e RR_e

A run holds the rows of one space; the rows whose effect dims are all zero are the clean ones,
and those with exactly one effect non-zero are that effect at that severity (a factorial space
also holds mixed rows, which are left out and counted). Robo3D scores mIoU over classes; here the
score is the placed object's IoU (`inserted_iou`, the background's own objects left out; in runs
scored without it, the run's objective) unless another column is named.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from falsify.errors import FalsifyError
from falsify.results.metrics import Status
from falsify.results.store import RunData, check_complete, open_run
from falsify.world.space import EFFECT_DIMS


@dataclass(frozen=True)
class Level:
    """One effect at one severity: the run's mean score, its rows, the reference's mean."""

    severity: float
    score: float | None    # None: no valid sample at this severity (every row undefined)
    samples: int
    reference: float | None = None

    def to_json(self) -> dict:
        return {"severity": self.severity,
                "score": None if self.score is None else round(self.score, 4),
                "samples": self.samples,
                "reference": None if self.reference is None else round(self.reference, 4)}


@dataclass(frozen=True)
class EffectRobustness:
    """An effect's levels, its corruption error (None without a reference) and its resilience."""

    effect: str
    levels: tuple[Level, ...]
    ce: float | None
    rr: float | None       # None: a severity without a valid sample
    note: str = ""         # why CE or RR is undefined, when one is (beyond "no --reference")

    def to_json(self) -> dict:
        return {"effect": self.effect, "levels": [lv.to_json() for lv in self.levels],
                "ce": None if self.ce is None else round(self.ce, 4),
                "rr": None if self.rr is None else round(self.rr, 4), "note": self.note}


@dataclass(frozen=True)
class RobustnessResult:
    """The run's robustness per effect and overall."""

    run: str
    reference: str | None
    column: str
    clean: float
    clean_samples: int
    clean_reference: float | None
    effects: tuple[EffectRobustness, ...]
    mixed_samples: int          # rows with two or more effects at once, left out
    mce: float | None
    mrr: float | None           # None when an effect's RR is undefined (see its note)

    def to_json(self) -> dict:
        return {"run": self.run, "reference": self.reference, "column": self.column,
                "clean": round(self.clean, 4), "clean_samples": self.clean_samples,
                "clean_reference": None if self.clean_reference is None
                else round(self.clean_reference, 4),
                "effects": [e.to_json() for e in self.effects],
                "mixed_samples": self.mixed_samples,
                "mce": None if self.mce is None else round(self.mce, 4),
                "mrr": None if self.mrr is None else round(self.mrr, 4),
                "definitions": "CE_e = sum_l (1 - s_el) / sum_l (1 - s_ref_el), mCE its mean; "
                               "RR_e = sum_l s_el / (L_e s_clean), mRR its mean (Robo3D, "
                               "ICCV 2023)"}


def score_column(data: RunData, column: str | None) -> str:
    """The named column, else the placed object's IoU (inserted_iou), else the objective's."""
    if column is not None:
        if column not in data.frame.columns:
            raise FalsifyError(f"--column {column!r}: not a column of {data.path}; allowed: "
                               + ", ".join(c for c in data.frame.columns if c.endswith("_iou")))
        return column
    return "inserted_iou" if "inserted_iou" in data.frame.columns else data.score_column


def levels_of(data: RunData, column: str) -> tuple[pd.Series, dict[str, dict[float, pd.Series]],
                                                     int]:
    """(clean scores, {effect: {severity: scores}}, mixed rows) over the ok rows with a score;
    a severity the run holds rows of but none valid keeps an empty Series, so that it is
    reported undefined rather than dropped (dropping it would shrink Robo3D's L unsaid)."""
    effects = [d for d in EFFECT_DIMS if d in data.space.dims]
    if not effects:
        raise FalsifyError(f"{data.path}: its space has no effect dim (one of "
                           f"{', '.join(EFFECT_DIMS)}); robustness needs the same space with "
                           "and without them")
    every = data.frame[effects].astype(float).fillna(0.0)
    every_active = (every != 0).sum(axis=1)
    scored = (data.frame["status"] == Status.OK) & data.frame[column].notna()
    f = data.frame[scored]
    values, active = every[scored], every_active[scored]
    clean = f[active == 0][column].astype(float)
    if not len(clean):
        n = int((every_active == 0).sum())
        if n:
            raise FalsifyError(f"{data.path}: none of its {n} rows without effects has a valid "
                               f"{column}; nothing to compare the effects with")
        raise FalsifyError(f"{data.path}: no row without effects (every effect dim at 0) to "
                           "compare with; add 0 to each effect dim's values")
    out: dict[str, dict[float, pd.Series]] = {}
    for e in effects:
        single = (every_active == 1) & (every[e] != 0)
        rows = f[single[scored]]
        groups = {float(sev): g.astype(float)
                  for sev, g in rows.groupby(values.loc[rows.index, e])[column]}
        out[e] = {float(sev): groups.get(float(sev), pd.Series(dtype=float))
                  for sev in sorted(set(every.loc[single, e]))}
    return clean, out, int((active > 1).sum())


def merged_levels(runs: list[RunData], column: str | None
                  ) -> tuple[pd.Series, dict[str, dict[float, pd.Series]], int]:
    """levels_of over several runs of one background set (one effect dim each, say), their
    clean rows pooled; FalsifyError names an effect two runs both hold."""
    cleans, levels, mixed, owner = [], {}, 0, {}
    for data in runs:
        clean, by_effect, m = levels_of(data, score_column(data, column))
        cleans.append(clean)
        mixed += m
        for e, by_sev in by_effect.items():
            if not by_sev:
                continue
            if e in levels:
                raise FalsifyError(f"{data.path}: effect {e} is in {owner[e]} too; give each "
                                   "effect in one run")
            levels[e], owner[e] = by_sev, data.path
    return pd.concat(cleans), levels, mixed


def robustness(run: str | Path | list, reference: str | Path | list | None = None,
               column: str | None = None, allow_incomplete: bool = False) -> RobustnessResult:
    """The runs' per-effect levels, CE and RR against `reference` (runs of the same spaces,
    in the same order, with another network), mCE and mRR. Several runs pool their clean rows
    and each adds its effects (Robo3D's effects one at a time, without their product). An
    incomplete run (or reference) is an error unless allowed: its missing levels would go
    unsaid."""
    runs = [run] if isinstance(run, str | Path) else list(run)
    refs = (None if reference is None else
            [reference] if isinstance(reference, str | Path) else list(reference))
    datas = [open_run(r) for r in runs]
    for d in datas:
        check_complete(d, allow_incomplete)
    col = score_column(datas[0], column)
    clean_rows, levels, mixed = merged_levels(datas, column)
    clean = float(clean_rows.mean())
    name = ", ".join(str(r) for r in runs)
    if clean <= 0:
        raise FalsifyError(f"{name}: the clean rows' mean {col} is 0; resilience is undefined")
    ref_levels: dict[str, dict[float, pd.Series]] = {}
    ref_clean = None
    if refs is not None:
        if len(refs) != len(runs):
            raise FalsifyError(f"--reference: {len(refs)} runs for {len(runs)}; give one "
                               "reference run per run, in the same order")
        ref_datas = [open_run(r) for r in refs]
        for d in ref_datas:
            check_complete(d, allow_incomplete, "--reference ")
        for r, d, rd in zip(refs, datas, ref_datas, strict=True):
            if rd.meta.get("config_hash") != d.meta.get("config_hash"):
                raise FalsifyError(f"--reference {r}: not a run of the same space as {d.path} "
                                   "(their config hashes differ)")
        ref_clean_rows, ref_levels, _ = merged_levels(ref_datas, column)
        ref_clean = float(ref_clean_rows.mean())
    effects = [effect_robustness(e, by_sev, clean, None if refs is None else
                                 ref_levels.get(e, {}))
               for e, by_sev in levels.items()]
    if not effects:
        raise FalsifyError(f"{name}: no row with exactly one effect non-zero; robustness "
                           "compares each effect alone with the clean rows")
    ces, rrs = [e.ce for e in effects], [e.rr for e in effects]
    return RobustnessResult(
        name, None if refs is None else ", ".join(str(r) for r in refs), col, clean,
        int(len(clean_rows)), ref_clean, tuple(effects), mixed,
        float(np.mean(ces)) if refs is not None and None not in ces else None,
        float(np.mean(rrs)) if None not in rrs else None)


def _mean(g: pd.Series | None) -> float | None:
    """A level's mean score; None where it has no valid sample (or is not held at all)."""
    return float(g.mean()) if g is not None and len(g) else None


def effect_robustness(effect: str, by_sev: dict[float, pd.Series], clean: float,
                      ref: dict[float, pd.Series] | None) -> EffectRobustness:
    """One effect's levels, CE_e and RR_e as Robo3D (Kong et al., ICCV 2023, Sec. 3.2) defines
    them over all L_e severities the run holds; either is None, with a note, where a severity
    has no valid score (in the run or, for CE, the reference) or the reference scores 1 at
    every severity (CE's denominator 0): a level left out would change the sums unsaid."""
    lv = tuple(Level(s, _mean(g), int(len(g)), None if ref is None else _mean(ref.get(s)))
               for s, g in sorted(by_sev.items()))
    sev = ", ".join(f"{x.severity:g}" for x in lv if x.score is None)
    notes = [f"no valid sample at severity {sev}"] if sev else []
    rr = None if sev else float(sum(x.score for x in lv) / (len(lv) * clean))
    ce = None
    if ref is not None:
        ref_sev = ", ".join(f"{x.severity:g}" for x in lv if x.reference is None)
        denom = 0.0 if ref_sev else float(sum(1.0 - x.reference for x in lv))
        if ref_sev:
            notes.append(f"no valid reference sample at severity {ref_sev}")
        elif denom <= 0:
            notes.append("the reference scores 1 at every severity: CE's denominator is 0")
        elif not sev:
            ce = float(sum(1.0 - x.score for x in lv) / denom)
    return EffectRobustness(effect, lv, ce, rr, "; ".join(notes))


def robustness_text(r: RobustnessResult) -> str:
    """The table, a line per effect and severity, then mCE and mRR."""
    lines = [f"{r.run}: {r.column}, clean {r.clean:.3f} ({r.clean_samples} rows)"
             + ("" if r.clean_reference is None else
                f"; reference {r.reference}: clean {r.clean_reference:.3f}")]
    table = []
    for e in r.effects:
        for lv in e.levels:
            table.append({"effect": e.effect, "severity": f"{lv.severity:g}",
                          "score": "-" if lv.score is None else f"{lv.score:.3f}",
                          "rows": lv.samples,
                          "reference": "" if lv.reference is None else f"{lv.reference:.3f}",
                          "CE": "" if e.ce is None else f"{e.ce:.3f}",
                          "RR": "" if e.rr is None else f"{e.rr:.3f}"})
    lines.append(pd.DataFrame(table).to_string(index=False))
    lines.extend(f"{e.effect}: {e.note}" for e in r.effects if e.note)
    why = ("no --reference" if r.reference is None
           else "CE undefined for " + ", ".join(e.effect for e in r.effects if e.ce is None))
    lines.append(("mCE " + (f"- ({why})" if r.mce is None else f"{r.mce:.3f}"))
                 + ", mRR " + ("- (RR undefined for " + ", ".join(
                     e.effect for e in r.effects if e.rr is None) + ")"
                     if r.mrr is None else f"{r.mrr:.3f}")
                 + (f"; {r.mixed_samples} rows with several effects at once left out"
                    if r.mixed_samples else ""))
    return "\n".join(lines)
