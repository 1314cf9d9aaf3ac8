"""What the run report's sections share: the objective's name, the model column's heading,
and a sample row's values as text."""

from __future__ import annotations

import math

import pandas as pd

from falsify.reports.page import esc
from falsify.results.miou_maps import fmt_value
from falsify.results.store import RunData


def bg_values(data: RunData) -> tuple:
    """The run's background values (none where its space has no background dim)."""
    return tuple(data.space.dims["background"].grid()) if "background" in data.space.dims else ()


def objective_name(data: RunData) -> str:
    """What the run's map averages: car IoU, another class's IoU, or mIoU over its classes."""
    o = data.objective
    return "car IoU" if o == "car" else "mIoU over the scored classes" if o == "miou" else \
        f"{esc(o)} IoU"


def objective_title(data: RunData) -> str:
    """The map's title suffix for a run with another objective than car ('' for car)."""
    return "" if data.objective == "car" else f": objective {esc(data.objective)}"


def placed_name(data: RunData) -> str:
    """What the space places: "car" in spaces that name the dim car_model, else "actor"."""
    return "car" if data.space.model_dim == "car_model" else "actor"


def model_heading(data: RunData) -> str:
    """The model column's heading: "car model" in spaces that name the dim so, else "actor"."""
    return "car model" if placed_name(data) == "car" else "actor"


def bg_text(data: RunData, row: pd.Series) -> str:
    """A row's background: the real scan's name on real backgrounds, else the street's id."""
    text = dim_text(row, "background")
    if data.space.real_backgrounds and text != "—":
        return data.space.background_name(int(float(text)))
    return text


def dim_text(row: pd.Series, name: str) -> str:
    """A row's value of a dim as text: "—" where missing, x, y and yaw to at most 3 places."""
    if name not in row.index:
        return "—"
    v = row[name]
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "—"
    if isinstance(v, str):
        return v
    return f"{float(v):.3f}".rstrip("0").rstrip(".") if name in ("x", "y", "yaw") else \
        fmt_value(v)


# Rows a heat-map cell lists when clicked (its lowest): the page embeds at most this many per
# cell, so its size does not grow with a run's rows beyond the map's cells.
CELL_ROWS = 25

# Most samples a plot draws one mark each for; over it a plot bins them (a density, a range
# per bin), so its size does not grow with a run's rows.
MAX_POINTS = 2000

# Dims the sample tables give a column of their own (besides the model dim).
TABLE_DIMS = ("x", "y", "yaw", "count", "background")


def other_dims(data: RunData) -> tuple[str, ...]:
    """The space's dims without a column of their own (weather, camera, further objects'): the
    tables list them in one column, so samples that differ only there do not read alike."""
    return tuple(d for d in data.space.dims if d not in (*TABLE_DIMS, data.space.model_dim))


def other_text(row: pd.Series, names: tuple[str, ...]) -> str:
    """A row's values of `names` as "fog 50, colour red"."""
    return ", ".join(f"{n} {dim_text(row, n)}" for n in names)


def score_parts(column: str) -> tuple[str | None, str | None]:
    """The precision and recall columns of an IoU score column ("car_iou": car_precision,
    car_recall); none for mIoU, which has neither."""
    if not column.endswith("_iou"):
        return None, None
    return column[:-4] + "_precision", column[:-4] + "_recall"
