"""Data-parallel training on 4 CPU devices (--xla_force_host_platform_device_count, set before jax starts, so the
checks run in subprocesses): the same global batch, seed and env groups on 1 and on 4 devices train the same params
(phase 1 + a phase-2 iteration of each agent), the env state is sharded over the devices, a 1-device checkpoint
restores onto 4 devices, a non-divisible env count is a one-line error, a vmapped sweep equals its single runs, and
two processes joined by jax.distributed (gloo) train like one.

Cost: the time is XLA compiles, so each distinct program is compiled once: phases 1+2 on 1 device ('one'), on 4
devices ('four'), the vmapped phase-2 sweep ('sweep') and phase 2 on the 2-process mesh. The parts run as concurrent
subprocesses (a compile is single-threaded). Runs that differ only in data (seed, PPO hyperparameters) or in the step
budgets share compiled phases (iteration.make_phase): the sweep's single runs and the 2-process run's reference are
phase-2-only runs (phase1_steps=0) that reuse the 1-device run's phase-2 programs."""

import json
import os
import socket
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from conftest import FAST_COMPILE_FLAGS

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

COMMON = textwrap.dedent("""
  import dataclasses, json, os, resource, sys, time
  T0 = time.time()
  import jax, numpy as np
  from specguard_jax.ppo import attacker, config, distributed, iteration, runner
  SPENT = {"trace": 0.0, "lower": 0.0, "compile": 0.0, "compiles": 0}
  def _spent(event, secs, **_):   # where the time goes (trace / lower to MLIR / XLA compile)
    for k, e in (("trace", "jaxpr_trace"), ("lower", "to_mlir"), ("compile", "backend_compile")):
      if e in event:
        SPENT[k] += secs
        SPENT["compiles"] += k == "compile" and secs > 1.0
  jax.monitoring.register_event_duration_secs_listener(_spent)
  TINY = config.PPOConfig(num_minibatches=2, update_epochs=2, lr=1e-3)
  # checkpoint_every_s: only the end-of-phase checkpoints (the restores below read the last one). Phase 2 with the
  # oracle detector: the default 'mixed' also compiles the residual one into every phase-2 program (5 of them here),
  # which has nothing to do with how the devices split the work (its env is tested in test_env_detection).
  cfg = config.TrainConfig(num_envs=8, unroll_length=8, iters_per_call=2, phase1_steps=128, phase2_steps=128,
                           hidden=(32, 32), sg=TINY, aa=TINY, seed=3, env_groups=4, alternate_iters=1,
                           checkpoint_every_s=1e9).with_env(worlds=("suburban_residential",),
                                                            detector="oracle").validate()
  cfg2 = dataclasses.replace(cfg, phase1_steps=0)   # phase 2 only: 1 SG + 1 AA iteration, cfg's phase-2 programs
  CB = dataclasses.replace(cfg2, seed=4, sg=dataclasses.replace(TINY, lr=2e-3, clip_eps=0.1),
                           aa=dataclasses.replace(TINY, ent_coef=0.02))   # the sweep's member b
  out, res = sys.argv[1], {}

  def restore(run, n, traced=None):
    '''run's newest checkpoint (the final phase-2 carry) restored onto the layout of an n-device mesh (0: all).
    The shapes come from the phase-2 init traced by the run on `traced` devices (default n): same arguments (replicated
    as train() passes them), so no retrace; its shardings are moved onto the n-device mesh.'''
    mesh, target = distributed.make_mesh(n if traced is None else traced), distributed.make_mesh(n)
    ph = iteration.make_phase(cfg, 2, mesh)
    k = jax.random.PRNGKey(0)
    sg, aa, k = distributed.replicate((ph.sg.init(k, cfg.n_obs), ph.aa.init(k, attacker.N_OBS), k), mesh)
    abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=jax.sharding.NamedSharding(
        target, x.sharding.spec)), runner.abstract_carry(ph, k, sg, aa))
    mgr = runner._checkpointer(f"{out}/{run}")
    carry = runner._restore_carry(mgr, mgr.latest_step(), abstract)
    mgr.close()
    return carry

  def finals(carry):
    return distributed.to_host([carry.sg.params, carry.aa.params, carry.sg.normalizer.mean,
                                carry.sg.normalizer.std, carry.aa.normalizer.mean])

  def train(name, c, n, **kw):
    t = time.time()
    runner.train(dataclasses.replace(c, num_devices=n), f"{out}/{name}", progress=False, **kw)
    res[f"wall_{name}"] = time.time() - t
    carry = restore(name, n)
    leaf = carry.env_state.obs
    res[f"sharding_{name}"] = [len(leaf.sharding.device_set), [list(x.data.shape) for x in leaf.addressable_shards]]
    lines = [json.loads(l) for l in open(f"{out}/{name}/metrics.jsonl")]
    res[f"losses_{name}"] = [l["sg_loss"] for l in lines]
    res[f"aa_losses_{name}"] = [l.get("aa_loss", 0.0) for l in lines]
    np.savez(f"{out}/{name}.npz", *jax.tree.leaves(finals(carry)))
    np.savez(f"{out}/{name}_sg.npz", *jax.tree.leaves(distributed.to_host(carry.sg.params)))
    return carry

  def done():
    r = resource.getrusage(resource.RUSAGE_SELF)
    res["wall"], res["cpu"], res["spent"] = time.time() - T0, r.ru_utime + r.ru_stime, SPENT
    print("RESULT " + json.dumps(res))
""")

