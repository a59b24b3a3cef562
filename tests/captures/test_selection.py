"""Frame selection: every N-th training frame, at most N evenly spaced."""

from __future__ import annotations

import itertools

import pytest

from regnf.captures.selection import evenly_spaced, select_frames

TRAIN = [0, 1, 2, 4, 5, 6, 7, 8, 9, 11, 12]
"""Training frame indices of a capture whose frames 3 and 10 are held out."""


def test_the_defaults_keep_every_training_frame() -> None:
    assert select_frames(TRAIN) == TRAIN


def test_stride_keeps_every_nth_training_frame_from_the_first() -> None:
    assert select_frames(TRAIN, stride=2) == [0, 2, 5, 7, 9, 12]
    assert select_frames(TRAIN, stride=20) == [0]


def test_max_frames_keeps_evenly_spaced_frames_with_both_ends() -> None:
    assert select_frames(TRAIN, max_frames=3) == [0, 6, 12]  # positions 0, 5, 10
    assert select_frames(TRAIN, max_frames=1) == [0]
    assert select_frames(TRAIN, max_frames=100) == TRAIN
    assert select_frames(TRAIN, stride=2, max_frames=2) == [0, 12]


@pytest.mark.parametrize("count,limit", [(7, 3), (600, 100), (101, 100), (5, 2)])
def test_evenly_spaced_positions_are_distinct_and_about_equally_apart(count: int, limit: int) -> None:
    got = evenly_spaced(count, limit).tolist()
    assert len(set(got)) == len(got) == limit
    assert got[0] == 0 and got[-1] == count - 1 and got == sorted(got)
    gaps = [b - a for a, b in itertools.pairwise(got)]
    assert max(gaps) - min(gaps) <= 1


@pytest.mark.parametrize("kwargs,message", [({"stride": 0}, "--stride must be at least 1, got 0"),
                                            ({"max_frames": 0}, "--max-frames must be at least 1, got 0")])
def test_bad_options_are_refused(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        select_frames(TRAIN, **kwargs)
