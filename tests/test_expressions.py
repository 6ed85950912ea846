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
