"""Signal Temporal Logic engine: parser, offline robustness (rtamt-equal) and a fixed-state online monitor.

  parse(text, params=None, signals=None) -> Formula
  robustness(formula_or_text, signals: {name: [..., T]}, dt=None, length=None) -> [..., T]
  episode_robustness(formula_or_text, signals, dt=None, length=None) -> [...]  (== robustness(...)[..., 0], cheaper)
  OnlineMonitor(formula, dt=None) ; monitor_init(formula, batch_shape, dt=None) ; monitor_update(formula, state, x_t)
Intervals without a unit are control steps; with 's'/'ms' they are seconds, converted with an explicit dt.
Size limits (MAX_DEPTH, MAX_NODES, MAX_WINDOW_STEPS, MAX_TEXT_CHARS) are refused with FormulaSizeError / IntervalError.
"""

from specguard_jax.stl.ast import (MAX_DEPTH, MAX_NODES, MAX_WINDOW_STEPS, Always, And, Eventually, Formula, Implies,
                                   Interval, Not, Or, Predicate, Until, horizon, is_temporal, signals_of, to_steps)
from specguard_jax.stl.errors import (FormulaSizeError, IntervalError, STLError, STLSyntaxError, UnknownSignalError,
                                      UnsupportedOnlineError)
from specguard_jax.stl.offline import episode_robustness, robustness
from specguard_jax.stl.online import MonitorState, OnlineMonitor, monitor_init, monitor_update
from specguard_jax.stl.parser import MAX_TEXT_CHARS, parse
