"""Stealthy ramp attacks designed against the residual CUSUM detector: the fastest ramp that stays hidden.

A STEALTHY schedule ramps a sensor bias linearly, b(t) = (t - onset) rho u for onset <= t < onset + |b| / rho
(u the bias direction; a negative direction is the "gradually decreasing" case), then holds b. `design_stealthy`
picks the ramp rate rho (units of the sensor's bias per s, see specguard_jax.attacks.attacks) so that a given
detector (a calibrated `DetectorConfig`: scale, drift k, threshold h per channel) raises no alarm for `hidden_s`
seconds after the onset, and the rate is the fastest on a refined grid that does so.

Why empirical. The detector's residuals do not respond to a ramp in one way that a closed-form CUSUM bound could use
(measured with calibrated thresholds, onset in cruise):
  * rate-limited (GPS): a ramping spoofer moves the fake velocity consistently (gps_vel += rho), so the EKF absorbs
    the ramp and its innovations settle back to noise; only the velocity step rho at the onset (and at the end of
    the ramp) is seen, as a transient in the GPS velocity channels. Below a critical rate (drone ~1.1 m/s) the ramp
    is not detected at all, above it it is caught within ~1 s: hidden time vs rate is a step. (On the rover the
    wheel odometry and the non-holonomic constraint also see the fake velocity: 0.36 m/s stays hidden ~12 s.)
  * level-limited (baro, mag, flow, gyro, accel): the residual grows with the bias reached, not its rate (the
    vertical GPS/baro disagreement, the heading error seen through the GPS velocity, the flow/GPS velocity mismatch,
    the IMU biases beyond what the EKF bias states and the detector's baseline absorb), so the alarm comes when the
    bias crosses a detectable level b* and the hidden time is ~ b* / rho (drone: b* ~ 4 m baro, ~0.4 rad mag,
    ~0.22 rad/s flow, ~0.07 rad/s gyro z, ~1 m/s^2 accel z).
The residual goes through the EKF, the autopilot and the vehicle (closed loop) in both cases, so the hidden time of
a rate is measured, not modelled: one batched, jitted simulation (`envs.record`, a `lax.scan` over
the env's own ticks, no Python loop over time) of a grid of rates x a few design missions, and the CUSUM replayed
over the recorded residuals with the detector's scale, k, h (`hidden_times`; it finds detector_update's alarm to the
tick, so one recording serves any thresholds). The grid is geometric over the sensor's `RATE_RANGES`; the fastest
rate whose hidden time is >= hidden_s (1 + margin) on every design mission (or the `quantile` of them), and every
slower grid rate too (monotone envelope: a lucky fast rate is not picked), is kept; `refine` more grids of the same
size between it and the next (failing) grid rate narrow it down. The design missions are the same for every rate
(common random numbers) and are also flown attack-free: one whose attack-free twin raises a (false) alarm within the
window is left out, since no rate can avoid it. Everything is seeded (`seed`): the design is reproducible. A rate
that ends the ramp before hidden_s (|b| / rho < hidden_s) is simulated as such (for GPS the fake velocity steps back
at the end of the ramp: a second transient). A mission that ends (completed, crashed) before an alarm counts as
hidden only up to its end (conservative). No grid rate hidden that long -> `feasible` False (schedule None).

Measured (drone, CPU; detector calibrated on 32 attack-free missions for 0.05 false alarms per mission, onset 12 s,
8 design missions, margin 0.2, 7 rates + 1 refinement; held-out: 24 other missions, the one with a false alarm left
out; hidden times (s after the onset) are censored at the window, hidden_s x 1.2 + 1 s):
                      hidden_s = 10 s: rate held-out min 4x median    hidden_s = 20 s: rate held-out min 4x median
  gps  +30 m east                  1.10 m/s        >= 13      0.18                 1.10 m/s        >= 25      0.18
  baro -8 m                       0.254 m/s        >= 13       5.8                0.133 m/s         22.4       9.1
  baro +8 m                       0.330 m/s         10.9       3.6                0.117 m/s        >= 25      10.2
  mag  +90 deg                 0.0316 rad/s         10.2       1.6             0.0116 rad/s        >= 25      11.2
  flow +1 rad/s x            0.0154 rad/s^2        >= 13       4.3           0.0075 rad/s^2        >= 25       8.0
  gyro +0.5 rad/s z          0.0052 rad/s^2         12.3       4.7           0.0027 rad/s^2         24.8       7.4
  accel -2 m/s^2 z              0.073 m/s^3         12.6       2.8              0.031 m/s^3         25.0       8.6
Every sensor has a hidden regime against this detector (none is caught whatever the rate), but the magnetometer's
hidden time varies most between missions (it depends on the heading error vs the flight direction): use more design
missions or a larger margin for it. The in-env detector (envs.make(..., detector='residual',
detector_config=cfg), info['alarm']) agrees (checked for gps, baro, flow): designed ramps raise no alarm in the
window, 4x faster ones do.

Units: s, and the bias units of the target sensor (rates per s).
"""

