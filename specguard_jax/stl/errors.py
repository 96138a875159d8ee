"""Errors raised by the STL engine: all are `ValueError`s with a one-line message naming the problem."""


class STLError(ValueError):
  """Base class of every STL-engine error (bad text, unknown signal, bad interval, unsupported monitor)."""


class STLSyntaxError(STLError):
  """Malformed STL text; the message starts with the 0-based character position."""

  def __init__(self, text: str, pos: int, problem: str):
    near = text[pos:pos + 12]
    where = f"near {near!r}" if near else "at end of text"
    super().__init__(f"STL syntax error at position {pos} ({where}): {problem}")
    self.text = text
    self.pos = pos
    self.problem = problem


class UnknownSignalError(STLError):
  """A formula mentions a signal that is not provided / not allowed."""


class IntervalError(STLError):
  """An empty, inverted, negative, non-integral (after unit conversion) or too long time interval."""


class FormulaSizeError(STLError):
  """A formula beyond the engine's size limits (text length, nesting depth, node count: see `stl.ast`)."""


class UnsupportedOnlineError(STLError):
  """The formula is outside the fragment the fixed-state online monitor supports."""
