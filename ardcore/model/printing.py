"""How a symbolic model becomes Python source: sympy expressions printed for numba (scalar math, no
numpy calls), assignment blocks with shared subexpressions, and the names every quantity gets."""

from __future__ import annotations

import sympy as sp
from sympy.printing.pycode import PythonCodePrinter

from .declaration import SymbolicModel


class Printer(PythonCodePrinter):
    """Plain scalar code: math functions unqualified, small integer powers as products."""

    def __init__(self):
        super().__init__({"fully_qualified_modules": False, "standard": "python3"})

    def _print_sign(self, e):
        return f"_sign({self._print(e.args[0])})"

    def _print_SmoothAbs(self, e):
        return f"_sabs({self._print(e.args[0])}, {self._print(e.args[1])})"

    def _print_SmoothSign(self, e):
        return f"_ssign({self._print(e.args[0])}, {self._print(e.args[1])})"

    def _print_SmoothDelta(self, e):
        return f"_sdelta({self._print(e.args[0])}, {self._print(e.args[1])})"

    def _print_Abs(self, e):
        return f"abs({self._print(e.args[0])})"

    def _print_Float(self, e):
        return repr(float(e))

    def _print_Rational(self, e):
        return repr(float(e))

    def _print_Integer(self, e):
        return repr(float(int(e)))

    def _print_Pi(self, e):
        return repr(float(sp.pi))

    def _print_Pow(self, e, rational=False):
        b, x = e.args
        if x.is_Integer and 1 < int(x) <= 6:
            bs = self.parenthesize(b, sp.printing.precedence.PRECEDENCE["Mul"] + 1)
            return "*".join([bs] * int(x))
        if x.is_Integer and -6 <= int(x) < 0:
            bs = self.parenthesize(b, sp.printing.precedence.PRECEDENCE["Mul"] + 1)
            return "(1.0/(" + "*".join([bs] * (-int(x))) + "))"
        if x == sp.S.Half:
            return f"sqrt({self._print(b)})"
        if x == -sp.S.Half:
            return f"(1.0/sqrt({self._print(b)}))"
        return f"({self._print(b)})**({self._print(x)})"

    def _print_Function(self, e):
        name = e.func.__name__
        return f"{name}({', '.join(self._print(a) for a in e.args)})"

    _print_sin = _print_cos = _print_exp = _print_tanh = _print_Function


class Emitter:
    """Turns named sympy expressions into CSE'd assignment lines."""

    def __init__(self, rename: dict, prefix: str):
        self.rename = rename
        self.prefix = prefix
        self.printer = Printer()

    def code(self, e: sp.Expr) -> str:
        return self.printer.doprint(sp.sympify(e).xreplace(self.rename))

    def block(self, targets: list[tuple[str, sp.Expr]], indent: str) -> list[str]:
        if not targets:
            return []
        syms = sp.numbered_symbols(self.prefix)
        repl, red = sp.cse([e for _, e in targets], symbols=syms, optimizations="basic")
        lines = [f"{indent}{s.name} = {self.code(v)}" for s, v in repl]
        lines += [f"{indent}{name} = {self.code(v)}" for (name, _), v in zip(targets, red)]
        return lines


def symbol_names(sm: SymbolicModel):
    n = len(sm.states)
    rename = {}
    for i, s in enumerate(sm.states):
        rename[s] = sp.Symbol(f"x{i}", real=True)
    for i, s in enumerate(sm.params):
        rename[s] = sp.Symbol(f"p{i}", real=True)
    for i, s in enumerate(sm.inputs):
        rename[s] = sp.Symbol(f"f{i}", real=True)
    Psym = [[sp.Symbol(f"P{min(i, j)}_{max(i, j)}", real=True) for j in range(n)] for i in range(n)]
    return rename, Psym


