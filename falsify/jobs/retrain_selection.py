"""How a retraining experiment picks R's scans besides the blind cells: control cells drawn at
random, the rules `falsify explain` finds on V carried over to R, and their random control."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import pandas as pd

from falsify.results.explain import Rule, holds
from falsify.world.space import Space

SELECTIONS = ("blind", "control", "rules", "random")


def transferable(rule: Rule) -> Rule:
    """The rule without its conditions on `background`: V's streets are not R's, so a rule's
    region carries over to R only in the other dims."""
    return dataclasses.replace(rule, conditions=tuple(
        c for c in rule.conditions if c.dim != "background"))


def covered(rules: Sequence[Rule], space: Space, rows: pd.DataFrame) -> np.ndarray:
    """Bool per row: covered by at least one rule's transferable conditions (a rule about a
    street of V alone covers nothing in R), each on rows whose sample holds the condition's
    car (a one-car row's pinned x_2 meets no rule on x_2, as explain found the rule)."""
    out = np.zeros(len(rows), bool)
    for rule in map(transferable, rules):
        if rule.conditions:
            out |= np.logical_and.reduce([c.mask(rows[c.dim]) & holds(space, rows, c.dim)
                                          for c in rule.conditions])
    return out


def random_rows(n: int, eval_index: pd.Series, seed: int, rows: pd.DataFrame) -> np.ndarray:
    """Bool per row of `rows`: among `n` of the `eval_index` values drawn without replacement
    (seeded), so a control takes as many samples as its targeted twin, from anywhere."""
    pool = np.sort(eval_index.to_numpy())
    pick = np.random.default_rng(seed).choice(len(pool), size=min(n, len(pool)), replace=False)
    return rows["eval_index"].isin(pool[pick]).to_numpy()


def control_cells(cmap, threshold: float, n: int, seed: int) -> list[tuple]:
    """`n` cells drawn without replacement (seeded) from those at or above the threshold."""
    ok = sorted(((c.a, c.b) for c in cmap.cells() if c.miou is not None and c.miou >= threshold),
                key=lambda ab: (float(ab[0]), float(ab[1])))
    if not ok:
        return []
    pick = np.random.default_rng(seed).choice(len(ok), size=min(n, len(ok)), replace=False)
    return [ok[i] for i in sorted(pick)]
