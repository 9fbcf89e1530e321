"""`engine.bench.object_coverage`: the share of a moving object's Gaussians that stay on it."""

from __future__ import annotations

import numpy as np
import pytest

from engine.bench.object_coverage import kept_fractions


def test_gaussians_that_follow_their_object_are_kept_and_a_relay_is_not():
    """Object 6 is rendered by the same 10 Gaussians at all 5 frames; object 7 by a relay:
    a new set of 10 Gaussians per frame, the others elsewhere (background or off-image)."""
    T, G = 5, 60
    labels = np.full((T, G), 0)
    labels[:, :10] = 6                      # followers
    for t in range(T):                      # relay: Gaussians 10 + 10 t .. on object 7 at frame t only
        labels[t, 10 + 10 * t:20 + 10 * t] = 7
    labels[0, 20:30] = -1                   # some of the relay off the image at frame 0
    visible = np.ones((T, 2), bool)
    kept = kept_fractions(labels, visible, 2, [6, 7])
    assert kept[6] == 1.0 and kept[7] == 0.0
    # half of object 7's frame-2 set follows it to frame 3 only: 1/2 at one of 4 frames
    labels[3, 30:35] = 7
    assert kept_fractions(labels, visible, 2, [6, 7])[7] == pytest.approx(0.5 / 4)


def test_frames_where_the_object_is_out_of_view_are_not_scored():
    labels = np.array([[6, 6, 0, 0],
                       [6, 6, 0, 0],
                       [0, 0, 0, 0]])          # frame 2: the object has left the image
    visible = np.array([[True], [True], [False]])
    assert kept_fractions(labels, visible, 1, [6]) == {6: 1.0}
    # no Gaussian on the object at the reference frame, or never in view elsewhere: None
    assert kept_fractions(labels, visible, 2, [6]) == {6: None}
    assert kept_fractions(labels, np.array([[False], [True], [False]]), 1, [6]) == {6: None}
