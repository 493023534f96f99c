"""The pose filter over camera reads (kpflow/vision/pose_filter.py): noisy reads of a still object average out, an
outlier read does not move the estimate, a moved object is followed after ``patience`` reads, symmetric yaws average
across their wrap, and the camera perception uses it when ``keypoints.filter`` asks."""

from __future__ import annotations

import numpy as np
import pytest

from kpflow.vision.keypoint_source import KeypointSource
from kpflow.vision.pose_filter import PoseFilter


def test_noisy_reads_of_a_still_object_average_out():
    rng = np.random.default_rng(0)
    truth = np.array([0.1, -0.05, 0.83])
    pose_filter, raw, filtered = PoseFilter(window=5), [], []
    for _ in range(200):
        read = truth + rng.normal(0, 0.004, 3)
        raw.append(np.linalg.norm(read - truth))
        filtered.append(np.linalg.norm(pose_filter.update("nut", read, 0.3 + rng.normal(0, 0.02), 1).pos - truth))
    assert np.median(filtered[10:]) < 0.6 * np.median(raw[10:])  # the median of 5 reads: about half the error


def test_one_outlier_is_rejected_and_a_moved_object_is_followed():
    pose_filter = PoseFilter(window=3, gate=0.02, patience=2)
    here, there = np.array([0.0, 0.0, 0.82]), np.array([0.1, 0.0, 0.82])
    for _ in range(3):
        pose_filter.update("cube", here, 0.0, 4, 0.021)
    np.testing.assert_allclose(pose_filter.update("cube", there, 0.0, 4, 0.021).pos, here)  # one read there: an outlier
    np.testing.assert_allclose(pose_filter.update("cube", here, 0.0, 4, 0.021).pos, here)
    pose_filter.update("cube", there, 0.0, 4, 0.021)
    np.testing.assert_allclose(pose_filter.update("cube", there, 0.0, 4, 0.021).pos, there)  # two in a row: it moved
    pose_filter.forget("cube")
    np.testing.assert_allclose(pose_filter.update("cube", here, 0.0, 4).pos, here)  # forgotten: the first read again
    assert pose_filter.update("cube", here, np.radians(30), 4).yaw == pytest.approx(
        0.0
    )  # 30 degrees: outside the yaw gate


def test_symmetric_yaws_average_across_their_wrap():
    """A cube read at +44 and -44 degrees is the same cube turned by 1 degree either way of 45: quarter turns apart."""
    pose_filter = PoseFilter(window=4, gate_deg=20)
    pos = np.zeros(3)
    yaws = [np.radians(44), np.radians(-44), np.radians(46), np.radians(-46)]
    for yaw in yaws:
        out = pose_filter.update("cube", pos, yaw, 4)
    assert abs(((out.yaw - np.radians(45)) + np.pi / 4) % (np.pi / 2) - np.pi / 4) < 1e-9
    assert PoseFilter().update("can", pos, 1.0, 0).yaw == 1.0  # no yaw to average


def test_filter_options_are_checked_where_they_are_given():
    assert KeypointSource("camera").pose_filter() is None
    made = KeypointSource("camera", filter={"window": 3, "gate": 0.01}).pose_filter()
    assert isinstance(made, PoseFilter) and made.window == 3 and made.gate == 0.01
    with pytest.raises(ValueError, match="unknown pose filter options \\['size'\\]"):
        KeypointSource("camera", filter={"size": 3})
    with pytest.raises(ValueError, match="whole numbers >= 1"):
        PoseFilter(window=0)
    with pytest.raises(ValueError, match="positive numbers"):
        PoseFilter(gate=-1.0)
