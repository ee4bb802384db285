"""Success checks as code, run in a sandbox: `def check(): return <bool>` over a read-only state API.

Checks are written by a language model (or `datagen.checks`' templates) and judge every generated episode,
so a snippet is untrusted code, and stripping builtins alone does not sandbox Python. The defence is a
whitelist over the AST before anything runs:
* one `def check():` (no arguments, decorators, annotations) plus docstrings; inside it only return,
  assignment to plain names (tuple unpacking, `+=`), if, for, break/continue/pass, expression statements,
  and/or/not, + - * / // % **, comparisons (no `is`), `x if c else y`, calls, bool/int/float/str/None
  constants, names, tuple/list literals, read-only subscripts/slices, list/generator comprehensions;
* refused: import, any attribute access, lambda, nested def, class, while, with, try, raise, assert, del,
  global/nonlocal, yield/await, walrus, starred, f-strings, dict/set, bit operators;
* a call names a whitelisted function directly (`API_FUNCTIONS`, `BUILTINS`); those names cannot be rebound
  or used as values and `check` cannot be referenced, so no recursion; identifiers are ASCII without `_`
  prefix; source ≤ 4000 chars, ≤ 1500 nodes, nesting ≤ 40, int literals ≤ 1e18; no arithmetic on strings
  or sequence literals ('a' * n, [0] * n, "%s" % x), no nested `**`, constant exponents ≤ 64.
At run time arithmetic is guarded (numbers only, ints ≤ 256 bits, no complex), `range` ≤ 1000 items, each
loop iteration and API call spends a step budget (plus a wall-clock deadline), and the API returns plain
bools, floats and tuples, never numpy. Every failure is a `SandboxError` naming the construct and line.
A check must return a real `bool`: None, 0/1 or a float are refused, not coerced, so a check that forgot
its comparison fails loudly instead of judging episodes by truthiness.
"""

from __future__ import annotations

import ast
import math
import operator
import re
import time
import warnings
from dataclasses import dataclass
from functools import lru_cache
from types import GeneratorType

MAX_SOURCE_CHARS, MAX_NODES, MAX_DEPTH = 4000, 1500, 40
MAX_STR, MAX_INT_LITERAL, MAX_INT_BITS, MAX_EXPONENT, MAX_RANGE = 500, 10**18, 256, 64, 1000
DEFAULT_MAX_STEPS, DEFAULT_MAX_SECONDS, API_COST = 100_000, 1.0, 10

# name -> (min args, max args)
API_FUNCTIONS = {"inside": (2, 2), "on_top": (2, 2), "in_contact": (2, 2), "holding": (1, 1),
                 "joint_fraction": (1, 1), "joint_value": (1, 1), "position": (1, 1), "aabb": (1, 1),
                 "distance": (2, 2)}
BUILTINS = {"abs": (1, 1), "min": (1, 20), "max": (1, 20), "all": (1, 1), "any": (1, 1), "len": (1, 1),
            "range": (1, 3), "round": (1, 2), "float": (1, 1), "int": (1, 1), "bool": (1, 1)}
CALLABLE = {**API_FUNCTIONS, **BUILTINS}
JOINT_FUNCTIONS = ("joint_fraction", "joint_value")
EXTRA_NAMES = {"in_contact": ("robot",)}  # besides the scene's names: "robot" = arm + gripper

_ALLOWED = {ast.Return, ast.Assign, ast.AugAssign, ast.If, ast.For,
            ast.Break, ast.Continue, ast.Pass, ast.Expr, ast.BoolOp, ast.And, ast.Or, ast.BinOp, ast.Add, ast.Sub,
            ast.Mult, ast.Div, ast.FloorDiv, ast.Mod, ast.Pow, ast.UnaryOp, ast.Not, ast.USub, ast.UAdd,
            ast.Compare, ast.Eq, ast.NotEq, ast.Lt, ast.LtE, ast.Gt, ast.GtE, ast.In, ast.NotIn, ast.IfExp,
            ast.Call, ast.Constant, ast.Name, ast.Load, ast.Store, ast.Tuple, ast.List, ast.Subscript, ast.Slice,
            ast.GeneratorExp, ast.ListComp, ast.comprehension}
