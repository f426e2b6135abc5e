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

from ..errors import ModelError

FUNCTIONS = {
    "sign": sp.sign,
    "abs": sp.Abs,
    "sqrt": sp.sqrt,
    "exp": sp.exp,
    "sin": sp.sin,
    "cos": sp.cos,
    "tanh": sp.tanh,
    # written with abs, so the filter smooths them as it smooths abs (ardcore.model.kinks)
    "max": lambda a, b: (a + b + sp.Abs(a - b)) / 2,
    "min": lambda a, b: (a + b - sp.Abs(a - b)) / 2,
}
"""Functions allowed in model expressions."""

ARITY = {"max": 2, "min": 2}
"""Arguments of the functions that do not take one."""

CONSTANTS = {"pi": sp.pi}

MAX_EXPRESSION_LENGTH = 2000
MAX_NODES = 600
"""Syntax-tree nodes one expression may hold (numbers, names, operators, calls)."""
MAX_DEPTH = 100
"""Nesting depth of one expression's syntax tree (``-(-(-x))`` is 4 deep; a sum of n terms n deep)."""
MAX_EXPANDED = 5000
"""Nodes of one expression once the derived quantities it uses are written out (a chain of derived terms
that each use the previous one twice doubles with every link)."""
MAX_EXPONENT = 64
"""Largest integer power of a symbolic base (``x**64``); larger ones only blow up the derivatives."""

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
    try:
        tree = ast.parse(source.strip(), mode="eval")
    except SyntaxError as exc:
        raise ModelError(f"{where}: cannot parse {source!r}: {exc.msg}") from None
    except (RecursionError, MemoryError):
        raise ModelError(f"{where}: expression nested too deeply") from None
    text = source.strip()
    _check_size(tree, where)

    return _Whitelist(set(names), text, where).visit(tree)


class _Whitelist:
    """The walk of :func:`parse_expression`: each allowed node becomes sympy, anything else a ModelError."""

    def __init__(self, allowed: set, text: str, where: str):
        self.allowed, self.text, self.where = allowed, text, where

    def visit(self, node: ast.AST) -> sp.Expr:
        if isinstance(node, ast.Expression):
            return self.visit(node.body)
        for kind, method in ((ast.Constant, self._constant), (ast.Name, self._name), (ast.BinOp, self._binop),
                             (ast.UnaryOp, self._unary), (ast.Call, self._call)):
            if isinstance(node, kind):
                return method(node)
        raise ModelError(f"{self.where}: token {_token(node, self.text)!r} is not allowed in {self.text!r}")

    def _constant(self, node: ast.Constant) -> sp.Expr:
        v, where, text = node.value, self.where, self.text
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ModelError(f"{where}: token {_token(node, text)!r} is not allowed (only numbers)")
        if not math.isfinite(v):
            raise ModelError(f"{where}: non-finite number {_token(node, text)!r}")
        return sp.Integer(v) if isinstance(v, int) else sp.Float(v)

    def _name(self, node: ast.Name) -> sp.Expr:
        if node.id in self.allowed:
            return sp.Symbol(node.id, real=True)
        if node.id in CONSTANTS:
            return CONSTANTS[node.id]
        if node.id in FUNCTIONS:
            raise ModelError(f"{self.where}: function {node.id!r} must be called, e.g. {node.id}(x)")
        raise ModelError(f"{self.where}: unknown name {node.id!r} in {self.text!r}")

    def _binop(self, node: ast.BinOp) -> sp.Expr:
        where, text = self.where, self.text
        op = _BINOPS.get(type(node.op))
        if op is None:
            tok = _OP_TOKENS.get(type(node.op), type(node.op).__name__)
            raise ModelError(f"{where}: operator {tok!r} is not allowed in {text!r}")
        a, b = self.visit(node.left), self.visit(node.right)
        # a numeric power of a symbolic base is bounded (a symbolic exponent is not a blow-up)
        if isinstance(node.op, ast.Pow) and b.is_number and a.free_symbols:
            if not (b.is_real and abs(float(b)) <= MAX_EXPONENT):
                raise ModelError(f"{where}: exponent {_token(node.right, text)!r} is too large "
                                 f"(at most {MAX_EXPONENT}) in {text!r}")
        if a.is_number and b.is_number:
            return _fold(type(node.op), a, b, node, text, where)
        return _finite_result(op(a, b), node, text, where)

    def _unary(self, node: ast.UnaryOp) -> sp.Expr:
        if isinstance(node.op, ast.USub):
            return -self.visit(node.operand)
        if isinstance(node.op, ast.UAdd):
            return self.visit(node.operand)
        tok = _OP_TOKENS.get(type(node.op), type(node.op).__name__)
        raise ModelError(f"{self.where}: operator {tok!r} is not allowed in {self.text!r}")

    def _call(self, node: ast.Call) -> sp.Expr:
        where, text = self.where, self.text
        if not isinstance(node.func, ast.Name) or node.func.id not in FUNCTIONS:
            raise ModelError(f"{where}: function {_token(node.func, text)!r} is not allowed "
                             f"(allowed: {', '.join(sorted(FUNCTIONS))})")
        arity = ARITY.get(node.func.id, 1)
        if node.keywords or len(node.args) != arity:
            count = "one argument" if arity == 1 else f"{arity} arguments"
            raise ModelError(f"{where}: {node.func.id}() takes exactly {count}")
        return _finite_result(FUNCTIONS[node.func.id](*map(self.visit, node.args)), node, text, where)


