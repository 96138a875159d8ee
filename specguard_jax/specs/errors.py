"""Errors of the specification layer (one-line messages, ValueError subclasses) and its warning category."""


class SpecError(ValueError):
  """Bad spec table, spec text, parameter name/value or spec/params file."""


class ParamFileWarning(UserWarning):
  """A parameter file loaded, but with something the caller should see (names the specs do not use)."""