_NAMES = {"Import": "import", "ImportFrom": "import", "Attribute": "attribute access", "Lambda": "lambda",
          "While": "while loop", "With": "with statement", "Try": "try/except", "TryStar": "try/except*",
          "Raise": "raise", "Assert": "assert", "Delete": "del", "Global": "global", "Nonlocal": "nonlocal",
          "ClassDef": "class definition", "Yield": "yield", "YieldFrom": "yield from", "Await": "await",
          "AsyncFunctionDef": "async def", "FunctionDef": "nested def", "Starred": "starred expression",
          "JoinedStr": "f-string",
          "FormattedValue": "f-string", "NamedExpr": "walrus (:=)", "Dict": "dict literal", "Set": "set literal",
          "DictComp": "dict comprehension", "SetComp": "set comprehension", "Match": "match statement",
          "Is": "`is` comparison", "IsNot": "`is not` comparison", "LShift": "<<", "RShift": ">>",
          "BitOr": "|", "BitAnd": "&", "BitXor": "^", "Invert": "~", "MatMult": "@", "keyword": "keyword argument"}
_IDENT = re.compile(r"[A-Za-z][A-Za-z0-9_]*\Z")
_OPS = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/", ast.FloorDiv: "//", ast.Mod: "%", ast.Pow: "**"}
_FUNCS = {"+": operator.add, "-": operator.sub, "*": operator.mul, "/": operator.truediv,
          "//": operator.floordiv, "%": operator.mod, "**": operator.pow}


class SandboxError(ValueError):
    """A snippet the sandbox refuses to compile or that failed while running; the message says where."""


def _fail(what: str, node: ast.AST | None = None) -> SandboxError:
    line = getattr(node, "lineno", None)
    return SandboxError(f"{what} (line {line})" if line else what)


def _what(node: ast.AST) -> str:
    return _NAMES.get(type(node).__name__, type(node).__name__)