# The 4-device programs: phase 1 + phase 2 of cfg on 4 devices (one env group of 2 envs per device).
FOUR = COMMON + textwrap.dedent("""
  assert len(jax.devices()) == 4, jax.devices()
  train("d4", cfg, 4, export=False)
  done()
""")

# The 1-device programs: cfg on 1 device; the sweep members' single phase-2-only runs (they share the 1-device run's
# phase-2 programs); member b's 1-device checkpoint restored onto the 4-device layout.
ONE = COMMON + textwrap.dedent("""
  assert len(jax.devices()) == 4, jax.devices()
  c1 = train("d1", cfg, 1, export=False)
  init = iteration.make_agents(cfg)[0].init(jax.random.split(jax.random.PRNGKey(cfg.seed), 3)[0], cfg.n_obs).params
  res["max_param_change"] = max(float(np.max(np.abs(np.asarray(x) - np.asarray(y)))) for x, y in zip(
      jax.tree.leaves(c1.sg.params), jax.tree.leaves(init)))
  train("a1", cfg2, 1, export=False)           # also the reference of the 2-process run
  t = time.time()
  runner.train(dataclasses.replace(CB, num_devices=1), f"{out}/b1", progress=False, export=False)
  res["wall_b1"] = time.time() - t
  b1 = restore("b1", 4, traced=1)              # a 1-device checkpoint restored onto the 4-device layout
  res["b1_restored_devices"] = len(b1.env_state.obs.sharding.device_set)
  np.savez(f"{out}/b1_sg.npz", *jax.tree.leaves(distributed.to_host(b1.sg.params)))
  try:
    iteration.make_phase(dataclasses.replace(cfg, num_envs=6, env_groups=0), 1)
    res["divisible_error"] = None
  except ValueError as e:
    res["divisible_error"] = str(e)
  done()
""")

# A vmapped sweep of 2 members (seed and hyperparameters as data, members over 2 of the 4 devices), phase 2 only.
SWEEP = COMMON + textwrap.dedent("""
  t = time.time()
  sw = runner.train_sweep([cfg2, CB], ["a", "b"], f"{out}/sweep", progress=False, export=False)
  res["wall_sweep"] = time.time() - t
  res["sweep_devices"] = sw[0]["devices"]
  res["sweep_lr_b"] = float(np.asarray(sw[1]["sg_state"].opt_state.hyperparams["lr"]))
  for name, s in zip("ab", sw):
    np.savez(f"{out}/sweep_{name}_sg.npz", *jax.tree.leaves(s["sg_state"].params))
  done()
""")

