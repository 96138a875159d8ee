"""Deployable policy: save/load a trained run's policy and export it to ONNX (normalisation folded into the graph).

The deployed function is obs [B, n_obs] float32 ->
  x = clip((obs - mean) / std, -clip, clip)         Brax running_statistics.normalize + the trainer's clip
  out = MLP(x)                                      Policy.forward (Gemm + activation per layer)
  discrete:  logits [B, 6], action = argmax(logits) [B], setpoint = DIRECTIONS[action] * speeds [B, 3] m/s
  gaussian:  mean [B, n], setpoint = tanh(mean) * speeds [B, n]: velocity m/s [3] (+ attitude residual m/s^2 [3])
`jax_policy_fn` is the JAX reference; `export_onnx` writes the same function as an ONNX graph (built with
onnx.helper, opset 17, ir_version 8, dynamic batch dim 'B') and refuses to write it unless onnxruntime matches the
reference (|diff| <= 1e-5 + 1e-5 * max|output|, same argmax up to float ties). A run directory holds
`policy.msgpack` ({'params', 'normalizer': {'mean', 'std'}}, flax.serialization) and `policy_config.json`
({'kind', 'n', 'hidden', 'activation', 'speeds', 'clip', 'n_obs'} and the observation layout 'obs_layout', absent in
policies saved before layouts were recorded); the trainer calls save_policy then export_onnx.
"""

from __future__ import annotations

import json
import os
import time

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np

from specguard_jax.ppo.networks import DIRECTIONS, Policy, to_setpoint

POLICY_FILE = "policy.msgpack"
CONFIG_FILE = "policy_config.json"
CONFIG_KEYS = ("kind", "n", "hidden", "activation", "speeds", "clip", "n_obs")
PARITY_ATOL = 1e-5
PARITY_RTOL = 1e-5
IR_VERSION = 8
MIN_OPSET, MAX_OPSET = 13, 17


# ---------------------------------------------------------------------------------------------------------------
# Inputs


def _normalizer_arrays(normalizer) -> tuple[np.ndarray, np.ndarray]:
  """(mean [n_obs], std [n_obs]) float32 from a Brax RunningStatisticsState / NestedMeanStd or a {'mean','std'}
  dict."""
  if isinstance(normalizer, dict):
    if "mean" not in normalizer or "std" not in normalizer:
      raise ValueError(f"normalizer dict needs 'mean' and 'std', got keys {sorted(normalizer)}")
    mean, std = normalizer["mean"], normalizer["std"]
  elif hasattr(normalizer, "mean") and hasattr(normalizer, "std"):
    mean, std = normalizer.mean, normalizer.std
  else:
    raise ValueError(f"normalizer must be a RunningStatisticsState or a {{'mean','std'}} dict, "
                     f"got {type(normalizer).__name__}")
  mean, std = np.asarray(mean, np.float32), np.asarray(std, np.float32)
  if mean.ndim != 1 or mean.shape != std.shape:
    raise ValueError(f"normalizer mean/std must be equal-length vectors, got {mean.shape} and {std.shape}")
  if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(std)) and np.all(std > 0)):
    raise ValueError("normalizer mean/std must be finite with std > 0")
  return mean, std


def _speeds(speeds, policy: Policy) -> np.ndarray:
  """The setpoint's scale per output: [3] velocity (m/s per axis), or [6] with the acceleration residual (m/s^2;
  EnvConfig.override_attitude) for a gaussian policy of 6 outputs."""
  s = np.asarray(speeds, np.float32)
  if s.ndim != 1 or s.shape[0] not in (3, 6) or not np.all(np.isfinite(s)):
    raise ValueError(f"speeds must be 3 (velocity, m/s) or 6 (+ attitude residual, m/s^2) finite numbers, "
                     f"got shape {s.shape}")
  want = 3 if policy.kind == "discrete" else policy.n
  if s.shape[0] != want:
    raise ValueError(f"{s.shape[0]} speeds for a {policy.kind} policy of {policy.n} outputs (needs {want})")
  return s


