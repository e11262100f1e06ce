"""The live view's scene helpers without a browser: which body holds a track, the colour
each marker gets, a camera's state from the daemon's status, sizes from the rig."""

from __future__ import annotations

import numpy as np

from daemon.view.link import held_by
from daemon.view.scene import (
    BODY_RGB,
    FREE_RGB,
    PICKED_RGB,
    SEGMENT_RGB,
    camera_state,
    marker_colours,
    scales,
)


def test_held_by_names_the_body_row_of_each_track():
    ids = np.array([7, 3, 9, 12, 5])
    body_tracks = np.array([[9, 3, -1], [5, -1, 40]])  # track 40 is not seen this frame
    assert held_by(ids, body_tracks).tolist() == [-1, 0, 0, -1, 1]
    assert held_by(ids, np.zeros((0, 4), np.int64)).tolist() == [-1] * 5
    assert held_by(np.zeros(0, np.int64), body_tracks).tolist() == []


def test_marker_colours_picked_over_segment_over_body_over_free():
    c = marker_colours(4, np.array([-1, 1, 1, 0]), np.array([False, False, False, True]),
                       np.array([-1, -1, 2, -1]))
    assert [tuple(x) for x in c.tolist()] == [FREE_RGB, BODY_RGB[1], SEGMENT_RGB[2],
                                              PICKED_RGB]


def test_camera_state_from_status():
    assert camera_state(None) == "waiting"
    assert camera_state({"connected": False, "rate_hz": 0.0}) == "dropped"
    assert camera_state({"connected": True, "rate_hz": 0.0}) == "no frames"
    assert camera_state({"connected": True, "rate_hz": 119.8}) == "connected"


def test_sizes_follow_the_rig():
    from calibkit.synthetic import sim

    small = scales(sim.make_rig(6, 2.0, seed=0))
    big = scales(sim.make_rig(6, 6.0, seed=0))
    assert big["marker_radius_m"] > small["marker_radius_m"] > 0.01
    assert big["body_axes_m"] > small["body_axes_m"]
