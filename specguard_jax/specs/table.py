"""Mission-specification tables: SpecGuard's S1..S12 (drone, PX4 names) and S1, S2, S5-S8, S12 (rover, ArduPilot).

Each spec is STL text over `specguard_jax.signals.SIGNAL_NAMES` and named parameters, plus the data the per-step
reward needs: the condition f(c) (`reward_signals`, affine expression texts), its threshold a (`reward_threshold`,
a parameter name or number), a phase guard (non-temporal STL; outside it the spec does not apply and its reward is
the family's maximum) and the sigmoid family / k (see `specguard_jax.rewards`).

Choices (for docs/DESIGN.md):
  * Phase guards use `implies`: S3 (min altitude) applies in cruise, turns and loiter (not
    on the ground, in take-off, descent or landing), S7 (min speed) applies in cruise only,
    S9 in landing, S10 in take-off, S11 in loiter, S5 in cruise. The 0/1 phase indicators are compared with a big-M
    scale, `(1000*in_cruise > 500)` rather than `(in_cruise > 0.5)`: the guard's robustness is then +-500 instead of
    +-0.5, so `guard -> body` has exactly the body's robustness while the phase is on (and >= 500 while it is off),
    and the episode robustness of a guarded spec is the body's worst margin over the phase, not a value capped at 0.5.
  * S5 (waypoints in their time windows, F_[ti,tj](dist_wp < R) per waypoint in the paper) is written over the env's
    per-mission `wp_slack` so one fixed formula serves every mission:  G(cruise -> (wp_slack > 0 or dist_wp < R)):
    at every cruise instant either the current waypoint's deadline has not passed or the vehicle is within R of it.
    The env advances the target on arrival, so a late arrival (or never arriving) is a violation, matching the
    paper's conjunction of F windows; the `dist_wp < R` disjunct forgives the ticks between entering R and the env's
    switch. The reward keeps the paper's condition (dist_wp, keep-below R).
  * S7 (min speed) and S10 (min climb rate) must tolerate accelerating out of waypoint turns / off the ground and
    braking into waypoints: G(cruise -> F[0, SG_ACCEL_TIME](speed > MIN or dist_wp < SG_TURN_DIST or not cruise)).
  * S9 is keep-below (descent_speed <= MPC_LAND_SPEED) and S11 keep-below (stay within the loiter radius), as their
    STL states; the paper's printed reward equations for S9/S11 are keep-above (see rewards).
  * S10 follows Table 4's STL (climb rate >= MPC_TKO_SPEED during take-off); the printed reward is keep-below.
  * S12: violated when fence_margin < 1 m (SG_GF_MARGIN / FENCE_MARGIN). GF_MAX_HOR_DIST / GF_MAX_VER_DIST set by a
    parameter file add the home-centred fence they describe (specs.vehicle_params, EnvConfig.params_file). The
    reward is one factor on the same 3D margin for both vehicles: the printed two-factor (h, v) product is an AND
    of the horizontal and vertical margins, right for staying inside a cylinder but wrong for the keep-out prisms,
    which the vehicle clears by being beside OR above them (beside a prism taller than its altitude, v < 0 and the
    product paid ~0 while the spec held).
  * Intervals are written in seconds and converted to steps with the dt given to the evaluator.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
from typing import Dict, Mapping, Optional, Sequence, Tuple

from specguard_jax import stl
from specguard_jax.signals import SIGNAL_NAMES
from specguard_jax.specs import params as P
from specguard_jax.specs.errors import SpecError

FAMILIES = ("two_sided", "keep_above", "keep_below", "s6", "fence_hv", "fence", "none")


@dataclasses.dataclass(frozen=True)
class Spec:
  """One mission specification (see module docstring for the fields' roles)."""

  name: str
  description: str
  stl: str
  critical: bool = False
  family: str = "none"
  k: float = 1.0
  reward_signals: Tuple[str, ...] = ()
  reward_threshold: str = "0"
  reward_guard: str = ""


@dataclasses.dataclass(frozen=True)
class SpecTable:
  """An immutable, hashable table of specs plus parameter values (usable as a static jit argument)."""

  vehicle: str
  specs: Tuple[Spec, ...]
  param_items: Tuple[Tuple[str, float], ...]

  @property
  def params(self) -> Dict[str, float]:
    return dict(self.param_items)

  @property
  def names(self) -> Tuple[str, ...]:
    return tuple(s.name for s in self.specs)

  @property
  def critical(self) -> Tuple[bool, ...]:
    return tuple(s.critical for s in self.specs)

  def __getitem__(self, name: str) -> Spec:
    for s in self.specs:
      if s.name == name:
        return s
    raise SpecError(f"no spec named {name!r} (have: {', '.join(self.names)})")

  def formula(self, name: str, dt: Optional[float] = None) -> stl.Formula:
    """Parsed formula of spec `name` with parameters substituted (intervals in steps when dt is given; a window beyond
    stl.MAX_WINDOW_STEPS steps raises SpecError naming the spec and the parameters its text uses)."""
    spec = self[name]
    f = _parse(spec, self.params, spec.stl, "stl")
    if dt is None:
      return f
    try:
      return stl.to_steps(f, dt)
    except stl.STLError as e:
      used = [f"{n}={v:g}" for n, v in self.param_items if re.search(rf"\b{re.escape(n)}\b", spec.stl)]
      raise SpecError(f"spec {name}: {e}" + (f" (its parameters: {', '.join(used)})" if used else "")) from None

  def threshold(self, spec: Spec) -> float:
    return _threshold(spec, self.params)

  def describe(self) -> str:
    """Readable multi-line listing of the table."""
    rows = [f"{self.vehicle} specs ({len(self.specs)}):"]
    for s in self.specs:
      rows.append(f"  {s.name:<4}{'*' if s.critical else ' '} {s.description:<34} {s.stl}")
    rows.append("  params: " + ", ".join(f"{k}={v:g}" for k, v in self.param_items))
    return "\n".join(rows)


def _parse(spec: Spec, params: Mapping[str, float], text: str, what: str) -> stl.Formula:
  try:
    return stl.parse(text, params=params, signals=SIGNAL_NAMES)
  except stl.STLError as e:
    raise SpecError(f"spec {spec.name} ({what}): {e}") from None


def _threshold(spec: Spec, params: Mapping[str, float]) -> float:
  t = spec.reward_threshold.strip()
  if t in params:
    return float(params[t])
  try:
    return float(t)
  except ValueError:
    raise SpecError(f"spec {spec.name}: reward threshold {t!r} is neither a parameter nor a number") from None


def validate(table: SpecTable) -> SpecTable:
  """Check every spec of `table` (STL, signals, parameters, reward fields); raise SpecError on the first problem."""
  params = table.params
  P.check_consistent(params)
  seen = set()
  for s in table.specs:
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", s.name or ""):
      raise SpecError(f"bad spec name {s.name!r} (use letters, digits, '_')")
    if s.name in seen:
      raise SpecError(f"duplicate spec name {s.name!r}")
    seen.add(s.name)
    _parse(s, params, s.stl, "stl")
    if s.family not in FAMILIES:
      raise SpecError(f"spec {s.name}: unknown reward family {s.family!r} (known: {', '.join(FAMILIES)})")
    if not (math.isfinite(s.k) and s.k > 0):
      raise SpecError(f"spec {s.name}: reward constant k={s.k} must be a positive number")
    need = {"fence_hv": 2, "none": 0}.get(s.family, 1)
    if len(s.reward_signals) != need:
      raise SpecError(f"spec {s.name}: family {s.family!r} needs {need} reward signal expression(s), "
                      f"got {len(s.reward_signals)}")
    for e in s.reward_signals:
      _parse(s, params, f"({e}) > 0", "reward signal")
    if s.reward_guard:
      g = _parse(s, params, s.reward_guard, "reward guard")
      if stl.is_temporal(g):
        raise SpecError(f"spec {s.name}: reward guard {s.reward_guard!r} must not use temporal operators")
    if s.family != "none":
      _threshold(s, params)
  return table


def _spec_rows(rows) -> Tuple[Spec, ...]:
  return tuple(Spec(*r) for r in rows)




def _on(phase: str) -> str:
  """Guard 'phase indicator(s) on', big-M scaled (see module docstring)."""
  return f"(1000*{phase} > 500)"


def _off(phase: str) -> str:
  return f"(1000*({phase}) < 500)"


_CRUISE = _on("in_cruise")
_DRONE_ROWS = (
    ("S1", "Avoid collisions", "always(obstacle_distance > CP_DIST)", True, "two_sided", 1.0,
     ("obstacle_distance",), "CP_DIST"),
    ("S2", "Do not veer off a boundary", "always(path_deviation < NAV_MC_POS_TH)", True, "keep_below", 0.5,
     ("path_deviation",), "NAV_MC_POS_TH"),
    ("S3", "Maintain minimum altitude",
     f"always({_on('in_cruise + in_turn + in_loiter')} -> (altitude > NAV_MIN_LTR_ALT))", False, "keep_above", 0.5,
     ("altitude",), "NAV_MIN_LTR_ALT", _on("in_cruise + in_turn + in_loiter")),
    ("S4", "Maintain maximum altitude", "always(altitude < MIS_TAKEOFF_ALT)", False, "keep_below", 0.5,
     ("altitude",), "MIS_TAKEOFF_ALT"),
    ("S5", "Navigate through waypoints",
     f"always({_CRUISE} -> (wp_slack > 0 or dist_wp < NAV_ACC_RAD))", False, "keep_below", 0.25,
     ("dist_wp",), "NAV_ACC_RAD", _CRUISE),
    ("S6", "Maintain distance from obstacle", "always(obstacle_distance > CP_DIST)", False, "s6", 0.5,
     ("obstacle_distance",), "CP_DIST"),
    ("S7", "Maintain minimum velocity",
     f"always({_CRUISE} -> eventually[0s, SG_ACCEL_TIME s]((speed_xy > MPC_XY_VEL_MIN) or "
     f"(dist_wp < SG_TURN_DIST) or {_off('in_cruise')}))", False, "keep_above", 1.0,
     ("speed_xy",), "MPC_XY_VEL_MIN", f"{_CRUISE} and (dist_wp > SG_TURN_DIST)"),
    ("S8", "Maintain maximum velocity", "always(speed_xy < MPC_XY_VEL_MAX)", False, "keep_below", 1.0,
     ("speed_xy",), "MPC_XY_VEL_MAX"),
    ("S9", "Precision landing", f"always({_on('in_landing')} -> (descent_speed <= MPC_LAND_SPEED))", False,
     "keep_below", 8.0, ("descent_speed",), "MPC_LAND_SPEED", _on("in_landing")),
    ("S10", "Takeoff speed",
     f"always({_on('in_takeoff')} -> eventually[0s, SG_ACCEL_TIME s]((speed_z >= MPC_TKO_SPEED) or "
     f"{_off('in_takeoff')}))", False, "keep_above", 2.0, ("speed_z",), "MPC_TKO_SPEED", _on("in_takeoff")),
    ("S11", "Maintain loiter radius", f"always({_on('in_loiter')} -> (loiter_deviation < NAV_MC_ALT_RADIUS))", False,
     "keep_below", 0.5, ("loiter_deviation",), "NAV_MC_ALT_RADIUS", _on("in_loiter")),
    ("S12", "Stay within geofence", "always(fence_margin > SG_GF_MARGIN)", True, "fence", 0.5,
     ("fence_margin",), "SG_GF_MARGIN"),
)

_ROVER_ROWS = (
    ("S1", "Avoid collisions", "always(obstacle_distance > AVOID_MARGIN)", True, "two_sided", 1.0,
     ("obstacle_distance",), "AVOID_MARGIN"),
    ("S2", "Do not veer off a boundary", "always(path_deviation < SG_POS_TH)", True, "keep_below", 0.5,
     ("path_deviation",), "SG_POS_TH"),
    ("S5", "Navigate through waypoints",
     f"always({_CRUISE} -> (wp_slack > 0 or dist_wp < WPNAV_RADIUS))", False, "keep_below", 0.25,
     ("dist_wp",), "WPNAV_RADIUS", _CRUISE),
    ("S6", "Maintain distance from obstacle", "always(obstacle_distance > AVOID_MARGIN)", False, "s6", 0.5,
     ("obstacle_distance",), "AVOID_MARGIN"),
    ("S7", "Maintain minimum velocity",
     f"always({_CRUISE} -> eventually[0s, SG_ACCEL_TIME s]((speed_xy > CRUISE_SPEED_MIN) or "
     f"(dist_wp < SG_TURN_DIST) or {_off('in_cruise')}))", False, "keep_above", 1.0,
     ("speed_xy",), "CRUISE_SPEED_MIN", f"{_CRUISE} and (dist_wp > SG_TURN_DIST)"),
    ("S8", "Maintain maximum velocity", "always(speed_xy < CRUISE_SPEED_MAX)", False, "keep_below", 1.0,
     ("speed_xy",), "CRUISE_SPEED_MAX"),
    ("S12", "Stay within geofence", "always(fence_margin > FENCE_MARGIN)", True, "fence", 0.5,
     ("fence_margin",), "FENCE_MARGIN"),
)


def drone_specs(overrides: Optional[Mapping[str, float]] = None) -> SpecTable:
  """The 12 drone specs of paper Table 4 with PX4 parameter defaults, updated by `overrides` ({NAME: value})."""
  return validate(SpecTable("drone", _spec_rows(_DRONE_ROWS), tuple(P.resolve(P.DRONE_PARAMS, overrides).items())))


def rover_specs(overrides: Optional[Mapping[str, float]] = None) -> SpecTable:
  """The 7 rover specs of the paper's ArduPilot table (S1, S2, S5, S6, S7, S8, S12), updated by `overrides`."""
  return validate(SpecTable("rover", _spec_rows(_ROVER_ROWS), tuple(P.resolve(P.ROVER_PARAMS, overrides).items())))


def with_params(table: SpecTable, overrides: Mapping[str, float]) -> SpecTable:
  """`table` with some parameter values replaced (names must exist in the table)."""
  cur = table.params
  for name, value in overrides.items():
    if name not in cur:
      raise SpecError(f"unknown parameter {name!r} for the {table.vehicle} table (known: {', '.join(sorted(cur))})")
    defs = {**P.DRONE_PARAMS, **P.ROVER_PARAMS}
    cur[name] = P.check_value(name, value, defs.get(name))
  return validate(dataclasses.replace(table, param_items=tuple(cur.items())))


def infer_reward(formula: stl.Formula):
  """(family, reward_signals, threshold, guard) for `always(P)` / `always(G -> P)` with P one predicate, else None."""
  if not isinstance(formula, stl.Always) or formula.interval is not None:
    return None
  body, guard = formula.arg, ""
  if isinstance(body, stl.Implies) and not stl.is_temporal(body.left):
    guard, body = str(body.left), body.right
  if not isinstance(body, stl.Predicate):
    return None
  if len(body.terms) == 1 and abs(body.terms[0][1]) == 1.0:
    name, c = body.terms[0]
    return ("keep_above" if c > 0 else "keep_below"), (name,), repr(-c * body.offset), guard
  expr = " + ".join(f"({c!r})*{n}" for n, c in body.terms) + f" + ({body.offset!r})"
  return "keep_above", (expr,), "0", guard


def add_spec(table: SpecTable, name: str, stl_text: str, *, description: str = "", critical: bool = False,
             family: Optional[str] = None, k: float = 1.0, reward_signals: Optional[Sequence[str]] = None,
             reward_threshold=None, reward_guard: str = "", params: Optional[Mapping[str, float]] = None,
             replace: bool = False) -> SpecTable:
  """Return `table` plus a spec written in STL text (no Python edits needed).

  params: new parameters the text uses ({NAME: value}).  If `family` is None the reward is inferred for
  `always(P)` / `always(guard -> P)` with a single predicate P (keep-above / keep-below on P's margin); otherwise the
  spec is monitored but gets no shaped reward (family "none").  replace: overwrite a spec of the same name.
  """
  cur = table.params
  for pname, value in (params or {}).items():
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", str(pname)) or pname in SIGNAL_NAMES:
      raise SpecError(f"bad parameter name {pname!r} (must be an identifier that is not a signal name)")
    cur[pname] = P.check_value(pname, value, P.param_def(pname))
  probe = Spec(name, description, stl_text)
  formula = _parse(probe, cur, stl_text, "stl")
  if family is None and reward_signals is None:
    inferred = infer_reward(formula)
    family, reward_signals, reward_threshold, guard = inferred or ("none", (), "0", "")
    reward_guard = reward_guard or guard
  spec = Spec(name, description or name, stl_text, bool(critical), family or "keep_above", float(k),
              tuple(reward_signals or ()), str(reward_threshold if reward_threshold is not None else "0"),
              reward_guard)
  specs = tuple(s for s in table.specs if not (replace and s.name == name)) + (spec,)
  return validate(SpecTable(table.vehicle, specs, tuple(cur.items())))


def load_spec_file(path: str, table: Optional[SpecTable] = None) -> SpecTable:
  """Add the specs and parameters of a spec file to `table` (default: an empty drone-less table).

  JSON (`.json`): {"params": {NAME: value}, "specs": [{"name", "stl", optional "critical", "family", "k",
  "reward_signals", "reward_threshold", "reward_guard", "description"}]}.
  Text (anything else), one item a line, '#' comments:
      param SG_MAX_ALT = 30
      spec S13 critical: always(altitude < SG_MAX_ALT)
  """
  table = table or SpecTable("custom", (), ())
  text = P.read_text(path, "spec file")
  if os.path.splitext(path)[1].lower() == ".json":
    try:
      doc = json.loads(text)
    except json.JSONDecodeError as e:
      raise SpecError(f"{path}: invalid JSON at line {e.lineno}: {e.msg}") from None
    except (ValueError, RecursionError) as e:   # an integer of > 4300 digits; nesting deeper than json recurses
      raise SpecError(f"{path}: unreadable JSON ({type(e).__name__}: {str(e)[:80]})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("params", {}), dict) \
        or not isinstance(doc.get("specs", []), list):
      raise SpecError(f"{path}: expected a JSON object {{\"params\": {{NAME: value}}, \"specs\": [{{...}}]}}")
    table = add_spec_params(table, doc.get("params", {}))
    for i, item in enumerate(doc.get("specs", [])):
      if not isinstance(item, dict):
        raise SpecError(f"{path}: spec #{i} is a JSON {type(item).__name__}, expected an object")
      item = dict(item)
      try:
        name, stl_text = item.pop("name"), item.pop("stl")
      except KeyError as e:
        raise SpecError(f"{path}: spec #{i} lacks the {e.args[0]!r} field") from None
      if not isinstance(name, str) or not isinstance(stl_text, str):
        raise SpecError(f"{path}: spec #{i}: 'name' and 'stl' must be strings")
      try:
        table = add_spec(table, name, stl_text, **item)
      except SpecError:
        raise
      except (TypeError, ValueError) as e:
        raise SpecError(f"{path}: spec {name}: {e}") from None
    return table
  pending: Dict[str, float] = {}
  for lineno, raw in enumerate(text.splitlines(), 1):
    line = raw.split("#", 1)[0].strip()
    if not line:
      continue
    m = re.fullmatch(r"param\s+([A-Za-z_]\w*)\s*=\s*(\S+)", line)
    if m:
      pending[m.group(1)] = P.check_value(f"{m.group(1)} ({path}:{lineno})", m.group(2), P.param_def(m.group(1)))
      continue
    m = re.fullmatch(r"spec\s+([A-Za-z_]\w*)(\s+critical)?\s*:\s*(.+)", line)
    if not m:
      raise SpecError(f"{path}:{lineno}: expected 'param NAME = VALUE' or 'spec NAME [critical]: STL'")
    try:
      table = add_spec(table, m.group(1), m.group(3), critical=bool(m.group(2)), params=pending)
    except SpecError as e:
      raise SpecError(f"{path}:{lineno}: {e}") from None
    pending = {}
  return add_spec_params(table, pending) if pending else table


def add_spec_params(table: SpecTable, extra: Mapping[str, float]) -> SpecTable:
  """`table` with extra parameters defined (new names allowed)."""
  cur = table.params
  for n, v in extra.items():
    cur[n] = P.check_value(n, v, P.param_def(n))
  return validate(dataclasses.replace(table, param_items=tuple(cur.items())))
