"""Range and type checks of config values, each failing with a one-line ValueError that names the key, the value and
what is allowed (the configs' `validate` methods call them, so every route into a config, Python, a JSON file or a
CLI flag, is checked in one place before anything is built or compiled)."""

from __future__ import annotations

import math
import numbers


def _fail(key: str, value, allowed: str):
  raise ValueError(f"{key} = {value!r} is not allowed; allowed: {allowed}")


def _interval(lo, hi, lo_open: bool, hi_open: bool) -> str:
  lo_s, hi_s = (f"{x:g}" if isinstance(x, float) else str(x) for x in (lo, hi))
  if hi is None:
    return f"> {lo_s}" if lo_open else f">= {lo_s}"
  if lo is None:
    return f"< {hi_s}" if hi_open else f"<= {hi_s}"
  return f"{'(' if lo_open else '['}{lo_s}, {hi_s}{')' if hi_open else ']'}"


def number(key: str, value, lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
           hi_open: bool = False, allow_inf: bool = False) -> None:
  """value must be a real number (not a bool), finite (or +-inf when allow_inf; never NaN) and within [lo, hi]
  (open ends with lo_open / hi_open; None: unbounded)."""
  what = "a number" if allow_inf else "a finite number"
  rng = _interval(lo, hi, lo_open, hi_open) if lo is not None or hi is not None else ""
  allowed = f"{what} {rng}".strip()
  if isinstance(value, bool) or not isinstance(value, numbers.Real):
    _fail(key, value, allowed)
  v = float(value)
  if math.isnan(v) or (math.isinf(v) and not allow_inf):
    _fail(key, value, allowed)
  if lo is not None and (v < lo or (lo_open and v == lo)):
    _fail(key, value, allowed)
  if hi is not None and (v > hi or (hi_open and v == hi)):
    _fail(key, value, allowed)


def integer(key: str, value, lo: int | None = None, hi: int | None = None) -> None:
  """value must be an int (not a bool) within [lo, hi] (None: unbounded)."""
  rng = _interval(lo, hi, False, False) if lo is not None or hi is not None else ""
  allowed = f"an integer {rng}".strip()
  if isinstance(value, bool) or not isinstance(value, numbers.Integral):
    _fail(key, value, allowed)
  if (lo is not None and value < lo) or (hi is not None and value > hi):
    _fail(key, value, allowed)


def one_of(key: str, value, choices) -> None:
  """value must be one of choices (compared only when hashable: a list where a name belongs is refused by name)."""
  try:
    ok = value in choices
  except TypeError:
    ok = False
  if not ok:
    _fail(key, value, f"one of {', '.join(map(str, choices))}")


def sequence(key: str, value, *, min_len: int = 0, length: int | None = None) -> None:
  """value must be a tuple or list (of `length` items, or at least min_len)."""
  if not isinstance(value, (tuple, list)):
    _fail(key, value, "a list")
  if length is not None and len(value) != length:
    _fail(key, value, f"a list of {length} items")
  if len(value) < min_len:
    _fail(key, value, f"a list of at least {min_len} item(s)")