from __future__ import annotations

import dataclasses
import types

import jax
import jax.numpy as jnp
import numpy as np

import envs
from specguard_jax.attacks import attacks as attacks_lib
from specguard_jax.detection import detector as det
from specguard_jax.detection import traces

# Default ramp-rate search range per sensor (|db/dt| in the sensor's bias units per s).
RATE_RANGES = {
    "gps": (0.05, 10.0),       # m/s
    "gyro": (2e-4, 0.5),       # rad/s^2
    "accel": (2e-3, 2.0),      # m/s^3
    "mag": (1e-3, 1.0),        # rad/s
    "baro": (0.01, 5.0),       # m/s
    "flow": (1e-3, 1.0),       # rad/s^2
}
NEVER = 1e9   # duration (s) of an attack that lasts until the episode ends


@dataclasses.dataclass(frozen=True, eq=False)
class StealthyDesign:
  """Result of `design_stealthy`.

  schedule: the designed STEALTHY AttackSchedule (None if not feasible).  sensor: target.  bias: [d] full bias.
  rate: |db/dt| of the ramp (bias units / s; nan if not feasible).  ramp_time: |b| / rate (s).
  hidden_s: the requested hidden time (s).  feasible: some grid rate stayed hidden that long.
  rates: [R] every rate simulated (ascending).  hidden: [R, M] hidden time (s) of each on each design mission,
  censored at the end of the observation window or of the mission.  required: hidden time the criterion asked for.
  dropped: [M] design missions left out (their attack-free twin raised a false alarm within the window).
  """
  schedule: attacks_lib.AttackSchedule | None
  sensor: str
  bias: np.ndarray
  rate: float
  ramp_time: float
  hidden_s: float
  feasible: bool
  rates: np.ndarray
  hidden: np.ndarray
  required: float
  dropped: np.ndarray


def window_ticks(env, onset: float, window_s: float) -> int:
  """Number of env ticks (env.config.tick_dt) that covers [0, onset + window_s]."""
  return int(np.ceil((onset + window_s) / env.config.tick_dt - 1e-6))


def _model_cfg(cfg):
  """The residuals depend on the vehicle model only, not on the calibration (scale, h, used, k): one compile."""
  n = len(cfg.scale)
  return dataclasses.replace(cfg, scale=(1.0,) * n, h=(1.0,) * n, used=(1.0,) * n, k=1.0)


def record_residuals(env, cfg, keys, schedules: attacks_lib.AttackSchedule, n_ticks: int, batch: int | None = None):
  """Fly len(keys) missions of `env` under `schedules` (batched AttackSchedule) for n_ticks ticks, in chunks of
  `batch` (the last one padded, so one compile serves every call with the same batch and n_ticks).

  Returns numpy (r [N, T, C] raw |residual|, fresh [N, T, C] fed & mission valid, time [N, T] s, valid [N, T]),
  the inputs of `detection.calibrate` and `hidden_times`.
  """
  n = int(keys.shape[0])
  batch = batch or n
  mcfg = _model_cfg(cfg)
  # Strong dtypes (no_attack() has weakly typed leaves): every schedule batch hits the same compiled recording.
  schedules = jax.tree.map(lambda x: jnp.asarray(x, jnp.asarray(x).dtype), schedules)
  out = []
  for i in range(0, n, batch):
    idx = np.minimum(np.arange(i, i + batch), n - 1)
    k = keys[idx]
    s = jax.tree.map(lambda x: x[idx], schedules)
    tr = traces.tick_trace(envs.record(env, k, n_ticks, traces.RECORD_FIELDS, attacks=s))
    r, fresh = traces.residual_trace(mcfg, tr, env.config.tick_dt)
    m = min(batch, n - i)
    out.append(jax.device_get((r[:m], fresh[:m], tr.time[:m], tr.valid[:m])))
  return tuple(np.concatenate(x) for x in zip(*out))


@jax.jit
def _first_alarm(scale, h, used, k, cap, r, fresh, time, onset):
  """CUSUM replay (detector.cusum_step) over [N, T, C] residuals; first tick at/after onset [N] with a score > 1."""
  cusum_cfg = types.SimpleNamespace(scale=scale, h=h, k=k, cap=cap)   # cusum_step only reads these four

  def one(rm, fm, tm, on):
    def body(s, x):
      ri, fi = x
      s, _ = det.cusum_step(cusum_cfg, s, ri, fi & (used > 0))
      return s, jnp.any(s / h * used > 1.0)
    _, alarm = jax.lax.scan(body, jnp.zeros(r.shape[-1]), (rm, fm))
    hit = alarm & (tm >= on)
    return jnp.any(hit), jnp.argmax(hit)

  return jax.vmap(one)(r, fresh, time, onset)


