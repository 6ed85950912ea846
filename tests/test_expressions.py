import numpy as np
import pytest

from mission_runner.expressions import ExpressionError, compile_expression


def test_expression_evaluates_on_arrays():
    f = compile_expression("2 * sin(pi * t / 100) + 4")
    t = np.array([0.0, 50.0, 150.0])
    np.testing.assert_allclose(f(t), [4.0, 6.0, 2.0])
    assert compile_expression("3")(np.zeros(4)).shape == (4,)
    np.testing.assert_allclose(compile_expression("where(t < 1, 0, 1)")(np.array([0.5, 2])), [0, 1])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("__import__('os').system('true')", "Call is not allowed"),
        ("__import__('os')", "unknown function '__import__'"),
        ("t.real", "Attribute is not allowed"),
        ("(lambda: 1)()", "not allowed"),
        ("x + 1", "unknown name 'x'"),
        ("[1, 2][0]", "not allowed"),
        ("'a' * 3", "not allowed"),
        ("sin(", "not a valid expression"),
        ("sin(1, 2, 3)", "sin()"),
        ("1" * 600, "longer than"),
    ],
)
def test_anything_but_arithmetic_is_refused(text, message):
    with pytest.raises(ExpressionError, match=message.replace("(", r"\(").replace(")", r"\)")):
        compile_expression(text)


@pytest.mark.parametrize(
    ("text", "value"),
    [("1/0", np.inf), ("10**10**10", np.inf), ("-1/0", -np.inf), ("1 % 0", np.nan)],
)
def test_arithmetic_gives_floats_and_never_raises(text, value):
    # Floats throughout: a huge power overflows to inf at once instead of computing an integer
    # with ten billion digits; whether a value may be infinite is the scenario's check.
    np.testing.assert_array_equal(compile_expression(text)(np.zeros(2)), [value, value])


def test_non_finite_values_come_out_as_they_are():
    values = compile_expression("log(t - 1)")(np.array([0.0, 1.0, 2.0]))
    assert np.isnan(values[0]) and values[1] == -np.inf and values[2] == 0.0


def test_a_number_too_large_for_a_float_is_refused():
    with pytest.raises(ExpressionError, match="number too large"):
        compile_expression("9" * 400)
