"""daemon/labelling/extend.py: a labelled run carried over the unlabelled points that
continue its motion, and not over a point that another point or run could as well be."""

import numpy as np

from daemon.labelling.extend import extend_runs


def _take(F=12, seen_from=5, seen_to=12, speed=(0.012, 0.004, -0.003), ghost=None):
    """Two markers moving steadily (12 mm a frame, as a limb at 1.4 m/s and 120 fps):
    marker 0 labelled in frames seen_from..seen_to-1 only, its point present in every
    frame; marker 1 labelled throughout, 0.3 m away. `ghost(i, x0)`: extra points."""
    frames = np.arange(100, 100 + F)
    per_frame, marks, truth = [], [], []
    for i in range(F):
        x0 = np.array([0.1, 0.2, 1.0]) + i * np.array(speed)
        x1 = x0 + np.array([0.3, 0.0, 0.0])
        pts = [x1, x0]
        extra = [] if ghost is None else ghost(i, x0)
        pts = np.array(pts + extra)
        m = np.full(len(pts), -1)
        m[0] = 1
        if seen_from <= i < seen_to:
            m[1] = 0
        per_frame.append(pts)
        marks.append(m)
        truth.append(np.r_[1, 0, np.full(len(extra), -1)])
    return frames, per_frame, marks, truth


def test_a_run_is_carried_back_and_forward_over_its_own_points():
    frames, per_frame, marks, truth = _take(seen_from=4, seen_to=8,
                                            ghost=lambda i, x0: [x0 + [0.0, 0.2, 0.1]])
    added = extend_runs(frames, per_frame, marks)
    assert added == 8  # frames 0-3 back, 8-11 forward
    for m, t in zip(marks, truth, strict=True):
        np.testing.assert_array_equal(m, t)  # the ghost 22 cm off stays unlabelled


def test_a_point_as_near_as_another_is_left_alone():
    # a second unlabelled point 6 mm beside the marker's own in frame 3 (inside the gate):
    # neither is taken there, so the run stops at frame 4 (nothing before it is reached)
    frames, per_frame, marks, _ = _take(
        ghost=lambda i, x0: [x0 + [0.0, 0.006, 0.0]] if i == 3 else [])
    extend_runs(frames, per_frame, marks)
    assert marks[4][1] == 0
    assert (marks[3] == -1).sum() == 2 and all(m[1] == -1 for m in marks[:3])


def test_nothing_is_joined_across_a_gap_in_the_frame_numbers_or_beyond_the_gate():
    frames, per_frame, marks, _ = _take()
    frames[5:] += 1  # frame numbers 100-104, then 106-...: indices 4 and 5 are not neighbours
    extend_runs(frames, per_frame, marks)
    assert all(m[1] == -1 for m in marks[:5])
    assert marks[5][1] == 0
    # nor when the run, carried back from further on, reaches the gap
    frames, per_frame, marks, _ = _take(seen_from=8)
    frames[5:] += 1
    extend_runs(frames, per_frame, marks)
    assert all(m[1] == 0 for m in marks[5:]) and all(m[1] == -1 for m in marks[:5])
    # a marker that stopped (its point 30 mm off the extrapolation) is not followed
    frames, per_frame, marks, _ = _take()
    for i in range(5):
        per_frame[i][1] = per_frame[5][1] + [0.0, 0.0, 0.03 * (5 - i)]
    extend_runs(frames, per_frame, marks)
    assert all(m[1] == -1 for m in marks[:5])


def test_two_runs_never_take_one_point():
    # markers 0 and 2 both end their runs at frame 5 going back, their extrapolations
    # 6 mm apart, and frame 4 holds one point between them: neither takes it
    frames = np.arange(10)
    per_frame, marks = [], []
    for i in range(10):
        a = np.array([0.0, 0.0, 1.0]) + i * np.array([0.01, 0, 0])
        b = a + [0.0, 0.006, 0.0]
        pts = np.array([a + [0, 0.003, 0]]) if i < 5 else np.array([a, b])
        per_frame.append(pts)
        marks.append(np.full(1, -1) if i < 5 else np.array([0, 2]))
    assert extend_runs(frames, per_frame, marks) == 0
    assert all((m == -1).all() for m in marks[:5])


def test_a_one_frame_glitch_is_replaced_by_the_runs_point_and_a_run_is_not():
    # marker 0 labelled from frame 5 on; in frame 4 the tracker put it on a point 5 cm off
    # its path (the ghost) while its own point went unlabelled, frames 0-3 unlabelled
    frames, per_frame, marks, truth = _take(ghost=lambda i, x0: [x0 + [0.0, 0.05, 0.0]])
    marks[4][1], marks[4][2] = -1, 0
    extend_runs(frames, per_frame, marks)
    for m, t in zip(marks, truth, strict=True):
        np.testing.assert_array_equal(m, t)
    # the same, but frames 3 and 4 both on the off point: a run of its own, left as it is
    frames, per_frame, marks, _ = _take(ghost=lambda i, x0: [x0 + [0.0, 0.05, 0.0]])
    for i in (3, 4):
        marks[i][1], marks[i][2] = -1, 0
    extend_runs(frames, per_frame, marks)
    assert all(m[2] == 0 and m[1] == -1 for m in marks[3:5])


def test_a_glitch_on_merged_points_gives_up_both():
    # frame 4's marker 0 sits on an off-path point and on its duplicate 1 mm beside it (two
    # points the labeller merged): the run's own point replaces both
    frames, per_frame, marks, truth = _take(
        ghost=lambda i, x0: [x0 + [0.0, 0.05, 0.0], x0 + [0.0, 0.051, 0.0]])
    marks[4][1], marks[4][2], marks[4][3] = -1, 0, 0
    extend_runs(frames, per_frame, marks)
    for m, t in zip(marks, truth, strict=True):
        np.testing.assert_array_equal(m, t)
