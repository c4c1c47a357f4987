"""Past the search deadline an estimator whose track fails reports it at once instead of
searching the whole frame; without a deadline it searches as before."""

import time

import numpy as np
import pytest

from estimators.deadline import NO_TIME_FOR_SEARCH, search_allowed, search_deadline
from estimators.geometry import Pose
from estimators.registry import build_estimator
from tests.estimators import rendered


def test_search_allowed_only_until_the_deadline_and_only_inside_the_block():
    assert search_allowed()
    with search_deadline(time.monotonic() + 60.0):
        assert search_allowed()
    with search_deadline(time.monotonic() - 0.001):
        assert not search_allowed()
        with search_deadline(None):
            assert search_allowed()
        assert not search_allowed()
    assert search_allowed()


@pytest.mark.parametrize("system", ["corners", "lines", "ellipses"])
def test_a_failed_track_past_the_deadline_is_not_followed_by_a_search(system):
    frame = rendered.frame(2.0)
    truth = frame.truth.X_CT
    # 25 cm off across the view: nothing tracks from there.
    wrong = Pose(truth.R, truth.p + np.array([0.25, -0.15, 0.0]))
    estimator = build_estimator(system, rendered.target(), frame.info)
    with search_deadline(time.monotonic() - 0.001):
        late = estimator.estimate(frame, wrong)
    assert not late.valid
    assert NO_TIME_FOR_SEARCH in late.reason
    searched = estimator.estimate(frame, wrong)  # no deadline: the frame is searched
    assert NO_TIME_FOR_SEARCH not in (searched.reason or "")
    assert searched.valid