def _clip(clip) -> float | None:
  if clip is None:
    return None
  c = float(clip)
  if not (np.isfinite(c) and c > 0):
    raise ValueError(f"clip must be a positive finite number or None, got {clip!r}")
  return c


def _layers(policy: Policy, params) -> list[tuple[np.ndarray, np.ndarray]]:
  """[(kernel [in, out], bias [out]) float32] of the policy MLP, checked against policy.hidden / policy.n."""
  try:
    net = params["net"]
  except (KeyError, TypeError, IndexError):
    raise ValueError("params must be a dict with a 'net' entry (Policy.init layout)") from None
  if policy.kind == "discrete" and policy.n != len(DIRECTIONS):
    raise ValueError(f"a discrete policy needs n={len(DIRECTIONS)} logits (DIRECTIONS), got n={policy.n}")
  sizes = tuple(policy.hidden) + (policy.n,)
  names = [f"dense_{i}" for i in range(len(sizes))]
  if sorted(net) != sorted(names):
    raise ValueError(f"params['net'] has layers {sorted(net)}, policy expects {names}")
  layers, n_in = [], None
  for name, size in zip(names, sizes):
    k = np.asarray(net[name]["kernel"], np.float32)
    b = np.asarray(net[name]["bias"], np.float32)
    if k.ndim != 2 or k.shape[1] != size or b.shape != (size,) or (n_in is not None and k.shape[0] != n_in):
      raise ValueError(f"params['net']['{name}'] kernel {k.shape} / bias {b.shape} do not fit hidden={sizes}")
    if not (np.all(np.isfinite(k)) and np.all(np.isfinite(b))):
      raise ValueError(f"params['net']['{name}'] has non-finite values")
    layers.append((k, b))
    n_in = size
  return layers


def _obs_layout(layout, n_obs: int) -> dict:
  """A policy_config.json 'obs_layout' ({'name' str, 'version' int, 'fields': [[name, size], ...]}, envs.observation
  .describe) checked: well formed, and its sizes add up to the policy's n_obs."""
  ok = (isinstance(layout, dict) and isinstance(layout.get("name"), str) and isinstance(layout.get("version"), int)
        and isinstance(layout.get("fields"), list)
        and all(isinstance(f, (list, tuple)) and len(f) == 2 and isinstance(f[0], str) and isinstance(f[1], int)
                and f[1] > 0 for f in layout["fields"]))
  if not ok:
    raise ValueError(f"obs_layout must be {{'name': str, 'version': int, 'fields': [[name, size], ...]}}, "
                     f"got {layout!r}"[:300])
  total = sum(f[1] for f in layout["fields"])
  if total != n_obs:
    raise ValueError(f"obs_layout {layout['name']!r} has {total} inputs, the policy takes {n_obs}")
  return {"name": layout["name"], "version": layout["version"], "fields": [[f[0], f[1]] for f in layout["fields"]]}


def n_obs_of(params) -> int:
  """Observation size the policy params expect (rows of the first kernel)."""
  return int(np.shape(params["net"]["dense_0"]["kernel"])[0])


# ---------------------------------------------------------------------------------------------------------------
# JAX reference


def normalize_obs(obs, mean, std, clip: float | None = 10.0):
  """clip((obs - mean) / std, -clip, clip) [.., n_obs] float32 (= running_statistics.normalize(obs, state, clip))."""
  x = (jnp.asarray(obs, jnp.float32) - jnp.asarray(mean, jnp.float32)) / jnp.asarray(std, jnp.float32)
  return x if clip is None else jnp.clip(x, -clip, clip)