def _validate(tree: ast.Module) -> list[tuple[str, int, str, int]]:
    """Whitelist walk; returns the (function, arg index, literal, line) of API calls with a string literal."""
    funcs = [n for n in tree.body if isinstance(n, ast.FunctionDef)]
    for stmt in tree.body:
        if not (isinstance(stmt, ast.FunctionDef) or (isinstance(stmt, ast.Expr) and isinstance(
                stmt.value, ast.Constant) and isinstance(stmt.value.value, str))):
            raise _fail(f"only `def check():` and docstrings may stand at the top level, found {_what(stmt)}", stmt)
    for f in funcs:
        if f.name != "check" or len(funcs) != 1:
            raise _fail(f"exactly one function, `def check():`, may be defined; found def {f.name!r}", f)
    if not funcs:
        raise SandboxError("the snippet must define `def check():`")
    fn, a = funcs[0], funcs[0].args
    if fn.decorator_list or fn.returns or a.posonlyargs or a.args or a.vararg or a.kwonlyargs or a.kwarg:
        raise _fail("`def check():` takes no arguments, decorators or annotations", fn)
    if not any(isinstance(n, ast.Return) and n.value is not None for n in ast.walk(fn)):
        raise _fail("check() must `return <bool>`", fn)
    stack, count, callees, stored, loaded, literals = [(n, 1) for n in reversed(fn.body)], 0, set(), set(), [], []
    while stack:
        node, depth = stack.pop()
        count += 1
        if count > MAX_NODES or depth > MAX_DEPTH:
            raise _fail(f"snippet too large or too deeply nested (max {MAX_NODES} nodes, depth {MAX_DEPTH})", node)
        if type(node) not in _ALLOWED:
            raise _fail(f"{_what(node)} is not allowed", node)
        if isinstance(node, ast.Name):
            if not _IDENT.match(node.id):
                raise _fail(f"name {node.id!r} is not allowed (ASCII, not starting with '_')", node)
            if node.id == "check" or (node.id in CALLABLE and isinstance(node.ctx, ast.Store)):
                raise _fail(f"{node.id!r} cannot be referenced or rebound", node)
            if isinstance(node.ctx, ast.Store):
                stored.add(node.id)
            else:
                loaded.append(node)
        elif isinstance(node, ast.Call):
            f = node.func
            if type(f) not in _ALLOWED:
                raise _fail(f"{_what(f)} is not allowed", f)
            if not (isinstance(f, ast.Name) and f.id in CALLABLE):
                name = repr(f.id) if isinstance(f, ast.Name) else f"a {type(f).__name__} expression"
                raise _fail(f"call of {name} is not allowed; callable: {sorted(CALLABLE)}", node)
            lo, hi = CALLABLE[f.id]
            if node.keywords or not lo <= len(node.args) <= hi:
                raise _fail(f"{f.id}() takes {lo}..{hi} positional arguments (keyword arguments are not allowed)",
                            node)
            callees.add(id(f))
            if f.id in API_FUNCTIONS:
                literals += [(f.id, i, a.value, node.lineno) for i, a in enumerate(node.args)
                             if isinstance(a, ast.Constant) and isinstance(a.value, str)]
        elif isinstance(node, ast.Constant):
            v = node.value
            if type(v) not in (bool, int, float, str, type(None)):
                raise _fail(f"constant of type {type(v).__name__} is not allowed", node)
            if (type(v) is int and abs(v) > MAX_INT_LITERAL) or (type(v) is str and len(v) > MAX_STR):
                raise _fail("literal too large", node)
        elif isinstance(node, ast.BinOp):
            op, r = _OPS.get(type(node.op)), node.right
            if op is None:
                raise _fail(f"{_what(node.op)} is not allowed", node)
            if any(isinstance(side, (ast.List, ast.Tuple, ast.ListComp)) or (isinstance(side, ast.Constant) and
                                                                             isinstance(side.value, str))
                   for side in (node.left, r)):
                raise _fail(f"operator {op} on a string or sequence is not allowed", node)
            if op == "**" and isinstance(r, ast.BinOp) and isinstance(r.op, ast.Pow):
                raise _fail("nested exponentiation is not allowed", node)
            if op == "**" and isinstance(r, ast.Constant) and type(r.value) in (int, float) and abs(
                    r.value) > MAX_EXPONENT:
                raise _fail(f"exponent larger than {MAX_EXPONENT} is not allowed", node)
        elif isinstance(node, (ast.Assign, ast.AugAssign, ast.For, ast.comprehension)):
            for t in node.targets if isinstance(node, ast.Assign) else [node.target]:
                if not (isinstance(t, ast.Name) or (not isinstance(node, ast.AugAssign) and isinstance(
                        t, (ast.Tuple, ast.List)) and all(isinstance(e, ast.Name) for e in t.elts))):
                    raise _fail("assignment targets must be plain names", node)
            if getattr(node, "is_async", 0):
                raise _fail("async comprehension is not allowed", node)
        stack.extend(reversed([(child, depth + 1) for child in ast.iter_child_nodes(node)]))  # source order
    for n in loaded:
        if n.id in CALLABLE and id(n) not in callees:
            raise _fail(f"{n.id!r} may only be called, not used as a value", n)
        if n.id not in CALLABLE and n.id not in stored:
            raise _fail(f"unknown name {n.id!r}; callable: {sorted(CALLABLE)}", n)
    return literals


class _Guard(ast.NodeTransformer):
    """Routes arithmetic through `_sb_binop` and every iteration through `_sb_iter` (bounded, budgeted)."""

    @staticmethod
    def _call(op, left, right):
        return ast.Call(ast.Name("_sb_binop", ast.Load()), [ast.Constant(_OPS[type(op)]), left, right], [])

    def visit_BinOp(self, node):
        self.generic_visit(node)
        return self._call(node.op, node.left, node.right)

    def visit_AugAssign(self, node):
        self.generic_visit(node)
        value = self._call(node.op, ast.Name(node.target.id, ast.Load()), node.value)
        return ast.Assign([node.target], value, lineno=node.lineno)

    def _wrap(self, node):
        self.generic_visit(node)
        node.iter = ast.Call(ast.Name("_sb_iter", ast.Load()), [node.iter], [])
        return node

    visit_For = visit_comprehension = _wrap