def _check_size(tree: ast.AST, where: str) -> None:
    """Reject trees too large or too deep to differentiate and compile in reasonable time and memory."""
    n = 0
    stack = [(tree, 0)]
    while stack:
        node, depth = stack.pop()
        n += 1
        if n > MAX_NODES:
            raise ModelError(f"{where}: expression too large (more than {MAX_NODES} terms and operators)")
        if depth > MAX_DEPTH:
            raise ModelError(f"{where}: expression nested too deeply (more than {MAX_DEPTH} levels)")
        stack.extend((c, depth + 1) for c in ast.iter_child_nodes(node))


def _fold(op: type, a: sp.Expr, b: sp.Expr, node: ast.AST, text: str, where: str) -> sp.Expr:
    """A constant sub-expression, evaluated in float64: it must stay finite and real (``9**9**9**9``,
    ``2**2000``, ``1/0`` and ``(-1)**0.5`` are rejected here instead of hanging or failing in the kernel)."""
    x, y = complex(a), complex(b)
    if x.imag or y.imag:
        raise ModelError(f"{where}: {_token(node, text)!r} is not a real number")
    x, y = x.real, y.real
    try:
        if op is ast.Pow:
            if x < 0 and not float(y).is_integer():
                raise ValueError("complex")
            v = math.pow(x, y)
        elif op is ast.Div:
            v = x / y
        else:
            v = _BINOPS[op](x, y)
    except (OverflowError, ZeroDivisionError, ValueError):
        v = math.nan
    if not math.isfinite(v):
        raise ModelError(f"{where}: {_token(node, text)!r} is not a finite real number in float64")
    exact = _BINOPS[op](a, b)
    # keep exact integers and rationals (derivatives stay clean); anything else as its float64 value
    return exact if exact.is_Rational and abs(v) < 2**53 else sp.Float(v)


def _finite_result(e: sp.Expr, node: ast.AST, text: str, where: str) -> sp.Expr:
    bad = e.has(sp.zoo, sp.oo, -sp.oo, sp.nan, sp.I)
    if not bad:
        # every constant, and a constant result such as exp(1000), must be a finite float64
        consts = [e] if e.is_number else list(e.atoms(sp.Number))
        try:
            bad = any(not math.isfinite(float(c)) for c in consts)
        except (TypeError, OverflowError):
            bad = True
    if bad:
        raise ModelError(f"{where}: {_token(node, text)!r} is not finite and real in float64 (division by "
                         f"zero, overflow or a complex number)")
    return e


def expanded_size(source, sizes: dict[str, int], *, where: str = "expression") -> int:
    """Syntax-tree nodes of ``source`` with each name in ``sizes`` (a derived quantity) counted as the
    nodes of its own written-out expression; raises :class:`ModelError` above :data:`MAX_EXPANDED`."""
    if not isinstance(source, str):
        return 1
    try:
        tree = ast.parse(source.strip(), mode="eval")
    except (SyntaxError, RecursionError, MemoryError, ValueError):
        return 1  # parse_expression reports it with its reason
    n = 0
    for node in ast.walk(tree):
        n += sizes.get(node.id, 1) if isinstance(node, ast.Name) else 1
    if n > MAX_EXPANDED:
        raise ModelError(f"{where}: expression too large once the derived quantities it uses are written out "
                         f"({n} > {MAX_EXPANDED} terms and operators)")
    return n