def hidden_times(cfg, r, fresh, time, valid, onset):
  """Seconds from the onset [N] (or scalar) to the detector's first alarm at or after it, per mission.

  cfg: the (calibrated) DetectorConfig whose scale, k, h, cap, used are replayed; r, fresh, time, valid: from
  `record_residuals`. Without an alarm the hidden time is censored at the end of the mission's valid ticks (or of
  the window). Returns numpy (hidden [N] s, detected [N] bool).
  """
  time = np.asarray(time)
  onset = np.broadcast_to(np.asarray(onset, np.float32), time.shape[:1])
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  det, idx = jax.device_get(_first_alarm(f32(cfg.scale), f32(cfg.h), f32(cfg.used), f32(cfg.k), f32(cfg.cap),
                                         f32(r), jnp.asarray(fresh, bool), f32(time), f32(onset)))
  dt = float(time[0, 1] - time[0, 0]) if time.shape[1] > 1 else 0.0
  valid = np.asarray(valid)
  last = np.where(valid.any(-1), time[np.arange(time.shape[0]), valid.shape[1] - 1 - np.argmax(valid[:, ::-1], -1)]
                  + dt, 0.0)
  t_alarm = np.where(det, time[np.arange(time.shape[0]), idx], last)
  return np.maximum(t_alarm - onset, 0.0), np.asarray(det)


def _ramp_schedules(sensor, bias, rates, onset, duration, free: bool = False):
  """Batched STEALTHY schedules [R (+1)] of `bias` at each rate; free: one attack-free schedule appended."""
  mag = float(np.linalg.norm(bias))
  s = [attacks_lib.schedule_for(sensor, bias, onset, duration, "stealthy", ramp_time=mag / float(q)) for q in rates]
  s += [attacks_lib.no_attack()] if free else []
  return jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v, jnp.asarray(v).dtype) for v in x]), *s)


def design_stealthy(env, cfg, sensor: str, bias, hidden_s: float, onset: float, duration: float | None = None, *,
                    rates=None, n_rates: int = 8, refine: int = 1, n_missions: int = 4, margin: float = 0.2,
                    quantile: float = 0.0, seed: int = 0, window_s: float | None = None,
                    batch: int | None = None) -> StealthyDesign:
  """Fastest STEALTHY ramp of `bias` on `sensor` that `cfg`'s detector does not flag for `hidden_s` s after `onset`.

  env: the vehicle's env (envs.make(...); its missions, worlds and domain randomisation are the design's).
  cfg: the detector (a calibrated DetectorConfig, e.g. detection.calibrate(...)). bias: [d] full bias (direction and
  magnitude, the sensor's units; the ramp reaches it after |b| / rate s). duration: attack length (s; None: until
  the episode ends). rates: (lo, hi) search range of |db/dt| (default RATE_RANGES[sensor]); n_rates geometric grid
  points, then `refine` grids of n_rates between the fastest passing rate and the next. A rate passes when the
  `quantile` (0: the minimum) of its hidden times over the design missions is >= hidden_s (1 + margin), and so do
  all slower rates. Design missions: n_missions keys from `seed`, each also flown attack-free; one whose attack-free
  twin raises an alarm within the window (a false alarm the attacker cannot avoid) is left out (`dropped`).
  window_s: observation after the onset (default hidden_s (1 + margin) + 1). batch: simulation chunk (default
  (n_rates + 1) x n_missions: every simulation of the design then reuses one compiled function).
  Returns a StealthyDesign (see module docstring for the method); the fastest grid rate passing means the rate is
  limited by the search range, not the detector.
  """
  if sensor not in attacks_lib.SENSOR_NAMES:
    raise ValueError(f"unknown sensor {sensor!r}; choose one of {', '.join(attacks_lib.SENSOR_NAMES)}")
  bias = np.atleast_1d(np.asarray(bias, np.float32))
  if not np.linalg.norm(bias) > 0:
    raise ValueError("bias must be non-zero")
  if hidden_s <= 0:
    raise ValueError("hidden_s must be > 0")
  lo, hi = rates or RATE_RANGES[sensor]
  duration = NEVER if duration is None else duration
  required = hidden_s * (1.0 + margin)
  window_s = window_s or required + 1.0
  n_ticks = window_ticks(env, onset, window_s)
  keys = jax.random.split(jax.random.PRNGKey(seed), n_missions)
  batch = batch or (n_rates + 1) * n_missions

  def evaluate(grid, free=False):
    sched = _ramp_schedules(sensor, bias, grid, onset, duration, free)
    n_rows = len(grid) + free
    rep = jax.tree.map(lambda x: jnp.repeat(x, n_missions, axis=0), sched)     # [rows * M], row-major
    r, fresh, time, valid = record_residuals(env, cfg, jnp.tile(keys, (n_rows, 1)), rep, n_ticks, batch)
    hidden, det = hidden_times(cfg, r, fresh, time, valid, np.repeat(np.r_[[onset] * len(grid), [0.0] * free],
                                                                      n_missions))
    return hidden.reshape(n_rows, n_missions), det.reshape(n_rows, n_missions)

  all_rates = np.geomspace(lo, hi, n_rates)
  all_hidden, det = evaluate(all_rates, free=True)
  dropped = det[-1]
  all_hidden = all_hidden[:-1]
  if dropped.all():
    raise ValueError(f"every design mission raised a false alarm within {onset + window_s:.1f} s: calibrate the "
                     "detector (detection.calibrate) or change seed / n_missions")
  for it in range(refine + 1):
    ok = np.quantile(all_hidden[:, ~dropped], quantile, axis=1) >= required
    n_ok = int(np.argmin(ok)) if not ok.all() else len(ok)   # contiguous passing rates from the slowest
    if n_ok == 0 or n_ok == len(ok) or it == refine:
      break
    grid = np.geomspace(all_rates[n_ok - 1], all_rates[n_ok], n_rates + 2)[1:-1]
    all_rates = np.concatenate([all_rates, grid])
    all_hidden = np.concatenate([all_hidden, evaluate(grid)[0]])
    order = np.argsort(all_rates)
    all_rates, all_hidden = all_rates[order], all_hidden[order]
  feasible = n_ok > 0
  rate = float(all_rates[n_ok - 1]) if feasible else float("nan")
  mag = float(np.linalg.norm(bias))
  schedule = (attacks_lib.schedule_for(sensor, bias, onset, duration, "stealthy", ramp_time=mag / rate)
              if feasible else None)
  return StealthyDesign(schedule=schedule, sensor=sensor, bias=bias, rate=rate, ramp_time=mag / rate,
                        hidden_s=float(hidden_s), feasible=feasible, rates=all_rates, hidden=all_hidden,
                        required=float(required), dropped=np.asarray(dropped))


