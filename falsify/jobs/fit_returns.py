"""Fit the sensor's return model on the geometry and reflectance of KITTI's object frames.

Run: ``falsify fit-returns $KITTI_OBJECT/velodyne/*.bin
--out configs/returns/kitti-hdl64e.json``. Only the points are used (never labels), and only
the three object frames: the SqueezeSeg-layout and SemanticKITTI scans are evaluation data.

What is fitted, from each frame projected into the 64×2048 HDL-64E grid:
- intensity = reflectivity · cos(incidence)^cos_exp · exp(-range / atten_m): least squares of
  log intensity over points with an estimated surface normal (from range-image neighbours);
- reflectivity levels: the median corrected reflectivity of ground points ("road") and the
  15/50/85/99.7 % quantiles of the rest ("dark", "mid", "bright", "retro");
- P(return | expected intensity): maximum likelihood over pixels whose left and right
  neighbours lie on one surface (ranges within 3 %): an empty such pixel is a dropout, and its
  expected intensity is its neighbours' mean; plus a per-row factor (lasers differ);
- the ego body's shadow: for the lowest rows, the fraction of frames with a return per
  azimuth bin.

``fit_labelled`` fits the same on labelled fit scans (``falsify fit-returns --labelled``), and
per SemanticKITTI training class besides: cos_exp and atten_m with one level per class, each
class's corrected reflectivity as a quantile table, the share of its spread between instances
(things' instance ids) and P(return) over dropout candidates whose neighbours share the class.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.optimize import minimize
from scipy.special import ndtr, ndtri
from scipy.stats import rankdata

from falsify.data.velodyne import read_kitti
from falsify.errors import FalsifyError
from falsify.semantic import TRAIN_CLASSES, TRAIN_ID, train_ids
from falsify.sensor.lidar import load_sensor

BLOCKED_FIRST_ROW = 55  # rows from here down are checked for the ego body's shadow
AZ_BINS = 128
Z_SCORES = np.linspace(-3.0, 3.0, 25)   # normal scores the class quantile tables are kept at
MIN_CLASS_POINTS = 500      # fewer corrected points: the class takes the pooled table
MIN_INSTANCE_POINTS = 20    # an instance with fewer points does not count to its spread
MIN_CLASS_CANDIDATES = 200  # fewer dropout candidates: the class takes the pooled P(return)
# What `dropout_from` takes from another model: P(return | intensity), row factor and shadow.
DROPOUT_KEYS = ("p_min", "p_max", "i0", "k", "row_keep", "blocked_rows", "blocked")


def _normals_cos(img: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """|cos| of the incidence angle per pixel from neighbour differences (nan where unknown)."""
    p, r = img[..., :3].astype(np.float64), img[..., 4].astype(np.float64)
    ok = r > 0
    dc = np.roll(p, -1, 1) - np.roll(p, 1, 1)
    dr = np.roll(p, -1, 0) - np.roll(p, 1, 0)
    okc = ok & np.roll(ok, -1, 1) & np.roll(ok, 1, 1)
    okr = ok & np.roll(ok, -1, 0) & np.roll(ok, 1, 0)
    okr[0], okr[-1] = False, False
    close = (np.abs(np.roll(r, -1, 1) - np.roll(r, 1, 1)) < 0.1 * r) & (
        np.abs(np.roll(r, -1, 0) - np.roll(r, 1, 0)) < 0.1 * r)
    n = np.cross(dc, dr)
    norm = np.linalg.norm(n, axis=-1)
    good = okc & okr & close & (norm > 1e-9)
    cos = np.abs((n * dirs).sum(-1)) / np.maximum(norm, 1e-12)
    return np.where(good, cos, np.nan)


def fit(paths: list[Path], command: str) -> dict:
    """The return model fitted on KITTI object frames (.bin, KITTI's ring order), as the JSON
    document configs/returns/ holds."""
    sensor = load_sensor("kitti-hdl64e-360")
    rows = sensor.rows
    feats, cands, valid_stack = _gather(paths, sensor)
    cos_exp, atten, levels, used = _fit_intensity(feats)
    ci = np.concatenate(cands["I"]).astype(np.float64)
    cr = np.concatenate(cands["returned"])
    crow = np.concatenate(cands["row"])
    (p_min, p_max, i0, k), row_keep = _fit_dropout(ci, cr, crow, rows)
    valid_all = np.mean(valid_stack, axis=0)  # (rows, W) fraction of frames with a return
    blocked = []
    for rr in range(BLOCKED_FIRST_ROW, rows):
        blocked.append([round(float(v), 3)
                        for v in valid_all[rr].reshape(AZ_BINS, -1).mean(axis=1)])
    blocked_rows = list(range(BLOCKED_FIRST_ROW, rows))
    # Above the blocked rows the per-row factor carries the laser's own weakness.
    return {
        "name": "kitti-hdl64e",
        "fitted_on": [p.name for p in paths],
        "command": command,
        "points_used": used,
        "dropout_candidates": int(len(cr)),
        "candidate_return_rate": float(cr.mean()),
        "params": {"reflectivity": levels, "cos_exp": cos_exp, "atten_m": atten,
                   "p_min": p_min, "p_max": p_max, "i0": i0, "k": k, "retro_gain": 1.0,
                   "row_keep": [round(v, 4) for v in row_keep],
                   "blocked_rows": blocked_rows, "blocked": blocked},
    }


def _gather(paths: list[Path], sensor) -> tuple[dict, dict, list[np.ndarray]]:
    """Per frame: the points with a known incidence (intensity, cos, range, on the ground), the
    dropout candidates (their neighbours' intensity, returned or not, row), and the mask of
    pixels with a return."""
    dirs = sensor.directions
    feats = {"I": [], "cos": [], "r": [], "ground": []}
    cands = {"I": [], "returned": [], "row": []}
    valid_stack = []
    for path in paths:
        scan = read_kitti(path, None, sensor)
        img = scan.image
        valid = img[..., 4] > 0
        valid_stack.append(valid)
        cos = _normals_cos(img, dirs)
        m = valid & np.isfinite(cos) & (cos > 0.05) & (img[..., 4] < 60)
        feats["I"].append(img[..., 3][m])
        feats["cos"].append(cos[m])
        feats["r"].append(img[..., 4][m])
        nz = np.abs(np.cross(np.roll(img[..., :3], -1, 1) - np.roll(img[..., :3], 1, 1),
                             np.roll(img[..., :3], -1, 0) - np.roll(img[..., :3], 1, 0))[..., 2])
        feats["ground"].append((img[..., 2][m] < -1.3) & (cos[m] > 0.0) & (nz[m] > 0))
        # Dropout candidates: left and right neighbours on one surface.
        r = img[..., 4]
        left, right = np.roll(r, 1, 1), np.roll(r, -1, 1)
        both = (left > 0) & (right > 0) & (np.abs(left - right) < 0.03 * np.maximum(left, right))
        both[BLOCKED_FIRST_ROW:] = False
        inten = (np.roll(img[..., 3], 1, 1) + np.roll(img[..., 3], -1, 1)) / 2
        cands["I"].append(inten[both])
        cands["returned"].append(valid[both])
        cands["row"].append(np.nonzero(both)[0])
    return feats, cands, valid_stack


def _fit_intensity(feats: dict) -> tuple[float, float, dict[str, float], int]:
    """cos_exp and atten_m by least squares of log intensity, the reflectivity levels, and how
    many points the fit used."""
    inten_all = np.concatenate(feats["I"]).astype(np.float64)
    cos = np.concatenate(feats["cos"])
    rng = np.concatenate(feats["r"]).astype(np.float64)
    ground = np.concatenate(feats["ground"])
    pos = inten_all > 0.005
    a = np.stack([np.ones(pos.sum()), np.log(cos[pos]), -rng[pos]], axis=1)
    coef, *_ = np.linalg.lstsq(a, np.log(inten_all[pos]), rcond=None)
    cos_exp = float(np.clip(coef[1], 0.0, 2.0))
    atten = float(1.0 / max(coef[2], 1e-4))
    refl = inten_all / (np.clip(cos, 0.05, 1.0) ** cos_exp * np.exp(-rng / atten))
    levels = {"road": float(np.median(refl[ground])),
              "dark": float(np.quantile(refl[~ground], 0.15)),
              "mid": float(np.quantile(refl[~ground], 0.5)),
              "bright": float(np.quantile(refl[~ground], 0.85)),
              "retro": float(np.quantile(refl, 0.997))}
    return cos_exp, atten, levels, int(pos.sum())


def _fit_dropout(ci: np.ndarray, cr: np.ndarray, crow: np.ndarray, rows: int
                 ) -> tuple[tuple[float, float, float, float], list[float]]:
    """P(return | expected intensity) by maximum likelihood over the dropout candidates
    (p_min, p_max, i0, k), and the per-row factor."""
    def p_of(x, ii):
        p_min, p_max, i0, k = x
        return p_min + (p_max - p_min) * (1.0 - np.exp(-(np.maximum(ii, 0) / i0) ** k))

    def nll(x):
        p = np.clip(p_of(x, ci), 1e-6, 1 - 1e-6)
        return -float(np.sum(np.where(cr, np.log(p), np.log1p(-p))))

    res = minimize(nll, x0=[0.5, 0.98, 0.05, 1.0], method="L-BFGS-B",
                   bounds=[(0.0, 1.0), (0.5, 1.0), (1e-3, 1.0), (0.2, 5.0)])
    p_min, p_max, i0, k = (float(v) for v in res.x)
    return (p_min, p_max, i0, k), _row_keep(cr, crow, p_of(res.x, ci), rows, p_max)


def _row_keep(returned: np.ndarray, row: np.ndarray, pred: np.ndarray, rows: int,
              p_max: float) -> list[float]:
    """Per laser row, its candidates' return rate over the model's prediction for them (1 for a
    row with under 200 candidates), held in 0.3..1/p_max."""
    out = []
    for rr in range(rows):
        m = row == rr
        out.append(1.0 if m.sum() < 200 else
                   float(np.clip(returned[m].mean() / pred[m].mean(), 0.3, 1.0 / p_max)))
    return out


def labelled_frames(paths: list[str], sequences: list[str] | None,
                    holdout: Sequence[str | Path] = ()) -> list[tuple[Path, Path]]:
    """(.bin, .label) of every scan the paths name; FalsifyError naming a held-out scan (never
    fitted to), one without SemanticKITTI labels, or one given twice (by path or content)."""
    from falsify.data.holdout import check_each_once, check_not_held_out
    from falsify.world.real_scans import real_scans

    scans = real_scans(paths, sequences)
    check_not_held_out([path for _, path, _, _ in scans], holdout, "fit-returns' scans")
    check_each_once([path for _, path, _, _ in scans], "fit-returns' scans")
    frames = []
    for _, path, label, kind in scans:
        if kind != "semantickitti" or label is None:
            raise FalsifyError(f"{path}: no SemanticKITTI .label beside it or in ../labels/ "
                               "(its classes cannot be fitted)")
        frames.append((path, label))
    return frames


def fit_labelled(frames: list[tuple[Path, Path]], name: str, command: str,
                 dropout_from: dict | None = None) -> dict:
    """The return model with per-class tables, fitted on labelled scans ((.bin, .label) pairs
    of fit data), as the JSON document configs/returns/ holds. With `dropout_from` (another
    model's params) the returns are dropped as that model drops them (from the expected
    intensity, its row factor and shadow), and only the intensity is fitted."""
    sensor = load_sensor("kitti-hdl64e-360")
    rows = sensor.rows
    pts = {"I": [], "cos": [], "r": [], "cls": [], "key": []}
    cands = {"I": [], "returned": [], "row": [], "cls": []}
    valid_stack = []
    for f, (bin_path, label_path) in enumerate(frames):
        scan = read_kitti(bin_path, label_path, sensor)
        img = scan.image
        valid = img[..., 4] > 0
        valid_stack.append(valid)
        train = train_ids(scan.semantic).astype(np.int64)
        cos = _normals_cos(img, sensor.directions)
        m = valid & np.isfinite(cos) & (cos > 0.05) & (img[..., 4] < 60)
        pts["I"].append(img[..., 3][m])
        pts["cos"].append(cos[m])
        pts["r"].append(img[..., 4][m])
        pts["cls"].append(train[m].astype(np.uint8))   # train ids 0..19, kept small
        inst = scan.instance[m].astype(np.int64)
        pts["key"].append(np.where(inst > 0, f * 100_000 + inst, -1))
        r = img[..., 4]
        left, right = np.roll(r, 1, 1), np.roll(r, -1, 1)
        lc, rc = np.roll(train, 1, 1), np.roll(train, -1, 1)
        both = ((left > 0) & (right > 0) & (np.abs(left - right) < 0.03 * np.maximum(left, right))
                & (lc == rc))
        both[BLOCKED_FIRST_ROW:] = False
        cands["I"].append(((np.roll(img[..., 3], 1, 1) + np.roll(img[..., 3], -1, 1)) / 2)[both])
        cands["returned"].append(valid[both])
        cands["row"].append(np.nonzero(both)[0].astype(np.int16))
        cands["cls"].append(lc[both].astype(np.uint8))
    # each frame's arrays dropped as they are joined: not held twice at the peak
    cat = {k: np.concatenate(pts.pop(k)) for k in list(pts)}
    cos_exp, atten = _fit_class_gain(cat)
    refl = cat["I"].astype(np.float64) / (np.clip(cat["cos"], 0.05, 1.0) ** cos_exp
                                          * np.exp(-cat["r"] / atten))
    table, share, counts = _class_tables(refl, cat["cls"], cat["key"])
    ci = np.concatenate(cands.pop("I")).astype(np.float64)
    cr = np.concatenate(cands.pop("returned"))
    crow = np.concatenate(cands.pop("row"))
    ccls = np.concatenate(cands.pop("cls"))
    (p_min, p_max, i0, k), _ = _fit_dropout(ci, cr, crow, rows)
    p_class, row_keep = _class_dropout(cr, crow, ccls, rows)
    road = cat["cls"] == TRAIN_ID["road"]
    levels = {"road": float(np.median(refl[road])),
              "dark": float(np.quantile(refl[~road], 0.15)),
              "mid": float(np.quantile(refl[~road], 0.5)),
              "bright": float(np.quantile(refl[~road], 0.85)),
              "retro": float(np.quantile(refl, 0.997))}
    valid_all = np.mean(valid_stack, axis=0)
    blocked_rows = list(range(BLOCKED_FIRST_ROW, rows))
    blocked = [[round(float(v), 3) for v in valid_all[rr].reshape(AZ_BINS, -1).mean(axis=1)]
               for rr in blocked_rows]
    params = {"reflectivity": levels, "cos_exp": cos_exp, "atten_m": atten,
              "p_min": p_min, "p_max": p_max, "i0": i0, "k": k, "retro_gain": 1.0,
              "row_keep": [round(v, 4) for v in row_keep],
              "blocked_rows": blocked_rows, "blocked": blocked}
    dropout = "class"
    if dropout_from is not None:
        dropout = "intensity"
        params.update({key: dropout_from[key] for key in DROPOUT_KEYS})
    params["classes"] = {"names": list(TRAIN_CLASSES), "dropout": dropout,
                         "z": [round(float(z), 4) for z in Z_SCORES],
                         "reflectivity": [[round(float(v), 5) for v in row] for row in table],
                         "instance_share": [round(float(v), 4) for v in share],
                         "p_return": [round(float(v), 4) for v in p_class],
                         "points": [int(n) for n in counts]}
    return {
        "name": name,
        "fitted_on": [str(Path(*b.parts[-3:])) for b, _ in frames],
        "command": command,
        "points_used": int(len(refl)),
        "dropout_candidates": int(len(cr)),
        "candidate_return_rate": float(cr.mean()),
        "params": params,
    }


def _fit_class_gain(cat: dict) -> tuple[float, float]:
    """cos_exp and atten_m by least squares of log intensity with one level per class, so that
    a class seen mostly near or mostly flat does not pass for range or incidence."""
    pos = cat["I"] > 0.005
    x = (np.log(cat["cos"][pos]).astype(np.float64), -cat["r"][pos].astype(np.float64))
    coef = within_class_slopes(cat["cls"][pos], x, np.log(cat["I"][pos].astype(np.float64)))
    cos_exp = float(np.clip(coef[-2], 0.0, 2.0))
    atten = float(1.0 / max(coef[-1], 1e-4))
    return cos_exp, atten


def within_class_slopes(cls: np.ndarray, x: tuple[np.ndarray, ...], y: np.ndarray
                        ) -> np.ndarray:
    """The least-squares coefficients of the float64 columns `x` in y ~ one level per class
    (`cls`, small non-negative ids) + x. By the Frisch-Waugh-Lovell theorem (Frisch and Waugh
    1933, Lovell 1963) they are those of y's deviations from its class means regressed on x's:
    a C x C system, so memory stays a few arrays of the points, not the N x (classes + C)
    design matrix (40 MB a scan). `x` and `y` are centred in place."""
    n = np.maximum(np.bincount(cls), 1)   # a class with no point is never indexed
    for v in (*x, y):
        v -= (np.bincount(cls, weights=v) / n)[cls]
    gram = np.array([[float(a @ b) for b in x] for a in x])
    return np.linalg.lstsq(gram, np.array([float(a @ y) for a in x]), rcond=None)[0]


def _class_tables(refl: np.ndarray, cls: np.ndarray, key: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per training class: reflectivity at Z_SCORES (the pooled table where the class has
    fewer than MIN_CLASS_POINTS), the share of its normal-score variance between instances, and
    its point count."""
    probs = ndtr(Z_SCORES)
    pooled = np.quantile(refl, probs)
    n_cls = len(TRAIN_CLASSES)
    table = np.tile(pooled, (n_cls, 1))
    share = np.zeros(n_cls)
    counts = np.bincount(cls, minlength=n_cls)
    for c in range(n_cls):
        m = cls == c
        if m.sum() < MIN_CLASS_POINTS:
            continue
        x = refl[m]
        table[c] = np.quantile(x, probs)
        share[c] = _instance_share(ndtri(rankdata(x) / (len(x) + 1)), key[m])
    return table, share, counts


def _instance_share(z: np.ndarray, key: np.ndarray) -> float:
    """The share of the normal scores' variance that lies between instances (key >= 0), from
    the spread of instance means less what their finite sizes explain; 0 without instances."""
    m = key >= 0
    ids, inverse, n = np.unique(key[m], return_inverse=True, return_counts=True)
    big = n >= MIN_INSTANCE_POINTS
    if big.sum() < 3:
        return 0.0
    means = np.bincount(inverse, weights=z[m])[big] / n[big]
    total = float(np.var(z[m][big[inverse]]))
    noise = float(np.mean(1.0 / n[big])) * total
    return float(np.clip((np.var(means) - noise) / max(total - noise, 1e-9), 0.0, 0.95))


def _class_dropout(returned: np.ndarray, row: np.ndarray, cls: np.ndarray, rows: int
                   ) -> tuple[np.ndarray, list[float]]:
    """P(return) per training class over its dropout candidates (the pooled rate where a class
    has fewer than MIN_CLASS_CANDIDATES), and the per-row factor against it."""
    n_cls = len(TRAIN_CLASSES)
    pooled = float(returned.mean())
    n = np.bincount(cls, minlength=n_cls)
    hits = np.bincount(cls, weights=returned.astype(np.float64), minlength=n_cls)
    p_class = np.where(n >= MIN_CLASS_CANDIDATES, hits / np.maximum(n, 1), pooled)
    return p_class, _row_keep(returned, row, p_class[cls], rows, float(p_class.max()))
