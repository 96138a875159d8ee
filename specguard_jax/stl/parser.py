"""Text parser for STL, close to rtamt's syntax.

Grammar (loosest binding first; `->` is right-associative, `until` left-associative like rtamt):
  formula   := or ( ('->' | 'implies') formula )?
  or        := and ( ('or' | '||' | '|') and )*
  and       := until ( ('and' | '&&' | '&') until )*
  until     := unary ( 'until' interval? unary )*
  unary     := ('not' | '!') unary | ('always' | 'G') interval? unary | ('eventually' | 'F') interval? unary
             | '(' formula ')' | predicate
  predicate := affine ('>' | '>=' | '<' | '<=') affine        (affine: sums of constant * signal, e.g. 2*x - y + 1)
  interval  := '[' bound (',' | ':') bound ']'      bound := number | PARAM, optionally followed by a unit
Interval units: none = control steps (integers); 's' or 'ms' = seconds, converted to steps later with an explicit dt
(`ast.to_steps`). As in rtamt, a unit written on one bound only applies to both. Identifiers found in `params` are
constants (in expressions and interval bounds); every other identifier is a signal name, except `inf`, `nan` and
`infinity` (any case), which are refused like every constant that is not a finite float64 (1e999) and every
predicate whose coefficients or offset overflow.

Limits: texts of at most MAX_TEXT_CHARS characters nesting at most MAX_NESTING levels, trees of at most ast.MAX_DEPTH
levels and ast.MAX_NODES nodes, step intervals of at most ast.MAX_WINDOW_STEPS steps (seconds intervals are checked
once converted, `ast.to_steps`); beyond them parse raises FormulaSizeError / IntervalError naming the position. The
parser recurses only into parentheses and prefix operators (at most two Python frames per level), so MAX_NESTING also
bounds its stack; binary operators are one loop and and / or chains become balanced trees.
"""

from __future__ import annotations

import math
import re
from typing import Iterable, List, Mapping, Optional, Tuple

from specguard_jax.stl import ast
from specguard_jax.stl.errors import FormulaSizeError, IntervalError, STLError, STLSyntaxError, UnknownSignalError

MAX_TEXT_CHARS = 200_000
"""Longest STL text accepted (characters); it bounds the token list built before parsing."""
MAX_NESTING = 3 * ast.MAX_DEPTH + 16
"""Deepest nesting of the text (levels: parentheses, 'not', temporal operators, unary signs). The parser recurses at
most twice per level; str() of a formula of depth MAX_DEPTH nests up to 3 * MAX_DEPTH + 1 + _PREDICATE_TEXT_NESTING
levels (a temporal operator prints as three: '(always[a,b](' ... '))')."""
_PREDICATE_TEXT_NESTING = 8

_TOKEN = re.compile(r"\s*(?:(?P<num>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)|(?P<id>[A-Za-z_][A-Za-z0-9_.]*)"
                    r"|(?P<op>->|>=|<=|&&|\|\||[()\[\],:+\-*/<>!&|]))")
_KEYWORDS = {"not", "and", "or", "implies", "always", "eventually", "until"}
_CMP = {">", ">=", "<", "<="}
_UNITS = {"s": ("s", 1.0), "ms": ("s", 1e-3), "step": ("steps", 1.0), "steps": ("steps", 1.0)}
_NON_FINITE_NAMES = {"inf", "nan", "infinity"}


def _tokenize(text: str) -> List[Tuple[str, str, int]]:
  toks, pos = [], 0
  while True:
    m = _TOKEN.match(text, pos)
    if m is None or m.end() == pos:
      rest = text[pos:]
      if rest.strip():
        p = pos + len(rest) - len(rest.lstrip())
        raise STLSyntaxError(text, p, f"unexpected character {text[p]!r}")
      break
    kind = m.lastgroup
    toks.append((kind, m.group(kind), m.start(kind)))
    pos = m.end()
  toks.append(("end", "", len(text)))
  return toks


