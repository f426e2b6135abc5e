"""Whitelisted parsing of user-written model expressions into sympy.

Expressions arrive over HTTP, so they are never passed to ``eval`` or
``sympify``. Python's own parser builds a syntax tree, and only the node
types listed here are translated; anything else is rejected with a message
that names the offending token.
"""

from __future__ import annotations

import ast
import math
from typing import Iterable

import sympy as sp

from .errors import ModelError

FUNCTIONS = {
    "sign": sp.sign,
    "abs": sp.Abs,
    "sqrt": sp.sqrt,
    "exp": sp.exp,
    "sin": sp.sin,
    "cos": sp.cos,
    "tanh": sp.tanh,
}
"""Functions allowed in model expressions."""

CONSTANTS = {"pi": sp.pi}

MAX_EXPRESSION_LENGTH = 2000

_BINOPS = {
    ast.Add: lambda a, b: a + b,
    ast.Sub: lambda a, b: a - b,
    ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b,
    ast.Pow: lambda a, b: a**b,
}

_OP_TOKENS = {
    ast.FloorDiv: "//", ast.Mod: "%", ast.MatMult: "@", ast.BitAnd: "&",
    ast.BitOr: "|", ast.BitXor: "^", ast.LShift: "<<", ast.RShift: ">>",
    ast.Not: "not", ast.Invert: "~",
}


def _token(node: ast.AST, source: str) -> str:
    seg = ast.get_source_segment(source, node)
    return seg if seg else type(node).__name__


def parse_expression(source: str, names: Iterable[str], *, where: str = "expression") -> sp.Expr:
    """Parse one model expression with a whitelist.

    Parameters
    ----------
    source : str
        The expression, e.g. ``"B*(a1*theta - CM) + c6*F"``.
    names : iterable of str
        Names the expression may refer to (states, parameters, constants,
        inputs, derived quantities). ``pi`` is always available.
    where : str
        Where the expression comes from, used in error messages.

    Returns
    -------
    sympy.Expr
        The expression with every name as a real ``sympy.Symbol``.

    Raises
    ------
    ModelError
        On syntax errors, unknown names, or any token outside the whitelist
        (numbers, names, ``+ - * / **``, unary sign, and the functions in
        :data:`FUNCTIONS`).
    """
    if not isinstance(source, str):
        if isinstance(source, (int, float)) and not isinstance(source, bool) and math.isfinite(source):
            return sp.Float(source) if isinstance(source, float) else sp.Integer(source)
        raise ModelError(f"{where}: expected an expression string, got {source!r}")
    if len(source) > MAX_EXPRESSION_LENGTH:
        raise ModelError(f"{where}: expression longer than {MAX_EXPRESSION_LENGTH} characters")
    if not source.strip():
        raise ModelError(f"{where}: empty expression")
    allowed = set(names)
    try:
        tree = ast.parse(source.strip(), mode="eval")
    except SyntaxError as exc:
        raise ModelError(f"{where}: cannot parse {source!r}: {exc.msg}") from None
    text = source.strip()

    def visit(node: ast.AST) -> sp.Expr:
        if isinstance(node, ast.Expression):
            return visit(node.body)
        if isinstance(node, ast.Constant):
            v = node.value
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ModelError(f"{where}: token {_token(node, text)!r} is not allowed (only numbers)")
            if not math.isfinite(v):
                raise ModelError(f"{where}: non-finite number {_token(node, text)!r}")
            return sp.Integer(v) if isinstance(v, int) else sp.Float(v)
        if isinstance(node, ast.Name):
            if node.id in allowed:
                return sp.Symbol(node.id, real=True)
            if node.id in CONSTANTS:
                return CONSTANTS[node.id]
            if node.id in FUNCTIONS:
                raise ModelError(f"{where}: function {node.id!r} must be called, e.g. {node.id}(x)")
            raise ModelError(f"{where}: unknown name {node.id!r} in {text!r}")
        if isinstance(node, ast.BinOp):
            op = _BINOPS.get(type(node.op))
            if op is None:
                tok = _OP_TOKENS.get(type(node.op), type(node.op).__name__)
                raise ModelError(f"{where}: operator {tok!r} is not allowed in {text!r}")
            return op(visit(node.left), visit(node.right))
        if isinstance(node, ast.UnaryOp):
            if isinstance(node.op, ast.USub):
                return -visit(node.operand)
            if isinstance(node.op, ast.UAdd):
                return visit(node.operand)
            tok = _OP_TOKENS.get(type(node.op), type(node.op).__name__)
            raise ModelError(f"{where}: operator {tok!r} is not allowed in {text!r}")
        if isinstance(node, ast.Call):
            if not isinstance(node.func, ast.Name) or node.func.id not in FUNCTIONS:
                raise ModelError(f"{where}: function {_token(node.func, text)!r} is not allowed "
                                 f"(allowed: {', '.join(sorted(FUNCTIONS))})")
            if node.keywords or len(node.args) != 1:
                raise ModelError(f"{where}: {node.func.id}() takes exactly one argument")
            return FUNCTIONS[node.func.id](visit(node.args[0]))
        raise ModelError(f"{where}: token {_token(node, text)!r} is not allowed in {text!r}")

    return visit(tree)
