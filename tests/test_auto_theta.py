"""The automatic global θ explained (``auto_theta``): its pieces against a plain computation, and the note."""

from __future__ import annotations

import numpy as np
import pytest

from vpr_explorer.method.auto_theta import AutoParts, auto_parts, rejects_all_note
from vpr_explorer.method.thresholds import AUTO_Z


def _unit(rows: np.ndarray) -> np.ndarray:
    return (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)


def test_parts_are_the_median_and_mad_of_every_training_pair():
    rng = np.random.default_rng(0)
    d = _unit(rng.normal(size=(30, 8)))
    parts = auto_parts(d)
    s = np.array([float(d[i] @ d[j]) for i in range(30) for j in range(i + 1, 30)])  # every distinct pair
    med = np.median(s)
    mad = np.median(np.abs(s - med))
    assert parts.n_scores == len(s) == 435
    assert parts.median == pytest.approx(med, abs=1e-6) and parts.mad == pytest.approx(mad, abs=1e-6)
    assert parts.theta == pytest.approx(med + AUTO_Z * mad / 0.675, abs=1e-6)


def test_wide_similarities_put_theta_above_one_and_the_note_says_why():
    # directions spread over a half circle: similarities from -1 to 1, a MAD of about 0.3
    angles = np.linspace(0, np.pi, 24)
    d = _unit(np.stack([np.cos(angles), np.sin(angles)], axis=1))
    parts = auto_parts(d)
    assert parts.theta > 1 and parts.rejects_everything
    note = rejects_all_note(parts, over="the database images (day)")
    assert f"= {parts.theta:.3f}" in note and f"median {parts.median:.3f}" in note and f"MAD {parts.mad:.3f}" in note
    assert "rejects every query" in note and "the database images (day)" in note


def test_no_note_when_theta_can_be_reached():
    assert rejects_all_note(AutoParts(theta=0.8, median=0.3, mad=0.05, n_scores=10)) is None
    assert rejects_all_note(AutoParts(theta=1.0, median=0.3, mad=0.05, n_scores=10)) is None  # 1 is reachable
