"""The KEY=VALUE syntax shared by --topics, --param and --set (mapserver.pairs)."""

from __future__ import annotations

import pytest

from core.config import ConfigError
from mapserver.errors import InputError
from mapserver.pairs import parse_pairs


def test_pairs_are_split_stripped_and_empty_entries_skipped() -> None:
    got = parse_pairs(" image = /cam ,, odometry=/odom,sonar=", flag="--topics", form="KEY=TOPIC", example="image=/a")
    assert got == {"image": "/cam", "odometry": "/odom", "sonar": ""}
    # the texts of a repeated flag count as one list
    assert parse_pairs(["laps=2", "seed=3,drift=0.1"], flag="--param", form="NAME=VALUE", example="laps=2") == {
        "laps": "2", "seed": "3", "drift": "0.1"
    }  # fmt: skip
    assert parse_pairs("", flag="--set", form="KEY=VALUE", example="a=1") == {}


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("laps", "bad --param entry 'laps': expected NAME=VALUE, e.g. laps=2"),
        ("=2", "bad --param entry '=2': expected NAME=VALUE, e.g. laps=2"),
        ("laps=2,laps=3", "bad --param: 'laps' given twice"),
    ],
)
def test_a_bad_pair_names_the_flag_and_the_entry(text: str, message: str) -> None:
    with pytest.raises(InputError) as caught:
        parse_pairs(text, flag="--param", form="NAME=VALUE", example="laps=2")
    assert str(caught.value) == message
    with pytest.raises(ConfigError):  # each flag raises its own kind of error
        parse_pairs(text, flag="--set", form="KEY=VALUE", example="a=1", error=ConfigError)
