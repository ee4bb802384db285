"""The check sandbox: hostile snippets are refused with a SandboxError naming the construct and line,
well-formed checks run, and fuzzed sources/ASTs never crash with anything else or run forbidden code."""

from __future__ import annotations

import ast
import sys
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from datagen.plan import SceneDescription, SceneObject
from datagen.sandbox import SandboxError, compile_check, run_check

SCENE = SceneDescription((SceneObject("obj0", "red block", "object"), SceneObject("obj1", "blue block", "object"),
                          SceneObject("bin_left", "left bin", "container"),
                          SceneObject("cabinet", "drawer", "articulated", joint="cabinet/slide"),
                          SceneObject("table", "table", "surface")))


class FakeState:
    """StateView's interface with numpy-free fixed answers; records the calls it gets."""

    def __init__(self):
        self.calls = []

    def _log(self, *a):
        self.calls.append(a)

    def inside(self, a, b):
        self._log("inside", a, b)
        return a == "obj0" and b == "bin_left"

    def on_top(self, a, b):
        return False

    def in_contact(self, a, b):
        return a == "obj0"

    def holding(self, a):
        return a == "obj1"

    def joint_fraction(self, j):
        return 0.9

    def joint_value(self, j):
        return 0.144

    def position(self, a):
        import numpy as np

        return np.array([0.1, 0.4, 0.02 if a != "obj1" else 0.1])

    def aabb(self, a):
        if a == "table":
            raise KeyError("body 'table' has no geoms")
        p = self.position(a)
        return p - 0.02, p + 0.02


def body(*lines: str) -> str:
    return "def check():\n" + "".join(f"    {line}\n" for line in lines)


GOOD = [
    (body("return inside('obj0', 'bin_left') and not holding('obj0')"), True),
    (body("return joint_fraction('cabinet/slide') >= 0.8"), True),
    (body("return joint_fraction('cabinet/slide') <= 0.2"), False),
    (body("return holding('obj1') and aabb('obj1')[0][2] > 0.03"), True),
    (body("x, y, z = position('obj0')", "return abs(z - 0.02) < 1e-9 and len(position('obj0')) == 3"), True),
    (body("return distance('obj0', 'obj1') > 0.05 and round(distance('obj0', 'obj0'), 3) == 0.0"), True),
    (body("n = 0", "for i in range(10):", "    n += i ** 2", "return n == 285"), True),
    (body("return all(in_contact(o, 'robot') for o in ('obj0',)) and not any([holding(o) for o in ('obj0',)])"),
     True),
    (body("lo, hi = aabb('obj0')", "return max(hi) > max(lo) and int(round(float(hi[2]) * 100)) == 4"), True),
    ('"""A docstring."""\ndef check():\n    """Why."""\n    if holding("obj0"):\n        return False\n'
     '    return bool(1) if 2 > 1 else False\n', True),
    (body("return position('obj0')[0:2] == (0.1, 0.4)"), True),
    (body("for i in range(3):", "    if i == 1:", "        break", "    else:", "        continue",
          "return i == 1"), True),
]


@pytest.mark.parametrize("src,expected", GOOD)
def test_well_formed_checks_run_and_return_bools(src, expected):
    assert run_check(src, FakeState(), SCENE) is expected


def test_api_returns_plain_python_values():
    src = body("p = position('obj0')", "lo, hi = aabb('obj0')",
               "return p == (0.1, 0.4, 0.02) and lo[2] < hi[2] and joint_value('cabinet/slide') > 0.1")
    assert run_check(src, FakeState(), SCENE) is True
    from datagen import sandbox

    api = sandbox._api(FakeState(), SCENE, sandbox._Budget(1000, 1.0))  # what the snippet's names are bound to
    pos, box, frac = api["position"]("obj0"), api["aabb"]("obj0"), api["joint_fraction"]("cabinet/slide")
    assert type(pos) is tuple and all(type(v) is float for v in pos) and type(frac) is float
    assert type(box) is tuple and all(type(v) is tuple and all(type(c) is float for c in v) for v in box)


