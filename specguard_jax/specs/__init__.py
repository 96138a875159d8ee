"""Mission specifications as STL (paper Table 4 and the ArduPilot table), parameters, spec files and evaluation.

  drone_specs(overrides=None) / rover_specs(overrides=None) -> SpecTable
  with_params(table, overrides) ; add_spec(table, name, stl_text, ...) ; load_spec_file(path, table=None)
  load_params_file(path, known=None) / loads_params(text, fmt, known=None) -> {NAME: value}
  SpecEvaluator.create(table, dt)(signals [..., T]) -> (robustness [..., n], violated [..., n]); online monitor_*.
"""

from specguard_jax.specs.errors import ParamFileWarning, SpecError
from specguard_jax.specs.evaluator import SpecEvaluator
from specguard_jax.specs.params import DRONE_PARAMS, ROVER_PARAMS, ParamDef, load_params_file, loads_params
from specguard_jax.specs.table import (FAMILIES, Spec, SpecTable, add_spec, add_spec_params, drone_specs, infer_reward,
                                       load_spec_file, rover_specs, validate, with_params)


def compile_specs(table: SpecTable, dt: float) -> SpecEvaluator:
  """Shorthand for SpecEvaluator.create(table, dt)."""
  return SpecEvaluator.create(table, dt)