@dataclass(frozen=True)
class CompiledCheck:
    """A snippet that passed the static rules; `run` evaluates it against one state."""

    source: str
    code: object
    literals: tuple

    def run(self, state, scene, max_steps: int = DEFAULT_MAX_STEPS,
            max_seconds: float = DEFAULT_MAX_SECONDS) -> bool:
        budget = _Budget(max_steps, max_seconds)
        ns = {"__builtins__": {}, "_sb_binop": _binop, "_sb_iter": budget.iter, **_builtins(budget),
              **_api(state, scene, budget)}
        try:
            exec(self.code, ns)
            result = ns["check"]()
        except Exception as e:  # SandboxError from the guards, or the snippet's own TypeError etc.
            raise SandboxError(_runtime_message(e)) from None
        _need(type(result) is bool, f"check() must return a bool, got {type(result).__name__} {result!r:.60}")
        return result


def compile_check(source: str, scene=None) -> CompiledCheck:
    """Parse and verify `source` against the rules; with `scene`, also the names its API calls spell out."""
    _need(isinstance(source, str), f"a check snippet must be a string, got {type(source).__name__}")
    compiled = _compile(source)
    if scene is not None:
        for fn, _i, value, line in compiled.literals:
            _check_name(fn, value, scene, line)
    return compiled


def run_check(snippet: str, state_view, scene, **limits) -> bool:
    """Compile (cached) and run a check snippet against a `sim.state.StateView` of the scene."""
    return compile_check(snippet, scene).run(state_view, scene, **limits)


@lru_cache(maxsize=512)
def _compile(source: str) -> CompiledCheck:
    _need(len(source) <= MAX_SOURCE_CHARS, f"snippet longer than {MAX_SOURCE_CHARS} characters")
    with warnings.catch_warnings():  # "'int' object is not subscriptable" and the like refuse the snippet
        warnings.simplefilter("error", SyntaxWarning)
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            tree = ast.parse(source, "<check>", "exec")
        except (SyntaxError, ValueError, RecursionError, MemoryError, OverflowError) as e:
            raise SandboxError(f"snippet does not parse: {type(e).__name__}: {e}") from None
        literals = _validate(tree)
        tree = ast.fix_missing_locations(_Guard().visit(tree))
        try:
            code = compile(tree, "<check>", "exec")
        except (SyntaxError, ValueError, RecursionError, MemoryError) as e:
            raise SandboxError(f"snippet does not compile: {type(e).__name__}: {e}") from None
    return CompiledCheck(source, code, tuple(literals))


def _check_name(fn: str, value, scene, line: int | None = None) -> None:
    at = f" (line {line})" if line else ""
    if fn in JOINT_FUNCTIONS:
        _need(value in scene.joints(), f"{fn}(): unknown joint {value!r}{at}; known joints: {scene.joints()}")
    else:
        _need(isinstance(value, str) and (value in scene.names() or value in EXTRA_NAMES.get(fn, ())),
              f"{fn}(): unknown object {value!r}{at}; known: {scene.names()}")


def _runtime_message(e: Exception) -> str:
    tb, line = e.__traceback__, None
    while tb is not None:
        if tb.tb_frame.f_code.co_filename == "<check>":
            line = tb.tb_lineno
        tb = tb.tb_next
    what = str(e) if isinstance(e, SandboxError) else f"check() raised {type(e).__name__}: {e}"
    return f"{what} (line {line})" if line else what


class _Budget:
    """Steps and wall time a run may spend; loops and API calls draw on it."""

    def __init__(self, steps: int, seconds: float):
        self.left, self.deadline, self.steps = steps, time.perf_counter() + seconds, steps

    def tick(self, n: int = 1) -> None:
        self.left -= n
        _need(self.left >= 0, f"check() exceeded its budget of {self.steps} steps")
        _need(time.perf_counter() <= self.deadline, "check() exceeded its time limit")

    def iter(self, it):
        _need(isinstance(it, (tuple, list, str, range, GeneratorType)), f"cannot iterate over {type(it).__name__}")
        for x in it:
            self.tick()
            yield x