HOSTILE = [
    ("import os\ndef check():\n    return True", "import"),
    (body("import os", "return True"), "import"),
    (body("from os import system", "return True"), "import"),
    (body("return __import__('os') is None"), "__import__"),
    (body("return getattr(position('obj0'), 'x')"), "getattr"),
    (body("return ().__class__.__mro__[1].__subclasses__() == 1"), "attribute access"),
    (body("return position('obj0').__class__ == 1"), "attribute access"),
    (body("return position('obj0').count(1) == 1"), "attribute access"),
    (body("return open('/etc/passwd') == 1"), "'open'"),
    (body("return eval('1') == 1"), "'eval'"),
    (body("return exec('x=1') is None"), "'exec'"),
    (body("return compile('1', 'f', 'eval') == 1"), "'compile'"),
    (body("while True:", "    pass", "return True"), "while loop"),
    (body("return check()"), "'check'"),
    (body("abs = check", "return abs()"), "'abs'"),
    (body("f = abs", "return f(1) == 1"), "call of 'f'"),
    (body("f = abs", "return True"), "'abs' may only be called"),
    (body("return position('obj0')(1)"), "call of a Call expression"),
    ("def check():\n    def inner():\n        return inner()\n    return inner()\n", "nested def"),
    ("def helper():\n    return True\ndef check():\n    return True\n", "def 'helper'"),
    (body("return len('a' * 10**9) > 0"), "string or sequence"),
    (body("return len([0] * 10**9) > 0"), "string or sequence"),
    (body("return 9**9**9 > 0"), "nested exponentiation"),
    (body("return 2 ** 100000 > 0"), "exponent larger"),
    (body("return 10**10**10 > 0"), "nested exponentiation"),
    (body("return 123456789012345678901234567890 > 0"), "literal too large"),
    (body("return (lambda: True)()"), "lambda"),
    (body("return [x for x in (1,)] == 1 or (yield)"), "yield"),
    (body("g = (x for x in (1, 2))", "return g.gi_frame is None"), "attribute access"),
    (body("return '{0.__class__}'.format(position('obj0')) == ''"), "attribute access"),
    (body("return f'{position(\"obj0\")!r}' == ''"), "f-string"),
    (body("return '%s' % 1 == '1'"), "string or sequence"),
    (body("return type(1) == int"), "'type'"),
    (body("global x", "return True"), "global"),
    (body("nonlocal x", "return True"), "nonlocal"),
    (body("try:", "    return holding('nope')", "except:", "    return True"), "try/except"),
    ("@open\ndef check():\n    return True\n", "decorators"),
    (body("return (y := True)"), "walrus"),
    (body("return [*position('obj0')] == []"), "starred"),
    (body("return __builtins__ == 1"), "'__builtins__'"),
    (body("_x = 1", "return True"), "'_x'"),
    (body("return ｏｐｅｎ('x') == 1"), "'open'"),  # NFKC-normalized by the parser: still refused
    (body("return \u0430bs(1) == 1"), "'\u0430bs'"),  # Cyrillic a: not an ASCII identifier
    (body("with open('x') as f:", "    pass", "return True"), "with statement"),
    ("class A:\n    pass\ndef check():\n    return True\n", "class definition"),
    (body("return {}.get(1) == 1"), "attribute access"),
    (body("return {} == 1"), "dict literal"),
    (body("return holding(*('obj0',))"), "starred"),
    (body("return holding(name='obj0')"), "keyword arguments are not allowed"),
    (body("assert False", "return True"), "assert"),
    (body("raise SystemExit", "return True"), "raise"),
    (body("del x", "return True"), "del"),
    (body("return 1 << 100000 > 0"), "<<"),
    (body("return position('obj0') is None"), "`is` comparison"),
    (body("x = [1]", "x[0] = 2", "return True"), "plain names"),
    (body("return holding('nope')"), "unknown object 'nope'"),
    (body("return joint_fraction('obj0') > 0.5"), "unknown joint 'obj0'"),
    ("async def check():\n    return True\n", "async def"),
    ("def check(x=open):\n    return True\n", "no arguments"),
    ("def check():\n    pass\n", "must `return"),
    ("check = 1\n", "top level"),
    ("x = [i for i in range(10**6)]\ndef check():\n    return True\n", "top level"),
    ("def check(:\n", "does not parse"),
    ("def check():\n    return True\x00\n", "does not parse"),
    ("def check():\n    return " + "(" * 300 + "1" + ")" * 300 + "\n", "does not parse"),
    ("def check():\n    return " + "-" * 80 + "1 > 0\n", "nested"),
    ("def check():\n    return True\n" + "#" * 5000, "longer than"),
]


@pytest.mark.parametrize("src,fragment", HOSTILE)
def test_hostile_snippets_are_refused_with_the_construct_named(src, fragment):
    with pytest.raises(SandboxError) as e:
        run_check(src, FakeState(), SCENE)
    assert fragment in str(e.value), str(e.value)