def jax_policy_fn(policy: Policy, params, normalizer, speeds, clip: float | None = 10.0):
  """Jittable obs [B, n_obs] -> dict of the ONNX graph's outputs: discrete {'logits' [B, 6], 'action' [B] int32
  (int64 in ONNX), 'setpoint' [B, 3]}; gaussian {'mean' [B, n], 'setpoint' [B, n]} (m/s, then m/s^2)."""
  mean, std = _normalizer_arrays(normalizer)
  speeds, clip = _speeds(speeds, policy), _clip(clip)
  layers = _layers(policy, params)
  if layers[0][0].shape[0] != mean.shape[0]:
    raise ValueError(f"normalizer has {mean.shape[0]} obs dims, policy expects {layers[0][0].shape[0]}")
  p = {"net": {f"dense_{i}": {"kernel": jnp.asarray(k), "bias": jnp.asarray(b)} for i, (k, b) in enumerate(layers)}}

  def fn(obs):
    out = policy.forward(p, normalize_obs(obs, mean, std, clip))
    if policy.kind == "discrete":
      action = jnp.argmax(out, axis=-1).astype(jnp.int32)
      return {"logits": out, "action": action, "setpoint": to_setpoint("discrete", action, speeds)}
    return {"mean": out, "setpoint": to_setpoint("gaussian", out, speeds)}

  return fn


# ---------------------------------------------------------------------------------------------------------------
# Run directory


def save_policy(run_dir: str, policy: Policy, params, normalizer, speeds, clip: float | None = 10.0,
                obs_layout: dict | None = None) -> None:
  """Write run_dir/policy.msgpack and run_dir/policy_config.json (validated first; the directory is created).
  obs_layout: the observation layout the policy was trained on (envs.observation.describe), recorded so that
  evaluate.py builds the same observation; None: not recorded (read back as the 24-input paper layout)."""
  mean, std = _normalizer_arrays(normalizer)
  layers = _layers(policy, params)
  speeds, clip = _speeds(speeds, policy), _clip(clip)
  if layers[0][0].shape[0] != mean.shape[0]:
    raise ValueError(f"normalizer has {mean.shape[0]} obs dims, policy expects {layers[0][0].shape[0]}")
  tree = {"net": {f"dense_{i}": {"kernel": k, "bias": b} for i, (k, b) in enumerate(layers)}}
  if policy.kind == "gaussian":
    tree["log_std"] = np.asarray(params["log_std"], np.float32)
  blob = flax.serialization.to_bytes({"params": tree, "normalizer": {"mean": mean, "std": std}})
  cfg = {"kind": policy.kind, "n": int(policy.n), "hidden": [int(h) for h in policy.hidden],
         "activation": policy.activation, "speeds": [float(s) for s in speeds], "clip": clip,
         "n_obs": int(mean.shape[0])}
  if obs_layout is not None:
    cfg["obs_layout"] = _obs_layout(obs_layout, int(mean.shape[0]))
  os.makedirs(run_dir, exist_ok=True)
  _atomic_write(os.path.join(run_dir, POLICY_FILE), blob)
  _atomic_write(os.path.join(run_dir, CONFIG_FILE), (json.dumps(cfg, indent=1) + "\n").encode())


def _atomic_write(path: str, data: bytes) -> None:
  tmp = path + ".tmp"
  with open(tmp, "wb") as f:
    f.write(data)
  os.replace(tmp, path)


def _one_line(e: BaseException) -> str:
  return " ".join(f"{type(e).__name__}: {e}".split())


