"""``preview --frames`` selects rows by source frame number (#34)."""

import pytest

from retarget_cli.errors import ParameterError
from retarget_cli.see.preview import describe_frames, parse_frames

FROM_100 = list(range(100, 140, 2))  # a take tracked with start: 100, step: 2


@pytest.mark.parametrize("spec, rows", [
    (None, range(20)), (":", range(20)), ("104:110", range(2, 5)), ("104:111", range(2, 6)), ("103:106", range(2, 3)),
    ("130:", range(15, 20)), (":104", range(0, 2)), ("138", range(19, 20)), ("100", range(0, 1)), ("-1", range(19, 20)),
    ("-3:", range(17, 20)), ("0:1000", range(20)),
])
def test_source_frame_ranges(spec, rows):
    assert parse_frames(spec, FROM_100) == rows


def test_rows_numbered_from_zero_keep_the_slice_meaning():
    assert parse_frames("5:17", 60) == range(5, 17) and parse_frames("7", 60) == range(7, 8)


@pytest.mark.parametrize("spec, message", [
    ("101", "--frames 101: frame 101 is not a frame of the take (20 frames, source frames 100-138, every 2nd)"),
    ("4", "frame 4 is not a frame of the take"),
    ("0:100", "--frames 0:100: selects no frame of the 20-frame take (source frames 100-138, every 2nd)"),
    ("a:b", "expected a:b with integers"),
])
def test_a_frame_outside_the_take_names_its_frames(spec, message):
    with pytest.raises(ParameterError) as err:
        parse_frames(spec, FROM_100)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_describe_frames():
    assert describe_frames([0, 1, 2]) == "source frames 0-2"
    assert describe_frames([3, 6, 9]) == "source frames 3-9, every 3rd"
    assert describe_frames([0, 1, 5]) == "source frames 0-5"