RUNTIME = [
    (body("for a in range(1000):", "    for b in range(1000):", "        pass", "return True"), "budget"),
    (body("return all(all(True for b in range(1000)) for a in range(1000))"), "budget"),
    (body("return len(range(10**9)) > 0"), "at most 1000"),
    (body("x = 10", "for i in range(100):", "    x = x * x", "return x > 1"), "too large"),
    (body("x = 2", "for i in range(100):", "    x **= 2", "return x > 1"), "too large"),
    (body("x = 10000.0", "return 1.5 ** x > 0"), "OverflowError"),
    (body("return (-8) ** 0.5 > 0"), "out of range"),
    (body("return 1 / 0 > 0"), "ZeroDivisionError"),
    (body("x = 'ab'", "y = x", "return len(x + y) > 0"), "numbers only"),
    (body("return round(5, -10**18) == 0"), "round()"),
    (body("return position('obj0')[7] > 0"), "IndexError"),
    (body("return 1"), "must return a bool, got int"),
    (body("return position('obj0')"), "must return a bool, got tuple"),
    (body("return None or 0.5"), "must return a bool, got float"),
    (body("x = 'obj' + 'x'", "return True"), "string or sequence"),
    (body("name = 'nope'", "return holding(name)"), "unknown object 'nope'"),
    (body("return holding(1)"), "unknown object 1"),
    (body("return int(float('inf')) > 0"), "OverflowError"),
    (body("return min(()) > 0"), "empty"),
    (body("return x > 0", ), "unknown name 'x'"),
    (body("for i in 5:", "    pass", "return True"), "cannot iterate"),
    (body("return aabb('table')[0][0] < 0"), "failed"),
]


@pytest.mark.parametrize("src,fragment", RUNTIME)
def test_runtime_limits_raise_sandbox_errors_quickly(src, fragment):
    t0 = time.perf_counter()
    with pytest.raises(SandboxError) as e:
        run_check(src, FakeState(), SCENE)
    assert fragment in str(e.value), str(e.value)
    assert time.perf_counter() - t0 < 2.0


def test_wall_clock_limit_and_line_numbers():
    src = body("x = 0", "for a in range(1000):", "    for b in range(1000):", "        x += 1", "return True")
    with pytest.raises(SandboxError, match=r"time limit \(line [45]\)"):
        run_check(src, FakeState(), SCENE, max_steps=10**9, max_seconds=0.05)


def test_static_compile_checks_scene_names_without_running():
    compile_check(body("return holding('obj0')"))  # no scene: names unchecked
    with pytest.raises(SandboxError, match=r"unknown object 'obj9' \(line 2\); known: \['obj0'"):
        compile_check(body("return holding('obj9')"), SCENE)
    with pytest.raises(SandboxError, match="a check snippet must be a string"):
        compile_check(None)


# -- fuzzing ----------------------------------------------------------------------------------------------
_EVENTS: list[str] = []
_WATCH = [False]


def _audit(event, args):
    ours = (event == "exec" and getattr(args[0], "co_filename", "") == "<check>") or (
        event == "object.__getattr__" and args[1] in ("tb_frame", "f_code"))  # the sandbox finding the line
    if _WATCH[0] and not ours:
        _EVENTS.append(event)


sys.addaudithook(_audit)


def _run_watched(src: str) -> None:
    """Compile/run must end in a bool or a SandboxError, and the run must raise no audit event (no import,
    open, exec of other code, subprocess, ...)."""
    try:
        checked = compile_check(src, SCENE)
    except SandboxError:
        return
    _EVENTS.clear()
    _WATCH[0] = True
    try:
        result = checked.run(FakeState(), SCENE, max_steps=2000, max_seconds=0.2)
        assert type(result) is bool
    except SandboxError:
        pass
    finally:
        _WATCH[0] = False
    assert not _EVENTS, (_EVENTS, src)


TOKENS = ["def check():\n    ", "return ", "holding(", "'obj0'", "'bin_left'", "inside(", "position(", ")", "(",
          "[", "]", ",", " and ", " or ", " not ", "==", "<", "+", "*", "**", "/", "%", "1", "9", "0.5", "x", "i",
          " for i in range(", " in ", "__import__", "open", ".", "__class__", "lambda: ", "\n    ", "if ", ":",
          "while ", "True", "'a'", "getattr", "min(", "len(", "=", "yield", "import os", "\n", " "]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.sampled_from(TOKENS), max_size=30))
def test_fuzzed_token_soup_never_crashes_or_escapes(tokens):
    _run_watched("".join(tokens))


@settings(max_examples=150, deadline=None)
@given(st.text(max_size=120))
def test_fuzzed_text_never_crashes(text):
    _run_watched(text)
    _run_watched("def check():\n    return " + text)


