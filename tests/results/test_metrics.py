"""Metrics: per-class counts and the official IoU / precision / recall definitions."""

from __future__ import annotations

import numpy as np
import pytest

from falsify.results.metrics import CLASSES, class_iou, class_scores, confusion, pooled


def test_confusion_hand_computed():
    label = np.array([[0, 1, 1, 1], [2, 2, 0, 3]])
    pred = np.array([[0, 1, 1, 0], [2, 1, 3, 3]])
    c = confusion(pred, label)
    assert c.dtype == np.int64 and c.shape == (4, 3)
    # TP, FP, FN per class.
    assert c.tolist() == [[1, 1, 1], [2, 1, 1], [1, 0, 1], [1, 1, 0]]
    s = {x.name: x for x in class_scores(c)}
    assert [x.name for x in class_scores(c)] == list(CLASSES)
    assert s["car"].iou == pytest.approx(2 / 4)
    assert s["car"].precision == pytest.approx(2 / 3) and s["car"].recall == pytest.approx(2 / 3)
    assert s["pedestrian"].iou == pytest.approx(1 / 2) and s["pedestrian"].precision == 1.0
    assert s["cyclist"].recall == 1.0 and s["cyclist"].note == ""
    assert class_iou(c) == pytest.approx(0.5)


def test_empty_prediction_ground_truth_and_both():
    label = np.array([0, 1, 1, 0])
    empty_pred = class_scores(confusion(np.zeros(4, np.int64), label))[1]
    assert (empty_pred.iou, empty_pred.recall, empty_pred.precision) == (0.0, 0.0, None)
    assert empty_pred.note == "no car predicted"
    empty_label = class_scores(confusion(label, np.zeros(4, np.int64)))[1]
    assert (empty_label.iou, empty_label.precision, empty_label.recall) == (0.0, 0.0, None)
    assert empty_label.note == "no car in label"
    both = class_scores(confusion(np.zeros(4, np.int64), np.zeros(4, np.int64)))[1]
    assert (both.iou, both.precision, both.recall) == (None, None, None)
    assert both.note == "no car in label or prediction"
    assert class_iou(confusion(np.zeros(4, np.int64), np.zeros(4, np.int64))) is None
    assert confusion(np.zeros((0,), np.int64), np.zeros((0,), np.int64)).sum() == 0


def test_pooled_equals_concatenated_and_batched_shapes():
    rng = np.random.default_rng(0)
    preds = rng.integers(0, 4, (5, 64, 512)).astype(np.int8)
    labels = rng.integers(0, 4, (5, 64, 512)).astype(np.uint8)
    per_frame = [confusion(p, lab) for p, lab in zip(preds, labels, strict=True)]
    assert np.array_equal(pooled(per_frame), confusion(preds, labels))
    assert np.array_equal(pooled(per_frame),
                          confusion(preds.reshape(-1), labels.reshape(-1)))
    assert pooled([]).shape == (4, 3)
    # Pooling is not averaging: frame IoUs 1 and 0, pooled 1 / 4.
    a = confusion(np.array([1, 0]), np.array([1, 0]))
    b = confusion(np.array([0, 0, 0]), np.array([1, 1, 1]))
    assert class_iou(pooled([a, b])) == pytest.approx(0.25)


def test_confusion_rejects_bad_input():
    with pytest.raises(ValueError, match="shape"):
        confusion(np.zeros(3, np.int64), np.zeros(4, np.int64))
    with pytest.raises(ValueError, match="class id 4"):
        confusion(np.array([0, 4]), np.array([0, 1]))
    with pytest.raises(ValueError, match="class id -1"):
        confusion(np.array([0, 1]), np.array([-1, 1]))
    with pytest.raises(ValueError, match="integer"):
        confusion(np.array([0.0, 1.0]), np.array([0, 1]))
