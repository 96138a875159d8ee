"""The SSR baseline's in-tick estimator (Choi et al., RAID 2020, "software sensors"): a system model predicts the
compromised sensor's readings from the control inputs; on detection the predictions REPLACE that sensor's readings fed
to the autopilot's own EKF; the original controller flies (specguard_jax.baselines.ssr fits and registers it).

Deployment: EnvConfig(control_mode='autopilot', detector='residual', recovery_estimator='software_sensors').
Per tick (`SoftwareSensors.pre_ekf`, before the EKF):
  * alarm down: the trusted EKF state of the previous tick and the controls applied since are checkpointed (ring of
    `window` ticks, specguard_jax.estimation.checkpointer);
  * alarm rising: the software-sensor model starts from the checkpoint `lag` ticks back and is rolled forward over the
    buffered controls (the fitted dynamics of specguard_jax.estimation.dynamics, assets/dynamics_<vehicle>.json);
  * alarm up: the model runs OPEN LOOP on the applied controls (it never sees a sensor again) and synthesises the
    diagnosed sensors' readings (GPS position/velocity, gyro rate + the EKF's gyro bias, accelerometer specific
    force + accel bias, magnetometer heading, barometric height, optical flow); those replace the compromised
    readings in the autopilot's EKF (fresh flags kept: same rates as the physical sensor).
Model error correction (ours, `bias_correction`): the mean world-acceleration residual of the model over the
checkpoint window (EKF velocity differences minus model acceleration: mostly the episode's wind, which the model does
not know) is added while rolling open loop.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from specguard_jax import math3d
from specguard_jax.estimation import checkpointer as ck
from specguard_jax.estimation import dynamics as dyn
from specguard_jax.estimation import model_file
from specguard_jax.estimation import traces
from specguard_jax.estimation import tree_file
from specguard_jax.estimation.estimator import Estimator
from specguard_jax.types import SENSOR_NAMES

# checkpoint entry: pos 3, vel 3, quat 4, rate 3
N_ENTRY = 13


@dataclasses.dataclass(frozen=True)
class SSRConfig:
  """window: checkpoint ring (ticks).  lag: checkpoint age the model starts from when the alarm rises (ticks).
  bias_correction: add the window's mean model acceleration residual while open loop.
  gates: per sensor (SENSOR_NAMES order) how far the physical reading may be from its software twin and still count
  as agreeing (GPS position m, gyro rad/s, accel m/s^2, mag rad, baro m, flow rad/s); agree_tau: time constant (s) of
  the smoothed disagreement that decides the hand-back."""
  window: int = 50
  lag: int = 10
  bias_correction: bool = True
  gates: tuple = (5.0, 0.1, 1.0, 0.2, 2.0, 0.3)
  agree_tau: float = 1.0


@struct.dataclass
class SSRState:
  """ckpt: trusted (state, control) ring.  model: DynState of the software-sensor model (meaningful while active).
  bias: [3] world acceleration correction (m/s^2).  active: [] bool, software sensors in use.  mask: [6] the sensors
  they replace (the detector's diagnosis, latched while active).  disagree: [6] smoothed |physical - software| /
  gate per sensor (> 1: the physical sensor is still off its software twin)."""
  ckpt: ck.CheckpointState
  model: dyn.DynState
  bias: jnp.ndarray
  active: jnp.ndarray
  mask: jnp.ndarray
  disagree: jnp.ndarray


def _features(s: dyn.DynState, u):
  """[n_u + 11] features of the software sensors' specific-force model: u, sum(u), v_b, |v_b| v_b, omega x v_b, 1."""
  r = math3d.quat_to_rot(s.quat)
  vb = r.T @ s.vel
  sp = jnp.linalg.norm(vb)
  return jnp.concatenate([u, jnp.sum(u)[None], vb, sp * vb, jnp.cross(s.rate, vb), jnp.ones(1)])


def feature_mask(vehicle: str, n_u: int) -> np.ndarray:
  """[3, n_u + 11] which features each body axis of the specific force may use (physically structured: a
  multicopter's horizontal specific force is drag only, its vertical one collective thrust; a rover's forward one
  throttle and drag, its lateral one the centripetal term)."""
  m = np.zeros((3, n_u + 11), bool)
  vb, sv, wv, one = n_u + 1, n_u + 4, n_u + 7, n_u + 10
  for ax in range(3):
    m[ax, [vb + ax, sv + ax, one]] = True
  if vehicle == "drone":
    m[2, n_u] = True                    # collective thrust
  else:
    m[0, :n_u] = True                   # throttle (and steering drag)
    m[1, wv + 1] = True                 # omega x v (centripetal)
  return m


@struct.dataclass
class ForceModel:
  """w: [3, F] specific-force weights (zero outside feature_mask); rms: [3] training residual (m/s^2)."""
  w: jnp.ndarray
  rms: jnp.ndarray


def specific_force(fm: ForceModel, s: dyn.DynState, u):
  return fm.w @ _features(s, u)


def _force_data(tr, vehicle: str):
  """(features [B, T-1, F], target specific force [B, T-1, 3], weight [B, T-1]) of flights tr (leaves [B, T, ...]):
  states from the EKF, target = accelerometer minus the EKF's bias; airborne ticks only (drone)."""
  e, rd = tr["ekf"], tr["readings"]
  s = dyn.DynState(pos=e["pos"], vel=e["vel"], quat=e["quat"], rate=rd.gyro - e["gyro_bias"])
  sp = jax.tree.map(lambda a: a[:, :-1], s)
  phi = jax.vmap(jax.vmap(_features))(sp, tr["controls"][:, 1:])
  y = (rd.accel - e["accel_bias"])[:, 1:]
  valid = jnp.ones(tr["time"].shape, bool) if vehicle != "drone" else tr["truth"].pos[..., 2] > 0.5
  return phi, y, (valid[:, 1:] & valid[:, :-1]).astype(jnp.float32)


@functools.partial(jax.jit, static_argnames=("vehicle", "heldout"))
def fit_force_model(tr, vehicle: str, lam: float = 1e-3, heldout: int = 0):
  """Ridge fit of the structured specific-force model on attack-free flights (common.flights traces, leaves
  [B, T, ...]), one axis at a time over its feature_mask. heldout > 0: fit on all but the last `heldout` missions.
  Returns (ForceModel, held-out residual RMS [3] (m/s^2) on the last `heldout` missions, NaN when heldout = 0)."""
  phi, y, w = _force_data(tr, vehicle)
  n_fit = phi.shape[0] - heldout
  flat = lambda a: a.reshape((-1,) + a.shape[2:])   # noqa: E731
  mask = feature_mask(vehicle, phi.shape[-1] - 11)
  ws, rms = [], []
  for ax in range(3):
    m = jnp.asarray(mask[ax], jnp.float32)
    wa, ra = dyn.ridge(flat(phi[:n_fit]) * m, flat(y[:n_fit, ..., ax:ax + 1]), flat(w[:n_fit]), lam)
    ws.append(wa[0] * mask[ax])
    rms.append(ra[0])
  fm = ForceModel(w=jnp.stack(ws), rms=jnp.stack(rms))
  if not heldout:
    return fm, jnp.full(3, jnp.nan)
  res = (jnp.einsum("af,btf->bta", fm.w, phi[n_fit:]) - y[n_fit:]) * w[n_fit:, :, None]
  return fm, jnp.sqrt(jnp.sum(res ** 2, (0, 1)) / jnp.maximum(jnp.sum(w[n_fit:]), 1.0))


def _unpack(e) -> dyn.DynState:
  return dyn.DynState(pos=e[..., 0:3], vel=e[..., 3:6], quat=e[..., 6:10], rate=e[..., 10:13])


def _accel(params, fm, s, u, bias):
  """(world acceleration [3], body angular acceleration [3]): structured specific force rotated to the world frame
  + gravity + bias correction; angular acceleration from the shipped rotational model."""
  _, alpha = dyn.derivatives(params, s, u)
  return math3d.quat_to_rot(s.quat) @ specific_force(fm, s, u) + dyn.G + bias, alpha


def _step(params, fm, s: dyn.DynState, u, bias, dt) -> dyn.DynState:
  """One tick of dt (s): semi-implicit Euler, exponential map on the attitude (as estimation.dynamics.step)."""
  acc, alpha = _accel(params, fm, s, u, bias)
  rate = s.rate + alpha * dt
  quat = math3d.normalize_quat(math3d.quat_mul(s.quat, math3d.rotvec_to_quat(0.5 * (s.rate + rate) * dt)))
  vel = s.vel + acc * dt
  return dyn.DynState(pos=s.pos + 0.5 * (s.vel + vel) * dt, vel=vel, quat=quat, rate=rate)


def model_start(cfg: SSRConfig, params, fm, ckpt: ck.CheckpointState, dt):
  """(DynState at the newest checkpointed tick + 1, bias [3]): the model rolled forward from the entry `lag` back
  over the buffered controls, and the window's mean acceleration residual (0 without bias_correction)."""
  states, controls, valid = ck.ckpt_ordered(ckpt)
  w = cfg.window
  lag = min(cfg.lag, w - 1)
  seq = _unpack(states)
  bias = jnp.zeros(3)
  if cfg.bias_correction:
    acc_model = jax.vmap(lambda s, u: _accel(params, fm, s, u, 0.0)[0])(seq, controls)     # [W, 3]
    acc_meas = (seq.vel[1:] - seq.vel[:-1]) / dt                                           # [W-1, 3]
    ok = (valid[1:] & valid[:-1])[:, None]   # empty slots hold zeros (a zero quaternion): select, never multiply
    bias = jnp.sum(jnp.where(ok, acc_meas - acc_model[:-1], 0.0), 0) / jnp.maximum(jnp.sum(ok), 1.0)
  start = jnp.maximum(w - 1 - lag, w - ckpt.count)
  s0 = jax.tree.map(lambda a: a[jnp.clip(start, 0, w - 1)], seq)

  def body(i, s):
    j = start + i   # entry j's control moves entry j's state one tick forward
    s_new = _step(params, fm, s, controls[jnp.clip(j, 0, w - 1)], bias, dt)
    return jax.tree.map(lambda a, b: jnp.where(j <= w - 1, a, b), s_new, s)

  return jax.lax.fori_loop(0, lag + 1, body, s0), bias


def predicted_readings(fm, s_prev: dyn.DynState, s: dyn.DynState, u, ekf, flow_min_height: float):
  """Software-sensor readings at the model state s (reached from s_prev under controls u): dict of SensorReadings
  fields. IMU readings include the EKF's bias estimates (the EKF subtracts them again)."""
  r = math3d.quat_to_rot(s.quat)
  vb = r.T @ s.vel
  return {"gps_pos": s.pos, "gps_vel": s.vel, "gyro": s.rate + ekf.gyro_bias,
          "accel": specific_force(fm, s_prev, u) + ekf.accel_bias,
          "mag_yaw": math3d.quat_to_euler(s.quat)[2], "baro_alt": s.pos[2],
          "flow": vb[:2] / jnp.maximum(s.pos[2], flow_min_height)}


_FIELDS = {"gps": ("gps_pos", "gps_vel"), "gyro": ("gyro",), "accel": ("accel",), "mag": ("mag_yaw",),
           "baro": ("baro_alt",), "flow": ("flow",)}


def substitute(readings, pred: dict, mask, active):
  """readings with the fields of each sensor in mask ([6] 0/1, SENSOR_NAMES order) replaced by pred while active."""
  out = {}
  for i, name in enumerate(SENSOR_NAMES):
    use = active & (jnp.asarray(mask)[i] > 0)
    for f in _FIELDS[name]:
      out[f] = jnp.where(use, pred[f], getattr(readings, f))
  return readings.replace(**out)


@dataclasses.dataclass(eq=False)
class SoftwareSensors(Estimator):
  """The env hook (estimation.estimator.Estimator). params: shipped rotational dynamics; fm: the fitted
  specific-force model."""
  cfg: SSRConfig
  params: dyn.DynParams
  fm: ForceModel
  vehicle: str
  dt: float
  flow_min_height: float
  n_u: int

  @classmethod
  def create(cls, env, model_path: str = "", cfg: SSRConfig | None = None):
    if not model_path:
      raise ValueError("recovery_estimator='software_sensors' needs recovery_model= the SSR model file "
                       "(specguard_jax.baselines.ssr.build writes it)")
    n_u = 4 if env.vehicle == "drone" else 2
    fm = load_force_model(model_path, n_u)
    path = env.config.dynamics_model or model_file.default_path(env.vehicle)
    return cls(cfg or SSRConfig(), model_file.load_params(path, n_u), fm, env.vehicle, env.config.tick_dt,
               float(env.ekf_cfg.flow_min_height), n_u)

  def init(self, ekf, readings):
    s = dyn.DynState(pos=ekf.pos, vel=ekf.vel, quat=ekf.quat, rate=readings.gyro - ekf.gyro_bias)
    return SSRState(ckpt=ck.ckpt_init(self.cfg.window, N_ENTRY, self.n_u), model=s, bias=jnp.zeros(3),
                    active=jnp.zeros((), bool), mask=jnp.zeros(len(SENSOR_NAMES)),
                    disagree=jnp.zeros(len(SENSOR_NAMES)))

  def pre_ekf(self, sim, readings):
    st: SSRState = sim["baseline"]
    det = sim["det"]
    alarm = jnp.asarray(det.alarm) > 0
    # Recovery mode: on from the alarm; off once the alarm is down AND every replaced sensor agrees with its software
    # twin again. The detector watches the EKF, which fuses the software sensors: it goes quiet while the attack is
    # still on, and handing back on its clear alone re-fused the attack and restarted the model from a stale checkpoint.
    held = st.active & jnp.any((st.mask > 0) & (st.disagree > 1.0))
    active = alarm | held
    mask = jnp.where(alarm, jnp.asarray(det.mask, jnp.float32), st.mask)
    u = traces.vehicle_controls(self.vehicle, sim)        # applied during the previous tick
    e, rd = sim["ekf"], sim["readings"]                     # trusted while not in recovery
    s_ekf = dyn.DynState(pos=e.pos, vel=e.vel, quat=e.quat, rate=rd.gyro - e.gyro_bias)
    entry = jnp.concatenate([s_ekf.pos, s_ekf.vel, s_ekf.quat, s_ekf.rate])
    ckpt = ck.ckpt_update(st.ckpt, entry, u, active)
    rising = active & ~st.active
    s_start, bias0 = model_start(self.cfg, self.params, self.fm, ckpt, self.dt)   # previous tick, from the checkpoint
    s_start = jax.tree.map(lambda a, b: jnp.where(ckpt.count > 0, a, b), s_start, s_ekf)   # nothing checkpointed
    s_base = jax.tree.map(lambda a, b: jnp.where(rising, a, b), s_start, st.model)
    bias = jnp.where(rising, bias0, st.bias)
    # states that no compromised sensor feeds stay synchronised with the EKF (attitude, body rate); position and
    # velocity always run on the model while in recovery
    m = mask > 0
    gyro_c, mag_c = m[SENSOR_NAMES.index("gyro")], m[SENSOR_NAMES.index("mag")]
    s_base = s_base.replace(quat=jnp.where(gyro_c | mag_c, s_base.quat, e.quat),
                            rate=jnp.where(gyro_c, s_base.rate, s_ekf.rate))
    s_new = _step(self.params, self.fm, s_base, u, bias, self.dt)                 # this tick
    s_new = s_new.replace(rate=jnp.where(gyro_c, s_new.rate, readings.gyro - e.gyro_bias))
    finite = jnp.all(jnp.isfinite(jnp.concatenate(jax.tree.leaves(s_new))))
    s_new = jax.tree.map(lambda a, b: jnp.where(finite, a, b), s_new, s_ekf)   # a diverged model restarts
    pred = predicted_readings(self.fm, s_base, s_new, u, e, self.flow_min_height)
    rd_ekf = substitute(readings, pred, mask, active)
    d, fresh = disagreement(readings, pred, self.cfg.gates)
    a = jnp.where(fresh, min(1.0, self.dt / self.cfg.agree_tau), 0.0)
    disagree = jnp.where(rising, jnp.maximum(d, 2.0), (1.0 - a) * st.disagree + a * d)   # starts "disagreeing"
    model = jax.tree.map(lambda x, y: jnp.where(active, x, y), s_new, s_ekf)
    new = SSRState(ckpt=ckpt, model=model, bias=jnp.where(active, bias, jnp.zeros(3)), active=active,
                   mask=jnp.where(active, mask, 0.0), disagree=jnp.where(active, disagree, 0.0))
    return dict(sim, baseline=new), rd_ekf


def disagreement(readings, pred: dict, gates: tuple):
  """(|physical - software| / gate [6] per sensor (SENSOR_NAMES; GPS: position, mag: wrapped heading), fresh [6]:
  the sensor delivered a new sample this tick)."""
  diff = {"gps": jnp.linalg.norm(readings.gps_pos - pred["gps_pos"]),
          "gyro": jnp.linalg.norm(readings.gyro - pred["gyro"]),
          "accel": jnp.linalg.norm(readings.accel - pred["accel"]),
          "mag": jnp.abs(jnp.mod(readings.mag_yaw - pred["mag_yaw"] + jnp.pi, 2 * jnp.pi) - jnp.pi),
          "baro": jnp.abs(readings.baro_alt - pred["baro_alt"]),
          "flow": jnp.linalg.norm(readings.flow - pred["flow"])}
  fresh = {"gps": readings.gps_fresh, "mag": readings.mag_fresh, "baro": readings.baro_fresh,
           "flow": readings.flow_fresh}
  d = jnp.stack([diff[n] for n in SENSOR_NAMES]) / jnp.asarray(gates, jnp.float32)
  f = jnp.stack([jnp.asarray(fresh.get(n, 1.0)) > 0 for n in SENSOR_NAMES])
  return d, f


def load_force_model(path: str, n_u: int) -> ForceModel:
  """The fitted specific-force model from its file (tree_file); one-line ValueError if missing or corrupt."""
  tmpl = ForceModel(w=np.zeros((3, n_u + 11), np.float32), rms=np.zeros(3, np.float32))
  tree, _ = tree_file.load_tree(path, tmpl)
  return ForceModel(w=jnp.asarray(tree.w, jnp.float32), rms=jnp.asarray(tree.rms, jnp.float32))