def load_policy(run_dir: str):
  """(policy, params, {'mean','std'} [n_obs], speeds [n] (m/s, then m/s^2), clip) from a run dir by save_policy.
  Arrays come back as numpy float32. Missing or malformed files -> ValueError naming the file."""
  cfg_path, pol_path = os.path.join(run_dir, CONFIG_FILE), os.path.join(run_dir, POLICY_FILE)
  try:
    with open(cfg_path) as f:
      cfg = json.load(f)
  except (OSError, ValueError) as e:
    raise ValueError(f"{cfg_path}: cannot read policy config ({_one_line(e)})") from None
  if not isinstance(cfg, dict) or any(k not in cfg for k in CONFIG_KEYS):
    missing = [k for k in CONFIG_KEYS if not isinstance(cfg, dict) or k not in cfg]
    raise ValueError(f"{cfg_path}: policy config misses keys {missing}")
  try:
    if not isinstance(cfg["hidden"], list):
      raise ValueError(f"hidden must be a list of layer sizes, got {cfg['hidden']!r}")
    policy = Policy(kind=cfg["kind"], n=int(cfg["n"]), hidden=tuple(int(h) for h in cfg["hidden"]),
                    activation=cfg["activation"])
    speeds, clip, n_obs = _speeds(cfg["speeds"], policy), _clip(cfg["clip"]), int(cfg["n_obs"])
    if "obs_layout" in cfg:
      _obs_layout(cfg["obs_layout"], n_obs)
  except (TypeError, ValueError) as e:
    raise ValueError(f"{cfg_path}: bad policy config ({_one_line(e)})") from None
  try:
    with open(pol_path, "rb") as f:
      blob = f.read()
  except OSError as e:
    raise ValueError(f"{pol_path}: cannot read policy weights ({_one_line(e)})") from None
  try:
    tree = flax.serialization.msgpack_restore(blob)
  except Exception as e:  # noqa: BLE001  (msgpack raises several unrelated exception types on corrupt input)
    raise ValueError(f"{pol_path}: not a valid policy msgpack ({_one_line(e)})") from None
  try:
    params, norm = tree["params"], tree["normalizer"]
    mean, std = _normalizer_arrays(norm)
    layers = _layers(policy, params)
    if layers[0][0].shape[0] != n_obs or mean.shape != (n_obs,):
      raise ValueError(f"weights/normalizer do not match n_obs={n_obs} of {CONFIG_FILE}")
    out = {"net": {f"dense_{i}": {"kernel": k, "bias": b} for i, (k, b) in enumerate(layers)}}
    if policy.kind == "gaussian":
      log_std = np.asarray(params["log_std"], np.float32)
      if log_std.shape != (policy.n,):
        raise ValueError(f"log_std has shape {log_std.shape}, expected ({policy.n},)")
      out["log_std"] = log_std
  except (KeyError, TypeError, IndexError, ValueError) as e:
    raise ValueError(f"{pol_path}: weights do not fit {CONFIG_FILE} ({_one_line(e)})") from None
  return policy, out, {"mean": mean, "std": std}, speeds, clip


def load_obs_layout(run_dir: str) -> dict | None:
  """The observation layout a run's policy_config.json records ({'name', 'version', 'fields'}), None where it records
  none (policies saved before layouts were recorded: the 24-input paper layout). ValueError naming the file when the
  record is malformed or does not add up to the policy's n_obs."""
  cfg_path = os.path.join(run_dir, CONFIG_FILE)
  try:
    with open(cfg_path) as f:
      cfg = json.load(f)
  except (OSError, ValueError) as e:
    raise ValueError(f"{cfg_path}: cannot read policy config ({_one_line(e)})") from None
  if not isinstance(cfg, dict) or "obs_layout" not in cfg:
    return None
  try:
    return _obs_layout(cfg["obs_layout"], int(cfg.get("n_obs", -1)))
  except (TypeError, ValueError) as e:
    raise ValueError(f"{cfg_path}: bad obs_layout ({_one_line(e)})") from None


def load_jax_policy(run_dir: str):
  """jax_policy_fn of a trained run directory (obs [B, n_obs] -> dict of outputs; wrap in jax.jit)."""
  policy, params, normalizer, speeds, clip = load_policy(run_dir)
  return jax_policy_fn(policy, params, normalizer, speeds, clip)


# ---------------------------------------------------------------------------------------------------------------
# ONNX


