"""Per-class notes, the inserted/real split and SemanticKITTI's miou column, against
hand-computed values (each test fails on a plausible wrong variant of the code)."""

from __future__ import annotations

import numpy as np
import pytest

from falsify.results.metrics import Scoring, class_scores


def test_notes_say_only_what_is_missing() -> None:
    """A class predicted without false positives was still predicted: no "no car predicted"."""
    #                  tp fp fn
    counts = np.array([[0, 0, 0],    # unknown: nowhere
                       [5, 0, 3],    # car: predicted (all right), some missed
                       [0, 2, 0],    # pedestrian: predicted where there is none
                       [0, 0, 4]])   # cyclist: in the label, never predicted
    notes = {s.name: s.note for s in class_scores(counts)}
    assert notes == {"unknown": "no unknown in label or prediction", "car": "",
                     "pedestrian": "no pedestrian in label", "cyclist": "no cyclist predicted"}


def test_inserted_objects_missed_entirely_score_zero_and_real_leaves_them_out() -> None:
    """Pixels 0, 1: an inserted car the network misses entirely (IoU 0, not undefined);
    pixel 2: a real car found; pixel 3: a false car on the road."""
    truth = np.array([1, 1, 1, 0])
    inserted = np.array([True, True, False, False])
    pred = np.array([0, 0, 1, 1])
    m, _ = Scoring(parts=True).score(pred, truth, inserted)
    # inserted part: pixels 0, 1, 3 -> tp 0, fp 1, fn 2
    assert m["inserted_iou"] == 0.0 and m["inserted_recall"] == 0.0
    # real part: pixels 2, 3 -> tp 1, fp 1, fn 0
    assert m["real_iou"] == pytest.approx(1 / 2) and m["real_recall"] == 1.0
    # the whole scan: tp 1, fp 1, fn 2
    assert m["car_iou"] == pytest.approx(1 / 4)


def test_semantic_runs_store_miou_whatever_the_objective() -> None:
    """SemanticKITTI scoring writes the miou column even when it minimises one class."""
    s = Scoring.of(["car", "person", "traffic-sign"], "car")   # train ids 1, 6, 19
    assert s.semantic and s.score_column == "car_iou" and "miou" in s.columns
    truth = np.array([1, 1, 6, 6, 0])
    pred = np.array([1, 6, 6, 6, 1])   # the unlabeled pixel is left out
    m, note = s.score(pred, truth)
    assert m["car_iou"] == 0.5 and m["person_iou"] == pytest.approx(2 / 3)
    assert m["traffic_sign_iou"] is None
    assert m["miou"] == pytest.approx((1 / 2 + 2 / 3) / 2) and note == ""