class _Parser:
  """Recursive-descent parser over a token list (one instance per text)."""

  def __init__(self, text: str, params: Mapping[str, float], signals: Optional[Iterable[str]]):
    self.text = text
    self.used_param = False
    self.toks = _tokenize(text)
    self.i = 0
    self.params = dict(params)
    self.signals = None if signals is None else set(signals)
    self.depth = 0     # current nesting of the text (levels opened by '(', 'not', temporal operators, unary signs)
    self.deepest = 0   # the deepest nesting reached so far
    self.nodes = 0     # tree nodes built so far
    self.levels = {}   # id(node) -> depth of the tree below it (1 for a predicate)
    self.closing = _matching_parens(self.toks)

  # --- size limits ---
  def enter(self):
    """Open one nesting level of the text at the current token (before recursing into it)."""
    self.depth += 1
    self.deepest = max(self.deepest, self.depth)
    if self.depth > MAX_NESTING:
      self.fail(f"text nests more than {MAX_NESTING} levels deep (the maximum; parentheses, 'not', temporal "
                "operators and unary signs each open a level)", cls=FormulaSizeError)

  def node(self, f):
    """Count one tree node and check the tree's depth below it; returns it."""
    self.nodes += 1
    if self.nodes > ast.MAX_NODES:
      self.fail(f"formula has more than {ast.MAX_NODES} nodes (predicates and operators; the maximum)",
                cls=FormulaSizeError)
    d = 1 + max((self.levels[id(c)] for c in ast.children(f)), default=0)
    if d > ast.MAX_DEPTH:
      self.fail(f"formula tree nests more than {ast.MAX_DEPTH} levels deep (the maximum; every operator is a level, "
                "an and / or chain of n terms about log2(n))", cls=FormulaSizeError)
    self.levels[id(f)] = d
    return f

  def balanced(self, cls, items):
    """items[0] op items[1] op ... as a balanced tree (op associative: min / max), left-nested for 3 items."""
    while len(items) > 1:
      pairs = [self.node(cls(items[k], items[k + 1])) for k in range(0, len(items) - 1, 2)]
      items = pairs + items[len(pairs) * 2:]
    return items[0]

  # --- token helpers ---
  def peek(self, k: int = 0):
    return self.toks[min(self.i + k, len(self.toks) - 1)]

  def at(self, *values: str) -> bool:
    kind, val, _ = self.peek()
    return kind in ("op", "id") and val in values

  def take(self):
    t = self.toks[self.i]
    self.i += 1
    return t

  def expect(self, value: str, what: str):
    if not self.at(value):
      self.fail(f"expected {what}")
    return self.take()

  def fail(self, problem: str, pos: Optional[int] = None, cls=STLSyntaxError):
    pos = self.peek()[2] if pos is None else pos
    if cls is STLSyntaxError:
      raise STLSyntaxError(self.text, pos, problem)
    raise cls(f"STL formula too large at position {pos}: {problem}")

  # --- formulas ---
  def parse(self) -> ast.Formula:
    if self.peek()[0] == "end":
      self.fail("empty formula")
    f = self.formula()
    if self.peek()[0] != "end":
      self.fail("unexpected token after a complete formula")
    if not ast.has_seconds(f) and ast.window_span(f) > ast.MAX_WINDOW_STEPS:
      raise ast.window_error(f"the nested windows of {self.text[:80]!r}", ast.window_span(f))
    return f

  def formula(self):
    """Binary operators by precedence ('->' < or < and < until) in one loop over operand / operator stacks, so only
    parentheses and prefix operators recurse: '->' is right-associative, until left-associative, and / or chains
    are collected and built as balanced trees."""
    operands, ops = [self.unary()], []   # ops: (precedence, name, interval)
    while True:
      op = self._binary_op()
      while ops and (ops[-1][0] > op[0] or (ops[-1][0] == op[0] and op[1] == "until")):
        self._reduce(operands, ops)
      if op[1] == "end":
        return operands[0]
      ops.append(op)
      operands.append(self.unary())

  def _binary_op(self):
    """The binary operator at the current token, taken (with an until's interval), else (-1, 'end', None)."""
    for prec, name, spellings in ((0, "implies", ("->", "implies")), (1, "or", ("or", "||", "|")),
                                  (2, "and", ("and", "&&", "&")), (3, "until", ("until",))):
      if self.at(*spellings):
        self.take()
        return prec, name, (self.interval() if name == "until" and self.at("[") else None)
    return -1, "end", None

  def _reduce(self, operands, ops):
    """Pop the top operator (for and / or: the whole chain of it on top) and its operands; push the node."""
    prec, name, iv = ops.pop()
    if name in ("and", "or"):
      k = 1
      while ops and ops[-1][1] == name:
        ops.pop()
        k += 1
      items = operands[-k - 1:]
      del operands[-k - 1:]
      operands.append(self.balanced(ast.And if name == "and" else ast.Or, items))
      return
    right, left = operands.pop(), operands.pop()
    operands.append(self.node(ast.Implies(left, right) if name == "implies" else ast.Until(left, right, iv)))

  def _is_temporal_kw(self, names) -> bool:
    kind, val, _ = self.peek()
    if kind != "id" or val not in names:
      return False
    return val in _KEYWORDS or self.peek(1)[1] in ("(", "[")  # 'G'/'F' only when followed by ( or [

  def unary(self):
    if self.at("not", "!"):
      self.enter()
      self.take()
      f = self.node(ast.Not(self.unary()))
      self.depth -= 1
      return f
    for names, cls in ((("always", "G"), ast.Always), (("eventually", "F"), ast.Eventually)):
      if self._is_temporal_kw(names):
        self.enter()
        self.take()
        iv = self.interval() if self.at("[") else None
        f = self.node(cls(self.unary(), iv))
        self.depth -= 1
        return f
    if self.at("(") and not self._paren_is_arith():
      self.enter()
      self.take()
      f = self.formula()
      self.expect(")", "')' closing the parenthesised formula")
      self.depth -= 1
      return f
    kind, val, pos = self.peek()
    if kind == "end":
      self.fail("formula ended early: expected a predicate, 'not', a temporal operator or '('")
    if kind == "id" and val in _KEYWORDS:
      self.fail(f"unexpected keyword {val!r}: expected a predicate or a sub-formula")
    if kind == "op" and val not in ("(", "-", "+"):
      self.fail(f"unexpected {val!r}: expected a predicate or a sub-formula")
    return self.predicate()

  def _paren_is_arith(self) -> bool:
    """At '(': is it an arithmetic group (the matching ')' is followed by a comparison or arithmetic operator)?"""
    j = self.closing.get(self.i)
    if j is None:
      self.fail("unbalanced '(': no matching ')'")
    nxt = self.toks[j + 1]
    return nxt[0] == "op" and nxt[1] in _CMP | {"+", "-", "*", "/"}

  # --- predicates and affine expressions: (coefs dict, constant) ---
  def predicate(self):
    start = self.peek()[2]
    self.used_param = False
    self.deepest = base = self.depth
    lhs = self.affine()
    kind, op, pos = self.peek()
    if not (kind == "op" and op in _CMP):
      self.fail("expected a comparison ('>', '>=', '<', '<=') after the expression")
    self.take()
    rhs = self.affine()
    end = self.peek()[2]
    if op in (">", ">="):
      coefs, const = _sub(lhs, rhs)
    else:
      coefs, const = _sub(rhs, lhs)
    if not all(math.isfinite(v) for v in (const, *coefs.values())):
      self.fail("the predicate's coefficients or constant overflow float64 (not finite)", start)
    terms = tuple((n, c) for n, c in sorted(coefs.items()) if c != 0.0)
    if not terms:
      self.fail("the predicate compares constants only: it must mention a signal", start)
    # The source text is kept for printing unless it used parameters or nests deeply (str() must re-parse within
    # MAX_NESTING: the canonical form nests 2 levels).
    plain = not self.used_param and self.deepest - base <= _PREDICATE_TEXT_NESTING
    text = " ".join(self.text[start:end].split()) if plain else ""
    return self.node(ast.Predicate(terms, const, text))

  def affine(self):
    """A sum of products of factors, in one loop (a parenthesised group recurses through factor only)."""
    acc, sign = None, "+"
    while True:
      t = self.factor()
      while self.at("*", "/"):
        op, pos = self.take()[1:]
        rhs = self.factor()
        if op == "*":
          if t[0] and rhs[0]:
            self.fail("product of two signals: predicates must be affine in the signals", pos)
          t = _scale(rhs, t[1]) if not t[0] else _scale(t, rhs[1])
        else:
          if rhs[0]:
            self.fail("division by a signal: predicates must be affine in the signals", pos)
          if rhs[1] == 0:
            self.fail("division by zero", pos)
          t = _scale(t, 1.0 / rhs[1])
      acc = t if acc is None else (_add(acc, t) if sign == "+" else _sub(acc, t))
      if not self.at("+", "-"):
        return acc
      sign = self.take()[1]

  def factor(self):
    kind, val, pos = self.peek()
    if self.at("-", "+", "("):
      self.enter()
      self.take()
      if val == "(":
        e = self.affine()
        self.expect(")", "')' closing the parenthesised expression")
      else:
        e = self.factor() if val == "+" else _scale(self.factor(), -1.0)
      self.depth -= 1
      return e
    if kind == "num":
      self.take()
      return ({}, self.finite(val, pos))
    if kind == "id" and val not in _KEYWORDS:
      self.take()
      if val in self.params:
        self.used_param = True
        return ({}, float(self.params[val]))
      if val.lower() in _NON_FINITE_NAMES:
        self.fail(f"{val!r} is not a finite constant (and not a usable signal name)", pos)
      if self.signals is not None and val not in self.signals:
        raise UnknownSignalError(f"unknown signal {val!r} at position {pos} of {self.text!r} "
                                 f"(known: {', '.join(sorted(self.signals))})")
      return ({val: 1.0}, 0.0)
    self.fail("expected a number, a signal name or '('")

  def finite(self, token: str, pos: int) -> float:
    v = float(token)
    if not math.isfinite(v):
      self.fail(f"constant {token[:24]!r} is not a finite float64", pos)
    return v

  # --- intervals ---
  def interval(self) -> ast.Interval:
    start = self.expect("[", "'['")[2]
    if self.at("]"):
      self.fail("empty interval '[]'")
    lo, ulo = self.bound()
    if not self.at(",", ":"):
      self.fail("expected ',' or ':' between the interval bounds")
    self.take()
    hi, uhi = self.bound()
    self.expect("]", "']' closing the interval")
    units = {u[0] for u in (ulo, uhi) if u is not None}
    if len(units) > 1:
      raise STLSyntaxError(self.text, start, "interval mixes steps and seconds")
    unit = units.pop() if units else "steps"
    lo *= (ulo or uhi or ("steps", 1.0))[1]
    hi *= (uhi or ulo or ("steps", 1.0))[1]
    if lo < 0:
      raise IntervalError(f"negative interval bound in {self.text[start:self.peek()[2]]!r} at position {start}")
    if hi < lo:
      raise IntervalError(f"inverted interval {self.text[start:self.peek()[2]]!r} at position {start} (hi < lo)")
    if unit == "steps" and not (float(lo).is_integer() and float(hi).is_integer()):
      raise IntervalError(f"interval {self.text[start:self.peek()[2]]!r} at position {start}: step bounds must be "
                          "integers (write seconds with a unit, e.g. [0s, 2.5s])")
    if unit == "steps" and hi > ast.MAX_WINDOW_STEPS:
      raise ast.window_error(f"interval {self.text[start:self.peek()[2]].strip()!r} at position {start}", hi)
    return ast.Interval(float(lo), float(hi), unit)

  def bound(self):
    kind, val, pos = self.peek()
    sign = 1.0
    if self.at("-"):
      self.take()
      sign = -1.0
      kind, val, pos = self.peek()
    if kind == "num":
      self.take()
      v = self.finite(val, pos)
    elif kind == "id" and val in self.params:
      self.take()
      v = float(self.params[val])
    elif kind == "id" and val in ("inf", "oo"):
      self.fail("unbounded interval: write the operator without an interval instead")
    else:
      self.fail("expected a number or a parameter name as interval bound")
    if not math.isfinite(v):
      self.fail("interval bound must be finite", pos)
    unit = None
    if self.peek()[0] == "id" and self.peek()[1] in _UNITS:
      unit = _UNITS[self.take()[1]]
    return sign * v, unit