def build_onnx(policy: Policy, params, normalizer, speeds, *, clip: float | None = 10.0, opset: int = 17,
               metadata: dict | None = None):
  """The policy as an onnx.ModelProto: input 'obs' float32 [B, n_obs]; outputs as jax_policy_fn (action int64)."""
  import onnx
  from onnx import TensorProto, helper, numpy_helper

  if not MIN_OPSET <= int(opset) <= MAX_OPSET:
    raise ValueError(f"opset must be in [{MIN_OPSET}, {MAX_OPSET}], got {opset}")
  mean, std = _normalizer_arrays(normalizer)
  speeds, clip = _speeds(speeds, policy), _clip(clip)
  layers = _layers(policy, params)
  n_obs = layers[0][0].shape[0]
  if n_obs != mean.shape[0]:
    raise ValueError(f"normalizer has {mean.shape[0]} obs dims, policy expects {n_obs}")

  inits, nodes = [], []

  def const(name, value):
    inits.append(numpy_helper.from_array(np.asarray(value), name))
    return name

  def node(op, inputs, name, **attrs):
    nodes.append(helper.make_node(op, inputs, [name], name=name, **attrs))
    return name

  x = node("Sub", ["obs", const("obs_mean", mean)], "obs_centered")
  x = node("Div", [x, const("obs_std", std)], "obs_scaled")
  if clip is not None:
    x = node("Clip", [x, const("clip_min", np.float32(-clip)), const("clip_max", np.float32(clip))], "obs_norm")
  for i, (k, b) in enumerate(layers):
    last = i == len(layers) - 1
    out = ("logits" if policy.kind == "discrete" else "mean") if last else f"dense_{i}"
    x = node("Gemm", [x, const(f"dense_{i}_kernel", k), const(f"dense_{i}_bias", b)], out)
    if not last:
      if policy.activation == "tanh":
        x = node("Tanh", [x], f"act_{i}")
      elif policy.activation == "relu":
        x = node("Relu", [x], f"act_{i}")
      elif policy.activation == "elu":
        x = node("Elu", [x], f"act_{i}", alpha=1.0)
      elif policy.activation == "swish":  # x * sigmoid(x); no Swish op at opset <= 17
        x = node("Mul", [x, node("Sigmoid", [x], f"sigmoid_{i}")], f"act_{i}")
      else:
        raise ValueError(f"no ONNX lowering for activation {policy.activation!r}")

  obs_info = helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["B", n_obs])
  if policy.kind == "discrete":
    node("ArgMax", ["logits"], "action", axis=1, keepdims=0, select_last_index=0)
    node("Gather", [const("setpoint_table", DIRECTIONS * speeds[None, :]), "action"], "setpoint", axis=0)
    outputs = [helper.make_tensor_value_info("logits", TensorProto.FLOAT, ["B", policy.n]),
               helper.make_tensor_value_info("action", TensorProto.INT64, ["B"]),
               helper.make_tensor_value_info("setpoint", TensorProto.FLOAT, ["B", 3])]
  else:
    node("Mul", [node("Tanh", ["mean"], "mean_tanh"), const("speeds", speeds)], "setpoint")
    outputs = [helper.make_tensor_value_info("mean", TensorProto.FLOAT, ["B", policy.n]),
               helper.make_tensor_value_info("setpoint", TensorProto.FLOAT, ["B", policy.n])]

  graph = helper.make_graph(nodes, f"specguard_{policy.kind}_policy", [obs_info], outputs, initializer=inits,
                            doc_string="obs -> clip((obs-mean)/std) -> MLP -> logits|mean, setpoint [m/s; "
                                       "outputs 3:6 of a 6-output policy m/s^2]")
  model = helper.make_model(graph, producer_name="specguard-jax", opset_imports=[helper.make_opsetid("", opset)])
  model.ir_version = IR_VERSION
  props = {"kind": policy.kind, "n": str(policy.n), "n_obs": str(n_obs), "hidden": json.dumps(list(policy.hidden)),
           "activation": policy.activation, "speeds": json.dumps([float(s) for s in speeds]),
           "clip": json.dumps(clip), "outputs": ",".join(o.name for o in outputs),
           "normalization": "clip((obs - mean) / std, -clip, clip)"}
  if policy.kind == "discrete":
    props["directions"] = json.dumps(DIRECTIONS.astype(int).tolist())
  for key, val in (metadata or {}).items():
    val = val if isinstance(val, str) else json.dumps(val)
    if key in props and props[key] != val:
      raise ValueError(f"metadata key {key!r} clashes with the exported {key}={props[key]}")
    props[key] = val
  helper.set_model_props(model, props)
  onnx.checker.check_model(model, full_check=True)
  return model