# Two processes (one CPU device each) joined by jax.distributed (gloo collectives): cfg2 on the 2-process mesh, with
# checkpoints (collective saves and the restore below), logging and export (process 0).
MULTIHOST = textwrap.dedent("""
  import sys
  import jax, numpy as np
  jax.config.update("jax_cpu_collectives_implementation", "gloo")
  from specguard_jax.ppo import distributed    # before anything starts the backend
  distributed.initialize(sys.argv[2], 2, int(sys.argv[3]))
""") + COMMON + textwrap.dedent("""
  assert len(jax.devices()) == 2 and len(jax.local_devices()) == 1
  pid = jax.process_index()
  s = runner.train(cfg2, f"{out}/run", progress=False, export=True)
  res["processes"] = s["processes"]
  res["devices"] = s["devices"]
  carry = restore("run", 0)
  res["restored_devices"] = len(carry.env_state.obs.sharding.device_set)
  np.savez(f"{out}/p{pid}.npz", *jax.tree.leaves(finals(carry)))
  done()
""")


def _env(devices):
  env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
  # The suite's cheaper XLA:CPU compiles (tests/conftest.py), whatever SPECGUARD_TEST_FAST_COMPILE says: the programs
  # here are compiled once and run for a few tiny iterations; the fusion emitters off take ~25 % off a phase's compile.
  env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices} {FAST_COMPILE_FLAGS}"
  return env


