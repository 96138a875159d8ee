"""Errors of the specification layer (one-line messages, ValueError subclasses)."""


class SpecError(ValueError):
  """Bad spec table, spec text, parameter name/value or spec/params file."""
