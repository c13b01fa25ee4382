"""``harness.core.checks``: the one way every setting is checked, and the one-line message."""

from __future__ import annotations

import math

import pytest

from harness.core import checks


def test_a_good_value_comes_back_as_the_type_the_code_uses() -> None:
    assert checks.integer("k", 3.0) == 3 and type(checks.integer("k", 3.0)) is int  # 3e0 typed
    assert checks.positive("k", 2) == 2.0 and type(checks.positive("k", 2)) is float
    assert checks.non_negative("k", 0) == 0.0
    assert checks.in_range("k", 1.0, 0.0, 1.0, open_low=True) == 1.0
    assert checks.choice("k", "a", ("a", "b")) == "a"
    assert checks.boolean("k", False) is False
    assert checks.finite("k", -1e300) == -1e300


@pytest.mark.parametrize(
    ("check", "message"),
    [
        (lambda: checks.positive("plant.tire.road_friction", -1.0), "must be > 0 (got -1)"),
        (lambda: checks.positive("k", "1e-4"), "must be a number > 0 (got '1e-4')"),
        (lambda: checks.positive("k", True), "must be a number > 0 (got True)"),
        (lambda: checks.positive("k", math.inf), "must be > 0 (got inf)"),
        (lambda: checks.non_negative("k", -0.5), "must be >= 0 (got -0.5)"),
        (lambda: checks.integer("k", 7.5), "must be an integer >= 1 (got 7.5)"),
        (lambda: checks.integer("k", 0), "must be an integer >= 1 (got 0)"),
        (lambda: checks.integer("k", -1, minimum=0), "must be an integer >= 0 (got -1)"),
        (lambda: checks.in_range("k", 0.0, 0.0, 1.0, open_low=True), "must be in (0, 1] (got 0)"),
        (lambda: checks.in_range("k", 1.5, 0.0, 1.0), "must be in [0, 1] (got 1.5)"),
        (lambda: checks.choice("k", "osqp", ("daqp", "piqp")), "must be one of daqp, piqp"),
        (lambda: checks.boolean("k", 1), "must be true or false (got 1)"),
        (lambda: checks.finite("k", math.nan), "must be a finite number (got nan)"),
    ],
)
def test_a_bad_value_is_refused_in_one_line_that_names_the_key(check, message) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError) as error:
        check()
    text = str(error.value)
    assert message in text and "\n" not in text
    assert text.split(" must be ")[0] in ("k", "plant.tire.road_friction")
