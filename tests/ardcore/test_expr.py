import pytest
import sympy as sp

from ardflow.ardcore.errors import ModelError
from ardflow.ardcore.model.expr import parse_expression

NAMES = {"x", "y", "a"}


@pytest.mark.parametrize("src", [
    "x + y", "-x**3 * a", "sign(x) + abs(y)", "sqrt(a) * exp(-x)", "sin(x) + cos(y) - tanh(a)",
    "2.5e-3 * x / (1 + y**2)", "+x", "pi * x",
])
def test_accepts_whitelist(src):
    e = parse_expression(src, NAMES)
    assert isinstance(e, sp.Expr)


def test_translation_is_faithful():
    e = parse_expression("a*x**2 - 3*sin(y)/2", NAMES)
    x, y, a = (sp.Symbol(n, real=True) for n in "xya")
    assert sp.simplify(e - (a * x**2 - sp.Rational(3, 2) * sp.sin(y))) == 0


@pytest.mark.parametrize("src,token", [
    ("__import__('os')", "__import__"),
    ("x.real", "x.real"),
    ("x // 2", "//"),
    ("x % 2", "%"),
    ("log(x)", "log"),
    ("z + 1", "'z'"),
    ("x if y else a", "x if y else a"),
    ("[x]", "[x]"),
    ("'abc'", "'abc'"),
    ("lambda: 1", "lambda"),
    ("x == y", "x == y"),
    ("sin", "sin"),
    ("sin(x, y)", "one argument"),
    ("x @ y", "@"),
])
def test_rejects_and_names_the_token(src, token):
    with pytest.raises(ModelError) as ei:
        parse_expression(src, NAMES, where="drift")
    assert token in str(ei.value)
    assert "drift" in str(ei.value)


@pytest.mark.parametrize("src", ["", "   ", "x +", "(x", "1e999 * x"])
def test_rejects_malformed(src):
    with pytest.raises(ModelError):
        parse_expression(src, NAMES)