def _session(path: str):
  import onnxruntime as ort

  so = ort.SessionOptions()
  so.intra_op_num_threads = 1
  so.inter_op_num_threads = 1
  so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
  so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
  return ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])


def parity_obs(normalizer, n_rows: int = 1024, seed: int = 0) -> np.ndarray:
  """Test observations [n_rows + extremes, n_obs] float32: mean + std * N(0, 1), plus rows at the mean, at 0, at
  mean +- 1e3 std (saturating the clip) and at +-1e4."""
  mean, std = _normalizer_arrays(normalizer)
  rng = np.random.default_rng(seed)
  rows = mean + std * rng.standard_normal((n_rows, mean.shape[0]))
  signs = rng.choice([-1.0, 1.0], (8, mean.shape[0]))
  extremes = np.concatenate([mean[None], np.zeros_like(mean)[None], mean + 1e3 * std * signs,
                             mean + 30 * std * signs, np.full_like(mean, 1e4)[None], np.full_like(mean, -1e4)[None]])
  return np.concatenate([rows, extremes]).astype(np.float32)


def check_parity(onnx_path: str, fn, obs, atol: float = PARITY_ATOL, rtol: float = PARITY_RTOL) -> dict:
  """Run the ONNX file (onnxruntime) and the JAX `fn` on obs [B, n_obs]; ValueError (one line) unless the main
  output (logits | mean) agrees within tol = atol + rtol * max|JAX output| and no row's ONNX action is worse than
  the JAX argmax by more than tol. The rtol term matters only for outputs above ~1: onnxruntime and XLA differ by
  ~5e-7 relative (tanh/Gemm rounding), so |logits| ~ 50 gives ~2.5e-5 abs; rtol=0 is a plain abs check.
  Returns {'max_abs_diff', 'tol', 'setpoint_max_abs_diff', 'argmax_equal' (True for gaussian),
  'argmax_near_ties'}."""
  obs = np.asarray(obs, np.float32)
  sess = _session(onnx_path)
  names = [o.name for o in sess.get_outputs()]
  got = dict(zip(names, sess.run(None, {"obs": obs})))
  ref = {k: np.asarray(v) for k, v in jax.jit(fn)(obs).items()}
  if sorted(got) != sorted(ref):
    raise ValueError(f"ONNX outputs {sorted(got)} != JAX outputs {sorted(ref)}")
  main = "logits" if "logits" in ref else "mean"
  diff = float(np.max(np.abs(got[main].astype(np.float64) - ref[main]))) if obs.shape[0] else 0.0
  scale = float(np.max(np.abs(ref[main]), initial=0.0))
  tol = atol + rtol * scale
  if not np.isfinite(diff) or diff > tol:
    raise ValueError(f"ONNX/JAX parity failed: max |{main} diff| = {diff:.3g} > {tol:.3g} (max |{main}| = "
                     f"{scale:.3g}) on {obs.shape[0]} rows")
  same = np.ones(obs.shape[0], bool)
  near_ties = 0
  if main == "logits":
    same = got["action"] == ref["action"]
    if not np.all(same):
      # Where the actions differ, the ONNX choice must still be a JAX maximum within atol (a float-rounding tie).
      rows = np.nonzero(~same)[0]
      gap = ref["logits"][rows, ref["action"][rows]] - ref["logits"][rows, got["action"][rows]]
      if np.any(gap > tol):
        raise ValueError(f"ONNX/JAX parity failed: argmax differs on {int(np.sum(gap > tol))}/{obs.shape[0]} rows "
                         f"by logit gaps up to {float(np.max(gap)):.3g}")
      near_ties = int(rows.size)
  sp = np.abs(got["setpoint"][same] - ref["setpoint"][same])
  sp_diff = float(np.max(sp)) if sp.size else 0.0
  sp_tol = atol + rtol * float(np.max(np.abs(ref["setpoint"]), initial=0.0))
  if not np.isfinite(sp_diff) or sp_diff > sp_tol:
    raise ValueError(f"ONNX/JAX parity failed: max |setpoint diff| = {sp_diff:.3g} > {sp_tol:.3g}")
  return {"max_abs_diff": diff, "tol": tol, "setpoint_max_abs_diff": sp_diff, "argmax_equal": bool(np.all(same)),
          "argmax_near_ties": near_ties}