def _matching_parens(toks) -> dict:
  """{index of '(': index of its ')'} over a token list (unmatched '(' are absent), in one pass."""
  out, open_ = {}, []
  for j, (kind, val, _) in enumerate(toks):
    if kind == "op" and val == "(":
      open_.append(j)
    elif kind == "op" and val == ")" and open_:
      out[open_.pop()] = j
  return out


def _add(a, b):
  c = dict(a[0])
  for n, v in b[0].items():
    c[n] = c.get(n, 0.0) + v
  return c, a[1] + b[1]


def _scale(a, s):
  return {n: v * s for n, v in a[0].items()}, a[1] * s


def _sub(a, b):
  return _add(a, _scale(b, -1.0))


def parse(text: str, params: Optional[Mapping[str, float]] = None,
          signals: Optional[Iterable[str]] = None) -> ast.Formula:
  """Parse STL `text` into a Formula.

  params: identifiers to substitute by constants (e.g. {"CP_DIST": 5.0}).  signals: if given, the allowed signal names
  (anything else raises UnknownSignalError).  Raises an STLError (a ValueError) with a one-line message on bad input.
  """
  if not isinstance(text, str):
    raise STLError(f"STL text must be a str, got {type(text).__name__}")
  if len(text) > MAX_TEXT_CHARS:
    raise FormulaSizeError(f"STL text of {len(text)} characters is longer than the maximum {MAX_TEXT_CHARS}")
  return _Parser(text, _check_params(params or {}), signals).parse()


def _check_params(params: Mapping[str, float]) -> Mapping[str, float]:
  """`params` as {name: float}; raises STLError naming a value that is not a finite real number."""
  out = {}
  for name, value in params.items():
    try:
      v = float(value)
    except (TypeError, ValueError, OverflowError):
      raise STLError(f"STL parameter {name!r}: value {value!r} is not a number") from None
    if isinstance(value, bool) or not math.isfinite(v):
      raise STLError(f"STL parameter {name!r}: value {value!r} is not a finite number")
    out[name] = v
  return out