# Design biases per sensor for `design_rates` (the sensor's units; the ramp-rate limit depends on the direction more
# than on the magnitude: rate-limited GPS not at all, the level-limited sensors once |b| exceeds the detectable level).
DESIGN_BIAS = {
    "gps": (30.0, 0.0, 0.0),      # m east
    "gyro": (0.0, 0.0, 0.5),      # rad/s about z
    "accel": (0.0, 0.0, -2.0),    # m/s^2 down
    "mag": (float(np.pi / 2),),   # rad
    "baro": (-8.0,),              # m (the paper's "gradually decreasing")
    "flow": (1.0, 0.0),           # rad/s about x
}


def design_rates(env, sensors, hidden_s: float = 10.0, onset: float = 12.0, *, cfg=None, n_rates: int = 6,
                 refine: int = 1, n_missions: int = 4, margin: float = 0.2, seed: int = 0) -> dict:
  """Designed stealthy ramp rate per sensor against the env's calibrated detector: {sensor: {rate, feasible,
  ramp_time, hidden_s}} (rate in the sensor's bias units per s, nan when no rate in RATE_RANGES stays hidden).

  env: the vehicle's env with its detector (envs.make(..., detector='residual')); cfg: the detector (default
  env.det_cfg, the vehicle's calibrated preset). One `design_stealthy` of DESIGN_BIAS per sensor, all sharing one
  compiled simulation. The residual CUSUM is replayed; the GPS position cross-check (detector.position_check) is
  not, so the GPS rate is the CUSUM's limit only. An evaluation campaign (evaluation.campaign_settings 'designed')
  ramps each mission's own bias at the sensor's rate."""
  cfg = cfg if cfg is not None else env.det_cfg
  if cfg is None:
    raise ValueError("design_rates needs a detector: envs.make(..., detector='residual') or cfg=")
  out = {}
  for s in sensors:
    d = design_stealthy(env, cfg, s, DESIGN_BIAS[s], hidden_s, onset, n_rates=n_rates, refine=refine,
                        n_missions=n_missions, margin=margin, seed=seed, batch=(n_rates + 1) * n_missions)
    out[s] = {"rate": d.rate, "feasible": bool(d.feasible), "ramp_time": d.ramp_time, "hidden_s": float(hidden_s)}
  return out