def _need(ok, message: str) -> None:
    if not ok:
        raise SandboxError(message)


def _num(fn: str, *values) -> None:
    for v in values:
        _need(type(v) in (bool, int, float), f"{fn} works on numbers only, got {type(v).__name__}")


def _binop(op: str, a, b):
    _num(f"operator {op}", a, b)
    if type(a) is int and type(b) is int:
        _need(not (op == "**" and b > 0 and abs(a) > 1 and a.bit_length() * b > MAX_INT_BITS)
              and not (op == "*" and a.bit_length() + b.bit_length() > MAX_INT_BITS + 1),
              f"integer result of {op} too large")
    try:
        r = _FUNCS[op](a, b)
    except ArithmeticError as e:
        raise SandboxError(f"operator {op}: {type(e).__name__}: {e}") from None
    _need(type(r) is not complex and not (type(r) is int and r.bit_length() > MAX_INT_BITS),
          f"result of {op} is out of range")
    return r


def _builtins(budget: _Budget) -> dict:
    """The safe builtins, as plain functions (no type objects reach the snippet)."""

    def items(fn, args):
        seq = list(budget.iter(args[0])) if len(args) == 1 else list(args)
        _need(seq, f"{fn}() of an empty sequence")
        return seq

    def _range(*a):
        _need(all(type(v) in (int, bool) for v in a), "range() takes integers")
        _need(len(range(*a)) <= MAX_RANGE, f"range() of {len(range(*a))} items; at most {MAX_RANGE}")
        return range(*a)

    def _round(x, nd=None):
        _num("round()", x)
        _need(nd is None or (type(nd) is int and abs(nd) <= 30), "round(): digits must be an integer in -30..30")
        return round(x, nd)

    def _convert(kind):
        def conv(x):
            _need(type(x) in (bool, int, float, str) and not (type(x) is str and len(x) > 100),
                  f"{kind.__name__}() of {type(x).__name__} {x!r:.40}")
            return kind(x)
        return conv

    def _len(x):
        _need(isinstance(x, (tuple, list, str, range)), f"len() of {type(x).__name__}")
        return len(x)

    def _abs(x):
        _num("abs()", x)
        return abs(x)

    return {"abs": _abs, "min": lambda *a: min(items("min", a)), "max": lambda *a: max(items("max", a)),
            "all": lambda it: all(budget.iter(it)), "any": lambda it: any(budget.iter(it)), "len": _len,
            "range": _range, "round": _round, "float": _convert(float), "int": _convert(int),
            "bool": lambda x: bool(x)}


def _api(state, scene, budget: _Budget) -> dict:
    """The read-only state API over plain values; names are checked against the scene first."""

    def wrap(fn, impl):
        def call(*args):
            budget.tick(API_COST)
            for a in args:
                _check_name(fn, a, scene)
            try:
                return impl(*args)
            except (KeyError, ValueError, IndexError) as e:
                raise SandboxError(f"{fn}{args!r} failed: {e}") from None
        return call

    def vec(v):
        return tuple(float(x) for x in v)

    impls = {"inside": lambda a, b: bool(state.inside(a, b)), "on_top": lambda a, b: bool(state.on_top(a, b)),
             "in_contact": lambda a, b: bool(state.in_contact(a, b)), "holding": lambda a: bool(state.holding(a)),
             "joint_fraction": lambda j: float(state.joint_fraction(j)),
             "joint_value": lambda j: float(state.joint_value(j)), "position": lambda a: vec(state.position(a)),
             "aabb": lambda a: tuple(vec(v) for v in state.aabb(a)),
             "distance": lambda a, b: float(math.dist(vec(state.position(a)), vec(state.position(b))))}
    return {fn: wrap(fn, impl) for fn, impl in impls.items()}