def onnx_latency_us(onnx_path: str, n_obs: int, calls: int = 2000, warmup: int = 100) -> float:
  """Median wall time of one batch-1 onnxruntime call (1 intra-op thread, from Python) in microseconds."""
  sess = _session(onnx_path)
  x = np.zeros((1, n_obs), np.float32)
  feed = {"obs": x}
  for _ in range(warmup):
    sess.run(None, feed)
  t = np.empty(calls)
  for i in range(calls):
    t0 = time.perf_counter_ns()
    sess.run(None, feed)
    t[i] = time.perf_counter_ns() - t0
  return float(np.median(t) / 1e3)


def export_onnx(path: str, policy: Policy, params, normalizer, speeds, *, clip: float | None = 10.0,
                opset: int = 17, metadata: dict | None = None, parity_rows: int = 1024, seed: int = 0,
                atol: float = PARITY_ATOL, rtol: float = PARITY_RTOL, latency_calls: int = 2000) -> dict:
  """Write the policy (normalisation folded in) to `path` as ONNX after checking onnxruntime against
  jax_policy_fn on parity_obs rows (check_parity; ValueError and no file written on mismatch). metadata: extra
  str/JSON-able metadata_props (vehicle, variant, ...). latency_calls=0 skips the timing (-> None).
  Returns {'path', 'max_abs_diff', 'argmax_equal', 'latency_us_per_decision' (batch 1, 1 thread, median),
  'opset', 'tol', 'setpoint_max_abs_diff', 'argmax_near_ties', 'n_obs', 'bytes'}."""
  model = build_onnx(policy, params, normalizer, speeds, clip=clip, opset=opset, metadata=metadata)
  fn = jax_policy_fn(policy, params, normalizer, speeds, clip)
  path = os.fspath(path)
  if os.path.dirname(path):
    os.makedirs(os.path.dirname(path), exist_ok=True)
  tmp = path + ".tmp"
  with open(tmp, "wb") as f:
    f.write(model.SerializeToString())
  try:
    parity = check_parity(tmp, fn, parity_obs(normalizer, parity_rows, seed), atol, rtol)
    n_obs = n_obs_of(params)
    latency = onnx_latency_us(tmp, n_obs, latency_calls) if latency_calls > 0 else None
  except BaseException:
    os.remove(tmp)
    raise
  os.replace(tmp, path)
  return {"path": path, "max_abs_diff": parity["max_abs_diff"], "argmax_equal": parity["argmax_equal"],
          "latency_us_per_decision": latency, "opset": int(opset), "tol": parity["tol"],
          "setpoint_max_abs_diff": parity["setpoint_max_abs_diff"], "argmax_near_ties": parity["argmax_near_ties"],
          "n_obs": n_obs, "bytes": os.path.getsize(path)}
