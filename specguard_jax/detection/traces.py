"""Per-tick detector inputs recorded from the real env ticks, and detectors replayed over them (calibration, design,
benchmarks, tests).

`envs.record(env, keys, n_ticks, RECORD_FIELDS, attacks=...)` flies a batch through the env's own ticks (sensors ->
attack -> EKF -> navigator -> autopilot -> MJX) in one `lax.scan`; `tick_trace` turns its record into a `TickTrace`:
what a detector wired into the tick would see (the attacked readings, the EKF state after the tick's update, the
actuation that produced those readings, the tick's time, whether the attack was on, whether the mission is still
valid). This module does not import envs: the caller records.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import struct

from specguard_jax import ekf as ekf_lib
from specguard_jax.detection import detector as det


@struct.dataclass
class TickTrace:
  """Per-tick detector inputs, [..., T, ...]: readings (SensorReadings), ekf (EKFState), actuation [T, n],
  time [T] s (the attack clock at the tick), attack_on [T] bool, valid [T] bool (mission not finished, no crash)."""
  readings: object
  ekf: object
  actuation: jnp.ndarray
  time: jnp.ndarray
  attack_on: jnp.ndarray
  valid: jnp.ndarray


# The envs.record fields a TickTrace is made of.
RECORD_FIELDS = ("readings", "ekf", "actuation", "start_time", "attack_on", "alive")


@jax.jit
def tick_trace(rec: dict) -> TickTrace:
  """A TickTrace from `envs.record(..., RECORD_FIELDS, ...)` (leaves [B, T, ...]): time is the tick's start (the
  attack clock); valid is 'alive' up to the first tick that is not (a mission that ended, crashed or went NaN stays
  invalid)."""
  valid = jax.lax.associative_scan(jnp.logical_and, rec["alive"], axis=1)
  return TickTrace(readings=rec["readings"], ekf=rec["ekf"], actuation=rec["actuation"], time=rec["start_time"],
                   attack_on=rec["attack_on"], valid=valid)


def _slim_ekf(ekf):
  """Drop the covariance (not used by the detector) to keep traces small."""
  lead = ekf.P.shape[:-1] if ekf_lib.p_layout(ekf.P) == "packed" else ekf.P.shape[:-2]
  return ekf.replace(P=jnp.zeros(lead + (0, 0)))


@functools.partial(jax.jit, static_argnames=("cfg", "dt"))
def residual_trace(cfg: det.DetectorConfig, trace: TickTrace, dt: float):
  """Raw residuals of a batch of traces: (|r| [B, T, C], fresh [B, T, C] & valid) for `calibrate`."""

  def one(tr):
    def body(state, x):
      rd, ek, act = x
      r, fresh, state = det.residuals(cfg, state, rd, ek, act, dt)
      return state, (r, fresh)
    _, (r, fresh) = jax.lax.scan(body, det.detector_init(cfg), (tr.readings, tr.ekf, tr.actuation))
    return r, fresh & tr.valid[:, None]

  return jax.vmap(one)(trace)


@functools.partial(jax.jit, static_argnames=("cfg", "dt"))
def xcheck_trace(cfg: det.DetectorConfig, trace: TickTrace, dt: float):
  """Raw GPS cross-checks (detector.position_check) of a batch of traces with the alarm held down (the dead
  reckoning stays anchored, as on an attack-free flight): [B, T, 3] = (min |GPS - DR| m, velocity chi, |GPS height -
  baro| m (detector._hgt_off)), zero where the check is not armed or the mission is over; for calibrating dr_h / vel_h /
  hgt_h."""

  def one(tr):
    def body(state, x):
      rd, ek, act = x
      _, _, state = det.residuals(cfg, state, rd, ek, act, dt)
      cons, state = det.consistency(cfg, state, rd, ek, dt)
      xchk, armed, state = det.position_check(cfg, state, rd, ek, dt)
      hgt = cons[2] * (cons[4] > 0.5) * (state.airborne_time >= cfg.xcheck_arm_s)
      return state, jnp.concatenate([xchk[:2] * jnp.asarray([cfg.dr_h, cfg.vel_h]) * armed, hgt[None]])
    _, x = jax.lax.scan(body, det.detector_init(cfg), (tr.readings, tr.ekf, tr.actuation))
    return x * tr.valid[:, None]

  return jax.vmap(one)(trace)


@functools.partial(jax.jit, static_argnames=("cfg", "dt"))
def run_detector(cfg: det.DetectorConfig, trace: TickTrace, dt: float):
  """Replays `detector_update` over a batch of traces. Returns dict of [B, T] arrays: alarm, diagnosis,
  max_score; [B, T, C] scores; and [B, T, 6] mask (the diagnosed sensors, SENSOR_NAMES order)."""

  def one(tr):
    def body(state, x):
      rd, ek, act = x
      state = det.detector_update(cfg, state, rd, ek, act, dt)
      return state, (state.alarm, state.diagnosis, state.scores, state.mask)
    _, (alarm, diag, scores, mask) = jax.lax.scan(body, det.detector_init(cfg), (tr.readings, tr.ekf, tr.actuation))
    return {"alarm": alarm, "diagnosis": diag, "scores": scores, "max_score": jnp.max(scores, axis=-1), "mask": mask}

  return jax.vmap(one)(trace)


def detection_metrics(alarm, diagnosis, trace: TickTrace, attack, diag_delay_ticks: int = 0, mask=None,
                      mask_delay_ticks: int | None = None):
  """Per-mission outcomes (numpy-able [B] arrays). alarm, diagnosis [B, T]; attack: batched AttackSchedule;
  mask: [B, T, 6] the detector's diagnosed-sensor mask (run_detector's 'mask'), optional.

  false_alarm: an alarm before the onset (or anywhere, attack-free).  detected: an alarm raised while the attack is on
  (and no false alarm).  delay: s from onset to the first alarm after it (nan if none).  correct: the diagnosis on
  the first alarm tick after onset + diag_delay_ticks (the diagnosis window) is a sensor of the attack mask.
  With `mask`, at the last tick up to mask_delay_ticks (default diag_delay_ticks) after the first alarm where the alarm
  is up and the mission valid: mask_at [B, 6] the diagnosed mask (0/1); mask_exact [B] it equals the attack mask
  (and the mission is detected).
  """
  valid = trace.valid
  t = trace.time
  onset = attack.onset[:, None]
  pre = (t < onset) & valid
  false_alarm = jnp.any(alarm & pre, axis=-1)
  during = alarm & trace.attack_on & valid
  detected = jnp.any(during, axis=-1) & ~false_alarm
  first = jnp.argmax(during, axis=-1)
  t_first = jnp.take_along_axis(t, first[:, None], axis=-1)[:, 0]
  delay = jnp.where(detected, t_first - attack.onset, jnp.nan)
  at = jnp.minimum(first + diag_delay_ticks, alarm.shape[-1] - 1)
  d_first = jnp.take_along_axis(diagnosis, at[:, None], axis=-1)[:, 0]
  hit = jnp.take_along_axis(attack.mask, jnp.maximum(d_first, 0)[:, None], axis=-1)[:, 0] > 0
  correct = detected & (d_first >= 0) & hit
  out = {"false_alarm": false_alarm, "detected": detected, "delay": delay, "correct": correct}
  if mask is not None:
    # the last tick of that span with the alarm up on a valid mission (an alarm can clear and rise again)
    span = diag_delay_ticks if mask_delay_ticks is None else mask_delay_ticks
    ticks = jnp.arange(alarm.shape[-1])
    ok = alarm & valid & (ticks >= first[:, None]) & (ticks <= first[:, None] + span)
    at_m = jnp.max(jnp.where(ok, ticks, 0), axis=-1)
    m_at = jnp.take_along_axis(jnp.asarray(mask), at_m[:, None, None], axis=1)[:, 0] > 0.5
    out["mask_at"] = m_at
    out["mask_exact"] = detected & jnp.all(m_at == (attack.mask > 0.5), axis=-1)
  return out
