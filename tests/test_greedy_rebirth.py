"""The greedy fit's death-and-birth move (``FitDetectOptions.rebirth``), on the stand-in forward model of
tests/test_invert_fit.py (differentiable jnp geometry: no compilation of the guided model)."""

import dataclasses

import numpy as np
import pytest

from tofjax.config import ConfigError
from tofjax.invert import match
from tofjax.invert.greedy import FitDetectOptions, build_fit_detector

from test_invert_fit import _frame, stand_in  # noqa: F401  (stand_in is a fixture)


def test_fast_rebirth_finds_weak_contact_beside_strong(stand_in):  # noqa: F811
    """Two contacts 4 cm apart, one 5x weaker (noise-free frame, the noise of a 4x exposure). Without the
    move the search ends with three contacts: the strong one fitted twice and the weak one misplaced; with
    it, the two contacts within 1 cm and nothing else, at a chi-square 8x lower."""
    sc, base, optical = stand_in
    base = 0.25 * base
    K = 3
    truth = np.array([[0.07, 0.05, 0.9], [0.07, 0.09, 0.18]])
    frame = _frame(sc, base, truth, K)[None]
    opts = FitDetectOptions(cell_m=0.01, max_contacts=K, iterations=4, relocate_candidates=2, n_sigma=5.0)
    det = build_fit_detector(sc, base, optical, opts, n_baseline=10**9)
    off = det.with_options(dataclasses.replace(opts, rebirth=False)).process(frame)
    on = det.process(frame)
    assert match(off.detections[0].positions(), truth[:, :2], 0.01)[0] < 2 or len(off.detections[0].touches) != 2
    assert len(on.detections[0].touches) == 2, on.detections[0].touches
    assert match(on.detections[0].positions(), truth[:, :2], 0.01)[0] == 2, on.detections[0].touches
    assert on.chi2[0] < off.chi2[0] / 8, (on.chi2, off.chi2)
    with pytest.raises(ConfigError, match="rebirth"):
        FitDetectOptions(rebirth_candidates=0)