def _start(cmds, env):
  return [subprocess.Popen(c, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
          for c in cmds]


def _wait(procs, timeout):
  """Wait for all (a failure or the timeout stops the others) -> [(returncode, stdout, stderr)]."""
  end = time.time() + timeout
  try:
    while any(p.poll() is None for p in procs):
      if time.time() > end or any(p.poll() not in (None, 0) for p in procs):
        break
      time.sleep(0.5)
  finally:
    for p in procs:
      if p.poll() is None:
        p.kill()
  return [(p.returncode,) + p.communicate() for p in procs]


def _result(rc, out, err):
  lines = [x for x in out.splitlines() if x.startswith("RESULT ")]
  assert rc == 0 and lines, f"rc={rc}\n{err[-3000:]}"
  return json.loads(lines[-1][len("RESULT "):])


def _gloo_ok():
  import jax
  return hasattr(jax.config, "jax_cpu_collectives_implementation")   # set to 'gloo' in the child processes


MH_TEST = "test_two_processes_with_jax_distributed_train_like_one"


@pytest.fixture(scope="module")
def runs(request, tmp_path_factory):
  """All subprocesses start at once (the 2-process run too, if selected: it only needs the others' results for its
  comparison), so the compiles of the parts overlap on the cores; waits for the 1-, 4-device and sweep parts."""
  out, mh_dir = tmp_path_factory.mktemp("dp"), tmp_path_factory.mktemp("mh")
  t = time.time()
  parts = {"one": ONE, "four": FOUR, "sweep": SWEEP}
  procs = _start([[sys.executable, "-c", s, str(out)] for s in parts.values()], _env(4))
  mh = []
  if _gloo_ok() and any(item.name == MH_TEST for item in request.session.items):
    with socket.socket() as sock:
      sock.bind(("127.0.0.1", 0))
      port = sock.getsockname()[1]
    mh = _start([[sys.executable, "-c", MULTIHOST, str(mh_dir), f"127.0.0.1:{port}", str(i)] for i in (0, 1)],
                _env(1))
  try:
    results = dict(zip(parts, (_result(*o) for o in _wait(procs, timeout=1200))))
  except BaseException:
    for p in mh:
      p.kill()
    raise
  res = {k: v for r in results.values() for k, v in r.items() if k not in ("wall", "cpu", "spent")}
  res["cost"] = {k: {"wall": r["wall"], "cpu": r["cpu"], **r["spent"]} for k, r in results.items()}
  res["cost"]["all_parts_wall"] = time.time() - t
  print("\n[multidevice] " + json.dumps({k: v for k, v in res.items() if k.startswith(("wall", "cost"))}))
  yield dict(res=res, dir=out, mh=mh, mh_dir=mh_dir, t0=t)
  for p in mh:
    if p.poll() is None:
      p.kill()


@pytest.fixture(scope="module")
def dp(runs):
  return runs["res"]


def test_one_and_four_devices_train_the_same_params(dp, runs):
  d1, d4 = np.load(runs["dir"] / "d1.npz"), np.load(runs["dir"] / "d4.npz")
  assert dp["max_param_change"] > 1e-4            # training moved the params (so equality below means something)
  assert len(d1.files) == len(d4.files) > 0
  diff = max(float(np.max(np.abs(d1[k] - d4[k]))) for k in d1.files)
  assert diff < 1e-4, diff
  assert len(dp["losses_d1"]) == 4 and any(x != 0 for x in dp["aa_losses_d1"][2:])   # phase 2 updated the attacker
  assert dp["losses_d1"] == pytest.approx(dp["losses_d4"], rel=1e-3, abs=1e-5)
  assert dp["aa_losses_d1"] == pytest.approx(dp["aa_losses_d4"], rel=1e-3, abs=1e-5)


def test_env_state_is_sharded_over_the_devices(dp):
  n1, shards1 = dp["sharding_d1"]
  n4, shards4 = dp["sharding_d4"]
  assert n1 == 1 and shards1 == [[4, 2, 44]]        # observation [G, B/G, 44]: the recovery layout
  assert n4 == 4 and shards4 == [[1, 2, 44]] * 4   # one env group of 2 envs per device
  assert dp["b1_restored_devices"] == 4            # a 1-device checkpoint restored onto 4 devices


def _max_diff(a, b):
  assert len(a.files) == len(b.files) > 0
  return max(float(np.max(np.abs(a[k] - b[k]))) for k in a.files)


def test_vmapped_sweep_equals_single_runs(dp, runs):
  sa, sb, a1, b1 = (np.load(runs["dir"] / f"{n}.npz") for n in ("sweep_a_sg", "sweep_b_sg", "a1_sg", "b1_sg"))
  assert dp["sweep_devices"] == 2                          # 2 members over 2 of the 4 devices
  assert _max_diff(sa, sb) > 1e-3                          # the members really differ
  assert dp["sweep_lr_b"] == pytest.approx(2e-3)           # member b's step size is data in its optimizer state
  assert _max_diff(sa, a1) < 1e-4 and _max_diff(sb, b1) < 1e-4, (_max_diff(sa, a1), _max_diff(sb, b1))


def test_env_count_not_divisible_by_devices_is_one_line_error(dp):
  err = dp["divisible_error"]
  assert err is not None and "\n" not in err and "divisible by the device count (4)" in err


@pytest.mark.slow
@pytest.mark.skipif(not _gloo_ok(), reason="this jaxlib has no CPU collectives (gloo) for a 2-process CPU run")
def test_two_processes_with_jax_distributed_train_like_one(runs):
  r0, r1 = (_result(*o) for o in _wait(runs["mh"], timeout=900))
  print(f"\n[multidevice] 2 processes: {time.time() - runs['t0']:.1f} s since the start, wall {r0['wall']:.1f} s, "
        f"cpu {r0['cpu']:.1f} + {r1['cpu']:.1f} s, {r0['spent']}")
  assert r0["processes"] == 2 and r0["devices"] == 2 and r0["restored_devices"] == 2
  mh = runs["mh_dir"]
  p0, p1, ref = (np.load(f) for f in (mh / "p0.npz", mh / "p1.npz", runs["dir"] / "a1.npz"))
  assert len(p0.files) == len(ref.files) > 0
  for k in ref.files:
    np.testing.assert_array_equal(p0[k], p1[k])                    # both processes hold the same replicas
    # and they equal the single-process run to float rounding: the gradient is reduced in another order, and the
    # range-ring inputs (up to 20 m) make the first layer's rows for them the largest (seen: 2.6e-4 on one weight)
    np.testing.assert_allclose(p0[k], ref[k], rtol=0, atol=5e-4)
  lines = (mh / "run" / "metrics.jsonl").read_text().splitlines()
  assert len(lines) == 2 and json.loads(lines[1])["aa_loss"] != 0   # only process 0 logged; both agents updated
  assert (mh / "run" / "policy.onnx").exists()                      # process 0 exported
  assert json.loads((mh / "run" / "summary.json").read_text())["processes"] == 2


# The env step with the lanes EKF kernel, split over 2 devices by shard_map (iteration.group_step), against the XLA
# env's plain vmap on one device (the kernel's one-device batch is read from a trace: its compile would double the
# test's time). The kernel needs a Hopper GPU, so its call is stood in for by its plain-JAX body (the same
# arithmetic) run on the host by a pure_callback; what this checks is the batch each device hands the kernel and the
# packed layout of P on every device.
KERNEL = textwrap.dedent("""
  import json
  import jax, jax.numpy as jnp, numpy as np
  from jax.sharding import NamedSharding, PartitionSpec
  import envs
  from brax.envs.wrappers.training import VmapWrapper
  from envs.wrappers import AutoReset
  from specguard_jax import ekf as ekf_lib, ekf_lanes
  from specguard_jax.ppo import distributed, iteration
  assert len(jax.devices()) == 2, jax.devices()
  env = envs.make("drone", control_mode="override", worlds=("suburban_residential",))
  env._ekf_kernel = "lanes"
  seen = []

  def fake_lanes_call(P, aux, n_rows, n_out, body, in_place):   # the kernel's body on [B] vectors, no TMA
    seen.append(list(P.shape))
    def run(P, aux):
      mem, p_out = dict(enumerate(aux)), dict(enumerate(P.T))
      def p_store(i, j, v):
        p_out[ekf_lib.TRI_INDEX[(i, j)]] = v
      body(lambda i, j: P[:, ekf_lib.TRI_INDEX[(i, j)]], p_store, mem.__getitem__, mem.__setitem__)
      return (jnp.stack([p_out[k] for k in range(ekf_lib.N_PACKED)], axis=1),
              jnp.stack([jnp.broadcast_to(mem[k], (P.shape[0],)) for k in range(n_out)]))
    # Run op by op on the host, opaque to XLA as the kernel's custom call is: compiled inline, the body's ~8,600 ops
    # on [B] vectors were most of the sharded program's compile.
    return jax.pure_callback(lambda P, aux: jax.device_get(run(jnp.asarray(P), jnp.asarray(aux))),
                             jax.eval_shape(run, P, aux), P, aux)

  ekf_lanes._lanes_call = fake_lanes_call
  batched = AutoReset(VmapWrapper(env), refresh_in_step=False)
  # The reference: the same envs with the XLA filter, stepped on one device (P square there).
  ref = AutoReset(VmapWrapper(envs.make("drone", control_mode="override", worlds=("suburban_residential",))),
                  refresh_in_step=False)
  G, Bg = 2, 3
  keys = jax.random.split(jax.random.PRNGKey(0), G * Bg).reshape(G, Bg, -1)
  # Both resets in one program: they differ only in P's layout, so XLA compiles their common part once (CSE).
  state0, ref0 = jax.jit(lambda k: (jax.vmap(batched.reset)(k), jax.vmap(ref.reset)(k)))(keys)
  act = jnp.full((G, Bg, 3), 0.3)
  mesh = distributed.make_mesh(2)
  distributed.use_gspmd_for_shard_map(mesh)   # as iteration.make_phase does with the kernel on several devices
  roll = lambda step: jax.jit(lambda s: jax.lax.scan(lambda s, _: (step(s, act), None), s, None, length=3)[0])
  one = roll(iteration.group_step(ref, None))(ref0)
  jax.make_jaxpr(iteration.group_step(batched, None))(state0, act)   # traced only: the batch one device hands it
  batch_one, seen[:] = seen[-1], []
  sharded = iteration.group_step(batched, mesh, per_device=True)
  s2 = jax.device_put(state0, NamedSharding(mesh, PartitionSpec(distributed.AXIS)))
  traced = roll(sharded).trace(s2)             # one trace: its jaxpr (the scan's body inline) and its compile
  batch_two = seen[-1]
  jaxpr = str(traced.jaxpr)
  two = traced.lower().compile()(s2)
  P1, P2 = one.info["sim"]["ekf"].P, ekf_lib.as_square(two.info["sim"]["ekf"].P)
  plain = str(jax.make_jaxpr(iteration.group_step(batched, mesh))(state0, act))   # not per_device: SPMD's vmap
  res = {"kernel_batch": [batch_one, batch_two], "shard_map": "shard_map" in jaxpr,
         "plain_shard_map": "shard_map" in plain, "shardy": bool(getattr(jax.config, "jax_use_shardy_partitioner", 0)),
         "P_shape": list(two.info["sim"]["ekf"].P.shape), "obs_shards": [list(x.data.shape) for x in two.obs.addressable_shards],
         "max_obs_diff": float(jnp.max(jnp.abs(one.obs - two.obs))), "max_P_rel": float(jnp.max(jnp.abs(P1 - P2)) / jnp.max(jnp.abs(P1))),
         "moved": float(jnp.max(jnp.abs(one.obs - ref0.obs)))}
  print("RESULT " + json.dumps(res))
""")


def test_lanes_ekf_kernel_steps_the_envs_per_device():
  # NPROC sizes XLA:CPU's thread pool (default: the core count): each device's callback holds a thread of it while
  # the body's eager ops run on another, so 2 devices need more than the 2 threads of a 2-core machine.
  env = dict(_env(2), NPROC=str(max(4, os.cpu_count() or 1)))
  r = _result(*_wait(_start([[sys.executable, "-c", KERNEL]], env), timeout=900)[0])
  assert r["kernel_batch"] == [[6, 121], [3, 121]]     # one device: all 6 envs in one call; split: 3 per device
  assert r["shard_map"]                                # the step calls the kernel inside a per-device split
  assert not r["plain_shard_map"]                      # without the kernel no shard_map (it crashes XLA on several GPUs)
  assert not r["shardy"]                               # the kernel's shard_map compiled by GSPMD, as on the GPUs
  assert r["P_shape"] == [2, 3, 121]                   # the kernel's packed layout of P, kept in the env state
  assert r["obs_shards"] == [[1, 3, 24]] * 2           # one env group per device
  assert r["moved"] > 1e-3
  assert r["max_obs_diff"] < 1e-4 and r["max_P_rel"] < 1e-4, r   # float32 rounding of the two filters


# On a host with 2 GPUs: the three training programs that a shard_map had made XLA segfault at compile time there
# (jax 0.11.2) compile and run: a plain run and a 2-member sweep without the kernel, and a
# run with the lanes EKF kernel. Each in its own process (a segfault must fail this test, not end the session).
@pytest.mark.gpu
def test_two_gpus_compile_and_train(tmp_path):
  import jax
  if len(jax.devices()) < 2:
    pytest.skip("needs 2 GPUs")
  base = [sys.executable, "train.py", "--devices", "2", "--envs", "2048", "--unroll", "8", "--iters-per-call", "1",
          "--phase1-steps", "32768", "--phase2-steps", "0", "--eval-missions", "0", "--no-export", "--no-progress",
          "--compile-cache", "off"]
  runs = {"plain": ["--out", str(tmp_path / "plain")],
          "sweep": ["--sweep", "seed=0,1", "--out", str(tmp_path / "sweep")],
          "fused": ["--ekf-kernel", "lanes", "--out", str(tmp_path / "fused")]}
  env = dict(os.environ, XLA_PYTHON_CLIENT_PREALLOCATE="false",
             PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
  procs = _start([base + extra for extra in runs.values()], env)
  for name, (rc, _, err) in zip(runs, _wait(procs, timeout=900)):
    assert rc == 0, f"{name}: rc={rc}\n{err[-2000:]}"
  for name in ("plain", "fused"):
    s = json.loads((tmp_path / name / "summary.json").read_text())
    assert s["env_steps"] >= 32768 and s["devices"] == 2, (name, s)
  assert (tmp_path / "sweep" / "sweep.json").exists()
