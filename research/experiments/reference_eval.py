"""Per-class IoU of the 20-class reference networks on SemanticKITTI's evaluation split.

    python research/experiments/reference_eval.py [--split evaluation|fit]
        [--model NAME=REF:BACKEND]
        [--root ROOT] > research/experiments/reference-networks/eval.json

ROOT defaults to $SEMANTICKITTI (a SemanticKITTI root). Its evaluation split (sequences 00, 03,
06, 08) is only reported on; its fit split (01, 02, 04, 05, 07, 09, 10) may choose between
candidate networks. Each scan is projected with the networks' own sensor preset (KITTI
front view, 64 x 512, rows by laser ring) and scored per pixel as SemanticKITTI's evaluation
scores points: unlabeled pixels ignored, IoU per train class pooled over the scans, mIoU over
the classes present in the labels. The four-class bundled network's car IoU is scored the same
way beside them.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from falsify.data.velodyne import read_kitti
from falsify.models.runners import load_segmenter
from falsify.semantic import TRAIN_CLASSES, train_ids
from falsify.sensor.lidar import load_sensor
from falsify.world.real_scans import label_file

SPLITS = {"evaluation": ("00", "03", "06", "08"),
          "fit": ("01", "02", "04", "05", "07", "09", "10")}
MODELS = {"squeezeseg20": ("squeezeseg20", "onnx"),
          "pointnet20": ("falsify.models.pointnet:reference", "python"),
          "squeezeseg (4 classes)": (None, "onnx")}


def scores(conf: np.ndarray) -> dict:
    tp = np.diag(conf)
    denom = conf.sum(0) + conf.sum(1) - tp
    present = conf.sum(1) > 0
    iou = {TRAIN_CLASSES[c]: (round(float(tp[c] / denom[c]), 4) if denom[c] else None)
           for c in range(1, len(TRAIN_CLASSES))}
    vals = [iou[TRAIN_CLASSES[c]] for c in range(1, len(TRAIN_CLASSES)) if present[c]]
    return {"miou_present": round(float(np.mean(vals)), 4) if vals else None,
            "classes_present": int(present[1:].sum()), "iou": iou}


def main(root: Path, split: str = "evaluation", models: dict | None = None) -> dict:
    sensor = load_sensor("kitti-hdl64e-front")
    scans = {}
    for seq in SPLITS[split]:
        for b in sorted((root / "sequences" / seq / "velodyne").glob("*.bin")):
            lab = label_file(b)
            if lab is None:
                raise SystemExit(f"{b}: no labels found")
            scans.setdefault(seq, []).append(read_kitti(b, lab, sensor))
    n = len(TRAIN_CLASSES)
    out: dict = {"root": str(root), "split": split, "sensor": sensor.name, "models": {}}
    for name, (ref, backend) in (models or MODELS).items():
        model = load_segmenter(ref, backend=backend, threads=2)
        per_seq, total = {}, np.zeros((n, n), np.int64)
        for seq, items in scans.items():
            conf = np.zeros((n, n), np.int64)
            pred = model.predict(np.stack([s.image for s in items]))
            ids = pred.train_ids if len(model.spec.classes) > 4 else None
            for k, s in enumerate(items):
                truth = train_ids(s.semantic)
                keep = (s.image[..., 4] > 0) & (truth != 0)
                if ids is None:   # four classes: car, person, bicyclist of SemanticKITTI's
                    p = np.array([0, 1, 6, 7], np.int64)[pred.classes[k]]
                else:
                    p = ids[k].astype(np.int64)
                conf += np.bincount(truth[keep].astype(np.int64) * n + p[keep],
                                    minlength=n * n).reshape(n, n)
            per_seq[seq] = scores(conf)
            total += conf
        out["models"][name] = {"model_hash": model.model_hash[:12], "pooled": scores(total),
                               "per_sequence": per_seq}
    return out


if __name__ == "__main__":
    import argparse

    p = argparse.ArgumentParser()
    p.add_argument("--root", type=Path, default=os.environ.get("SEMANTICKITTI"),
                   required="SEMANTICKITTI" not in os.environ,
                   help="a SemanticKITTI root (default $SEMANTICKITTI)")
    p.add_argument("--split", choices=sorted(SPLITS), default="evaluation")
    p.add_argument("--model", action="append", default=[], help="NAME=REF:BACKEND")
    a = p.parse_args()
    chosen = {m.split("=", 1)[0]: tuple(m.split("=", 1)[1].rsplit(":", 1)) for m in a.model}
    print(json.dumps(main(a.root, a.split, chosen or None), indent=1))
