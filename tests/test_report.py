"""Report formatting: a measurement never prints as a bare zero, size ratios stay readable."""

from __future__ import annotations

from pipeline25d.report import _ratio, fmt_measure


def test_measurements_never_print_as_zero():
    assert fmt_measure(None, missing="n/a (2 check points)") == "n/a (2 check points)"
    assert fmt_measure(0.0) == "< 1e-06" and fmt_measure(4e-7) == "< 1e-06"
    assert fmt_measure(0.00042) == "0.00042" and fmt_measure(0.1234) == "0.123"


def test_size_ratio_puts_the_larger_side_first():
    assert _ratio(34.5) == "34.5 : 1"
    assert _ratio(19.76 / 423.86) == "1 : 21.5"          # maps larger than the model: not "0.0 : 1"