# Two grammars: a clean one (snippets that mostly compile and run) and one with forbidden pieces mixed in.
_FORBIDDEN = ["check", "open", "__import__", "_p", "type", "getattr"]
_CALLS = [("holding", 1), ("position", 1), ("aabb", 1), ("inside", 2), ("distance", 2), ("joint_fraction", 1),
          ("len", 1), ("range", 1), ("min", 2), ("max", 1), ("abs", 1), ("all", 1), ("round", 2), ("int", 1),
          ("bool", 1)]
_CONSTS = st.sampled_from([0, 1, 2, 9, 64, 10**9, 0.5, -1, "obj0", "bin_left", "cabinet/slide", "a", True, None])
_api_call = st.builds(lambda f, names: ast.Call(ast.Name(f[0], ast.Load()), [ast.Constant(n) for n in names[:f[1]]],
                                                []),
                      st.sampled_from(_CALLS[:6]), st.lists(st.sampled_from(["obj0", "obj1", "bin_left"]), min_size=2,
                                                            max_size=2))


def _grammar(dirty: bool):
    names = ["a", "b"] + (_FORBIDDEN if dirty else [])
    leaf = st.one_of(st.sampled_from(names).map(lambda n: ast.Name(n, ast.Load())), _CONSTS.map(ast.Constant))

    def extend(children):
        binop = st.sampled_from([ast.Add, ast.Sub, ast.Mult, ast.Pow, ast.Mod, ast.Div] + [ast.LShift] * dirty)
        cmp = st.sampled_from([ast.Lt, ast.Gt, ast.Eq, ast.In] + [ast.Is] * dirty)
        options = [
            _api_call, _api_call,
            st.builds(lambda a, op, b: ast.BinOp(a, op(), b), children, binop, children),
            st.builds(lambda a, op, b: ast.Compare(a, [op()], [b]), children, cmp, children),
            st.builds(lambda a, b: ast.BoolOp(ast.And(), [a, b]), children, children),
            st.builds(lambda a: ast.UnaryOp(ast.Not(), a), children),
            st.builds(lambda f, args: ast.Call(ast.Name(f[0], ast.Load()), args[:f[1]], []), st.sampled_from(_CALLS),
                      st.lists(children, min_size=2, max_size=2)),
            st.builds(lambda v, i: ast.Subscript(v, ast.Constant(i), ast.Load()), children,
                      st.sampled_from([0, 1, 2, -1])),
            st.builds(lambda e: ast.Tuple(e, ast.Load()), st.lists(children, max_size=3)),
            st.builds(lambda e, it: ast.GeneratorExp(e, [ast.comprehension(ast.Name("i", ast.Store()), it, [], 0)]),
                      children, children),
        ]
        if dirty:
            options += [
                st.builds(lambda f, args: ast.Call(ast.Name(f, ast.Load()), args, []), st.sampled_from(_FORBIDDEN),
                          st.lists(children, max_size=2)),
                st.builds(lambda v, a: ast.Attribute(v, a, ast.Load()), children,
                          st.sampled_from(["__class__", "real", "format"])),
                st.builds(lambda b: ast.Lambda(ast.arguments([], [], None, [], [], None, []), b), children),
            ]
        return st.one_of(*options)

    return st.recursive(leaf, extend, max_leaves=8)


_CLEAN, _DIRTY = _grammar(False), _grammar(True)


@st.composite
def _snippets(draw):
    dirty = draw(st.booleans())
    expr = _DIRTY if dirty else _CLEAN
    shape = draw(st.sampled_from(["plain", "bool", "loop"]))
    name = lambda n: ast.Name(n, ast.Store())  # noqa: E731
    stmts = [ast.Assign([name(n)], ast.Constant(draw(_CONSTS))) for n in "ab"] + [ast.Assign([name("b")], draw(expr))]
    if shape == "loop":
        stmts.append(ast.For(name("i"), ast.Call(ast.Name("range", ast.Load()), [ast.Constant(3)], []),
                             [ast.AugAssign(name("a"), ast.Add(), draw(expr))], []))
    ret = draw(expr)
    ret = ast.Call(ast.Name("bool", ast.Load()), [ret], []) if shape == "bool" else ret
    fn = ast.FunctionDef("check", ast.arguments([], [], None, [], [], None, []), stmts + [ast.Return(ret)], [], None)
    return ast.Module([fn], [])


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_snippets())
def test_fuzzed_asts_never_crash_or_escape(tree):
    try:
        src = ast.unparse(ast.fix_missing_locations(tree))
    except Exception:  # an AST the unparser cannot print is not a source anyone could send
        return
    _run_watched(src)
