"""The one URL-query parser every source uses (hw/__init__.py): keys, values, messages."""

from __future__ import annotations

import pytest

from illuminet.hw import SourceError, parse_query, query_bool, query_choice, query_float, query_int, query_size
from illuminet.hw.synthetic import SyntheticError
from illuminet.hw.synthetic import open_url as synthetic_url


def test_values_are_parsed_and_the_last_repeat_wins():
    q = parse_query(
        "x://dev?n=3&on=Yes&size=64x40&mode=b&n=4&f=1.5",
        {
            "n": query_int(0, 9),
            "on": query_bool,
            "size": query_size(even=True),
            "mode": query_choice("a", "b"),
            "f": query_float,
            "unused": str,
        },
    )
    assert q == {"n": 4, "on": True, "size": (64, 40), "mode": "b", "f": 1.5}


@pytest.mark.parametrize(
    "query, message",
    [
        ("color=1", "x://d?color=1: unknown parameter 'color'; known: n, on"),
        ("n=12", "x://d?n=12: n='12': expected an integer in 0..9"),
        ("n=two", "x://d?n=two: n='two': expected an integer in 0..9"),
        ("on=maybe", "x://d?on=maybe: on='maybe': expected 0/1"),
    ],
)
def test_bad_keys_and_values_name_the_url_key_and_value(query, message):
    with pytest.raises(SourceError) as e:
        parse_query(f"x://d?{query}", {"n": query_int(0, 9), "on": query_bool}, error=SourceError)
    assert str(e.value).startswith(message)


@pytest.mark.parametrize("value, ok", [("640x400", True), ("641x400", False), ("0x4", False), ("640", False)])
def test_sizes(value, ok):
    parse = query_size(even=True)
    if ok:
        assert parse(value) == (640, 400)
    else:
        with pytest.raises(ValueError, match="expected WIDTHxHEIGHT"):
            parse(value)


def test_non_finite_numbers_are_refused():
    with pytest.raises(ValueError, match="finite"):
        query_float("nan")


def test_every_source_scheme_refuses_the_same_way():
    from illuminet.hw import v4l2
    from illuminet.hw.replay import open_url as replay_url
    from illuminet.runtime.config import defaults

    with pytest.raises(SourceError, match=r"replay://s\?speed=2: unknown parameter 'speed'; known: timing, loop"):
        replay_url("replay://s?speed=2", defaults())
    with pytest.raises(SyntheticError, match=r"indoor\?speed=2: unknown parameter 'speed'; known: seed, size"):
        synthetic_url("synthetic://indoor?speed=2")
    with pytest.raises(ValueError, match=r"video0\?speed=2: unknown parameter 'speed'; known: stereo, right"):
        v4l2.parse_url("v4l2:///dev/video0?speed=2")
    pytest.importorskip("depthai")  # the OAK-D driver's vendor library
    from illuminet.hw import oakd

    with pytest.raises(ValueError, match=r"oakd://\?speed=2: unknown parameter 'speed'; known: fps, size"):
        oakd.parse_url("oakd://?speed=2")
