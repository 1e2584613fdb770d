"""TOML read with bounded nesting (kmea.wire.tomlvalue.loads): refused before tomllib
recurses, brackets inside strings and comments not counted."""

from __future__ import annotations

import pytest

from kmea.wire import tomlvalue as toml


def test_deep_nesting_is_refused_before_tomllib_sees_it() -> None:
    with pytest.raises(toml.TooDeep, match="700 levels, at most 64"):
        toml.loads("a = " + "[" * 700 + "]" * 700)
    with pytest.raises(toml.TooDeep):
        toml.loads("a = " + "{b = " * 65 + "1" + "}" * 65)
    deep_ok = "a = " + "[" * 64 + "1" + "]" * 64
    assert toml.loads(deep_ok)["a"] is not None


def test_brackets_in_strings_comments_and_headers_do_not_count() -> None:
    text = ('# [[[[ ' + "[" * 100 + '\n[[robots]]\nname = "' + "[" * 100 + '"\n'
            "lit = '" + "{" * 100 + "'\n" + 'multi = """\n' + "[" * 100 + '\n"""\n'
            'esc = "\\"[[[["\nmarkers = [40, 41]\n')
    data = toml.loads(text)
    assert data["robots"][0]["name"] == "[" * 100 and data["robots"][0]["markers"] == [40, 41]
    assert data["robots"][0]["esc"] == '"[[[['


def test_a_typed_in_value_too_deep_is_a_string_for_validation_to_refuse() -> None:
    assert toml.parse_toml_value("[" * 700 + "]" * 700) == "[" * 700 + "]" * 700
    assert toml.parse_toml_value("[40, 41]") == [40, 41]
