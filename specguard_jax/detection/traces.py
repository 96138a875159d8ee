"""Record per-tick detector inputs from the real env ticks and replay detectors over them (benchmarks, tests).

`record_ticks` resets a batch of envs and drives `env._tick` (sensors -> attack -> EKF -> navigator -> autopilot ->
MJX) in one `lax.scan` of fixed length, keeping what a detector wired into the tick would see: the attacked
readings, the EKF state after the tick's update, the actuation that produced those readings, the tick's time and
whether the attack was on. The env object is only duck-typed (envs.base.RAVEnv), so this module does not import
envs.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import struct

from specguard_jax import ekf as ekf_lib
from specguard_jax.attacks import attacks as attacks_lib
from specguard_jax.autopilot import navigator as nav_lib
from specguard_jax.detection import detector as det

_DONE = nav_lib.DONE


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


def _actuation(env, sim):
  veh = sim["vehicle"]
  if env.vehicle == "drone":
    return veh["rotors"]
  return jnp.stack([veh["steer"], veh["throttle"]])


@functools.partial(jax.jit, static_argnames=("env", "n_ticks"))
def record_ticks(env, keys, attacks, n_ticks: int, world_ids=None) -> TickTrace:
  """keys [B] PRNG keys, attacks: batched AttackSchedule [B], world_ids: optional [B] int32 world preset ids
  (envs.worlds.PRESET_NAMES; None: the env's config); returns a TickTrace with leaves [B, n_ticks, ...]."""

  def one(key, attack, world_id):
    state = env.reset_in_world(key, world_id, None, attack)
    mission, world = state.info["mission"], state.info["world"]
    zero = jnp.zeros(3)
    no_override = jnp.zeros((), bool)

    def body(carry, k):
      data, sim, alive = carry
      t = sim["nav"].time
      act = _actuation(env, sim)
      data, sim = env._tick(data, sim, mission, world, zero, no_override, k, attack)
      ok = jnp.all(jnp.isfinite(data.qpos)) & (sim["nav"].phase != _DONE)
      if env.vehicle == "drone":
        ok = ok & ~sim["vehicle"]["hit"]
      alive = alive & ok
      out = TickTrace(readings=sim["readings"], ekf=sim["ekf"], actuation=act, time=t,
                      attack_on=attacks_lib.attack_active(attack, t), valid=alive)
      return (data, sim, alive), out

    ks = jax.random.split(jax.random.fold_in(key, 7), n_ticks)
    _, tr = jax.lax.scan(body, (state.pipeline_state, state.info["sim"], jnp.ones((), bool)), ks)
    return tr

  if world_ids is None:
    return jax.vmap(lambda k, a: one(k, a, None))(keys, attacks)
  return jax.vmap(one)(keys, attacks, jnp.asarray(world_ids, jnp.int32))


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
  max_score; and [B, T, C] scores."""

  def one(tr):
    def body(state, x):
      rd, ek, act = x
      state = det.detector_update(cfg, state, rd, ek, act, dt)
      return state, (state.alarm, state.diagnosis, state.scores)
    _, (alarm, diag, scores) = jax.lax.scan(body, det.detector_init(cfg), (tr.readings, tr.ekf, tr.actuation))
    return {"alarm": alarm, "diagnosis": diag, "scores": scores, "max_score": jnp.max(scores, axis=-1)}

  return jax.vmap(one)(trace)


def detection_metrics(alarm, diagnosis, trace: TickTrace, attack, diag_delay_ticks: int = 0):
  """Per-mission outcomes (numpy-able [B] arrays). alarm, diagnosis [B, T]; attack: batched AttackSchedule.

  false_alarm: an alarm before the onset (or anywhere, attack-free).  detected: an alarm raised while the attack is on
  (and no false alarm).  delay: s from onset to the first alarm after it (nan if none).  correct: the diagnosis on
  the first alarm tick after onset + diag_delay_ticks (the diagnosis window) is a sensor of the attack mask.
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
  return {"false_alarm": false_alarm, "detected": detected, "delay": delay, "correct": correct}
