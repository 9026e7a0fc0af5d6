"""Scoring a SLAM run against the simulator's truth: revisit (loop-closure) errors."""

import numpy as np

from robot_agent.sim.evaluate import revisit_errors
from shared.geometry import compose


def circle(n=400, radius=5.0, laps=1.5):
    """A path around a circle, ``laps`` times: the second half comes back over the first."""
    phi = np.linspace(0.0, 2 * np.pi * laps, n)
    return np.stack([radius * np.cos(phi), radius * np.sin(phi), phi + np.pi / 2], axis=-1)


def test_truth_has_revisits_and_scores_zero():
    truth = circle()
    stamps = np.arange(len(truth)) * 1.0
    err = revisit_errors(truth, stamps, truth, stride=5)
    assert len(err) > 10
    np.testing.assert_allclose(err, 0.0, atol=1e-9)


def test_drift_shows_in_revisits_but_a_rigid_shift_does_not():
    truth = circle()
    stamps = np.arange(len(truth)) * 1.0
    shifted = compose(np.array([3.0, -2.0, 0.7]), truth)  # another frame: not an error
    np.testing.assert_allclose(revisit_errors(truth, stamps, shifted, stride=5), 0.0, atol=1e-9)
    drifted = truth.copy()
    drifted[:, 0] += np.linspace(0.0, 1.0, len(truth))  # 1 m of drift over the run
    err = revisit_errors(truth, stamps, drifted, stride=5)
    assert np.percentile(err, 95) > 0.3


def test_no_revisit_gives_no_pairs():
    truth = circle(laps=0.5)
    assert len(revisit_errors(truth, np.arange(len(truth)) * 1.0, truth)) == 0
