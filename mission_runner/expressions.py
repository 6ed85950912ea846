"""Safe arithmetic expressions of time for scenario files, e.g. ``"3 * sin(pi * t / 18.75)"``.

A config never runs Python: an expression is parsed with :mod:`ast` and only numbers, the variable
``t`` (seconds), the constants ``pi`` and ``e``, arithmetic operators and a fixed set of numpy
functions are accepted. The result evaluates element-wise on numpy arrays of times.

Every number is a float64 and every operation numpy's, so arithmetic never raises and never runs
long: ``1/0`` is inf, ``10**10**10`` overflows to inf at once (Python's integers would compute a
ten-billion-digit number). Whether the values are finite where they are used (over a run's
times) is for the caller to check: see ``config``.
"""

import ast
import operator
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: A compiled sub-expression: times ``(...)`` [s] -> its value, an array of the same shape or a
#: number (a constant does not depend on t).
Evaluator = Callable[[NDArray[np.float64]], Any]

FUNCTIONS: dict[str, Callable[..., Any]] = {
    "sin": np.sin,
    "cos": np.cos,
    "tan": np.tan,
    "arctan2": np.arctan2,
    "exp": np.exp,
    "log": np.log,
    "sqrt": np.sqrt,
    "abs": np.abs,
    "sign": np.sign,
    "floor": np.floor,
    "minimum": np.minimum,
    "maximum": np.maximum,
    "clip": np.clip,
    "where": np.where,
}
CONSTANTS = {"pi": np.pi, "e": np.e}
BINARY: dict[type[ast.operator], Callable[[Any, Any], Any]] = {
    ast.Add: operator.add,
    ast.Sub: operator.sub,
    ast.Mult: operator.mul,
    ast.Div: operator.truediv,
    ast.Pow: operator.pow,
    ast.Mod: operator.mod,
}
UNARY: dict[type[ast.unaryop], Callable[[Any], Any]] = {
    ast.USub: operator.neg,
    ast.UAdd: operator.pos,
}
COMPARE: dict[type[ast.cmpop], Callable[[Any, Any], Any]] = {
    ast.Lt: operator.lt,
    ast.LtE: operator.le,
    ast.Gt: operator.gt,
    ast.GtE: operator.ge,
}
MAX_LENGTH = 500


class ExpressionError(ValueError):
    """The text is not an allowed expression; the message says what is not allowed."""


def compile_expression(text: str) -> Callable[[ArrayLike], NDArray[np.float64]]:
    """Parse ``text`` into a function of time ``t`` (float or array, seconds).

    Raises :class:`ExpressionError` naming the offending construct.
    """
    if len(text) > MAX_LENGTH:
        raise ExpressionError(f"expression longer than {MAX_LENGTH} characters")
    try:
        tree = ast.parse(text, mode="eval")
    except SyntaxError as error:
        raise ExpressionError(f"not a valid expression: {error.msg}") from None
    evaluate = _compile(tree.body)

    def function(t: ArrayLike) -> NDArray[np.float64]:
        times = np.asarray(t, dtype=float)
        with np.errstate(all="ignore"):
            return np.broadcast_to(np.asarray(evaluate(times), dtype=float), times.shape).copy()

    try:
        function(np.linspace(0.0, 1.0, 3))  # catches wrong arities and the like at load time
    except (ValueError, TypeError, ArithmeticError) as error:
        raise ExpressionError(f"cannot be evaluated: {error}") from None
    return function


def _compile(node: ast.expr) -> Evaluator:
    constant = node.value if isinstance(node, ast.Constant) else None
    if isinstance(constant, int | float) and not isinstance(constant, bool):
        try:
            number = np.float64(constant)  # numpy's, so that its arithmetic cannot raise
        except OverflowError:
            raise ExpressionError(f"number too large: {str(constant)[:20]}...") from None
        return lambda t: number
    if isinstance(node, ast.Name):
        if node.id == "t":
            return lambda t: t
        if node.id in CONSTANTS:
            value = np.float64(CONSTANTS[node.id])
            return lambda t: value
        raise ExpressionError(f"unknown name {node.id!r}; allowed: t, {', '.join(CONSTANTS)}")
    if isinstance(node, ast.BinOp) and type(node.op) in BINARY:
        op, left, right = BINARY[type(node.op)], _compile(node.left), _compile(node.right)
        return lambda t: op(left(t), right(t))
    if isinstance(node, ast.UnaryOp) and type(node.op) in UNARY:
        unary, operand = UNARY[type(node.op)], _compile(node.operand)
        return lambda t: unary(operand(t))
    if isinstance(node, ast.Compare) and len(node.ops) == 1 and type(node.ops[0]) in COMPARE:
        op, left = COMPARE[type(node.ops[0])], _compile(node.left)
        right = _compile(node.comparators[0])
        return lambda t: op(left(t), right(t))
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and not node.keywords:
        name = node.func.id
        if name not in FUNCTIONS:
            allowed = ", ".join(FUNCTIONS)
            raise ExpressionError(f"unknown function {name!r}; allowed: {allowed}")
        function = FUNCTIONS[name]
        arguments = [_compile(argument) for argument in node.args]

        def call(t: NDArray[np.float64]) -> Any:
            try:
                return function(*(argument(t) for argument in arguments))
            except TypeError as error:
                raise ExpressionError(f"{name}(): {error}") from None

        return call
    raise ExpressionError(f"{type(node).__name__} is not allowed in an expression")
