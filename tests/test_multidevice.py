"""Data-parallel training on 4 CPU devices (--xla_force_host_platform_device_count, set before jax starts, so the
checks run in subprocesses): the same global batch, seed and env groups on 1 and on 4 devices train the same params
(phase 1 + a phase-2 iteration of each agent), the env state is sharded over the devices, a 1-device checkpoint
restores onto 4 devices, a non-divisible env count is a one-line error, a vmapped sweep equals its single runs, and
two processes joined by jax.distributed train like one.

Cost: every distinct XLA program is compiled once. The 1-device part ('one') and the 4-device part ('four') run as
two concurrent subprocesses (one compile each at a time; 2 cores). Runs that share a program config share compiled
phases (iteration.make_phase's cache): the sweep's single runs and the multi-process reference are phase-2-only runs
(phase1_steps=0), which reuse the 1-device run's phase-2 programs; the sweep itself is phase 2 only."""

import json
import os
import socket
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

COMMON = textwrap.dedent("""
  import dataclasses, json, os, resource, sys, time
  T0 = time.time()
  import jax, numpy as np
  from specguard_jax.ppo import attacker, config, distributed, iteration, runner
  TINY = config.PPOConfig(num_minibatches=2, update_epochs=2, lr=1e-3)
  # checkpoint_every_s: only the end-of-phase checkpoints (the restores below read the last one).
  cfg = config.TrainConfig(num_envs=8, unroll_length=8, iters_per_call=2, phase1_steps=128, phase2_steps=128,
                           hidden=(32, 32), worlds=("suburban_residential",), sg=TINY, aa=TINY, seed=3,
                           env_groups=4, alternate_iters=1, checkpoint_every_s=1e9).validate()
  cfg2 = dataclasses.replace(cfg, phase1_steps=0)   # phase 2 only: 1 SG + 1 AA iteration, cfg's phase-2 programs
  out, res = sys.argv[1], {}

  def restore(run, n):
    '''run's newest checkpoint (the final phase-2 carry) restored onto the layout of an n-device mesh (0: all).'''
    ph = iteration.make_phase(cfg, 2, distributed.make_mesh(n))
    k = jax.random.PRNGKey(0)
    abstract = runner.abstract_carry(ph, k, ph.sg.init(k, 24), ph.aa.init(k, attacker.N_OBS))
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
    return carry

  def done():
    r = resource.getrusage(resource.RUSAGE_SELF)
    res["wall"], res["cpu"] = time.time() - T0, r.ru_utime + r.ru_stime
    print("RESULT " + json.dumps(res))
""")

# The 4-device programs: phase 1 + phase 2 of cfg on 4 devices (one env group of 2 envs per device).
FOUR = COMMON + textwrap.dedent("""
  assert len(jax.devices()) == 4, jax.devices()
  train("d4", cfg, 4, export=False)
  done()
""")

# The 1-device programs and the sweep: cfg on 1 device; a vmapped 2-member phase-2 sweep (seed and hyperparameters
# as data, members over 2 of the 4 devices) against its members' single phase-2-only runs, which share the 1-device
# run's phase-2 programs; member b's 1-device checkpoint restored onto the 4-device layout.
ONE = COMMON + textwrap.dedent("""
  assert len(jax.devices()) == 4, jax.devices()
  c1 = train("d1", cfg, 1, export=False)
  init = iteration.make_agents(cfg)[0].init(jax.random.split(jax.random.PRNGKey(cfg.seed), 3)[0], 24).params
  res["max_param_change"] = max(float(np.max(np.abs(np.asarray(x) - np.asarray(y)))) for x, y in zip(
      jax.tree.leaves(c1.sg.params), jax.tree.leaves(init)))
  cb = dataclasses.replace(cfg2, seed=4, sg=dataclasses.replace(TINY, lr=2e-3, clip_eps=0.1),
                           aa=dataclasses.replace(TINY, ent_coef=0.02))
  t = time.time()
  sw = runner.train_sweep([cfg2, cb], ["a", "b"], f"{out}/sweep", progress=False, export=False)
  res["wall_sweep"] = time.time() - t
  res["sweep_devices"] = sw[0]["devices"]
  a1 = train("a1", cfg2, 1, export=False)     # also the reference of the 2-process run
  t = time.time()
  runner.train(dataclasses.replace(cb, num_devices=1), f"{out}/b1", progress=False, export=False)
  res["wall_b1"] = time.time() - t
  b1 = restore("b1", 4)                       # a 1-device checkpoint restored onto the 4-device layout
  res["b1_restored_devices"] = len(b1.env_state.obs.sharding.device_set)
  diff = lambda x, y: max(float(np.max(np.abs(np.asarray(u) - np.asarray(v)))) for u, v in zip(
      jax.tree.leaves(x), jax.tree.leaves(y)))
  res["sweep_diff_a"] = diff(sw[0]["sg_state"].params, distributed.to_host(a1.sg.params))
  res["sweep_diff_b"] = diff(sw[1]["sg_state"].params, distributed.to_host(b1.sg.params))
  res["sweep_a_vs_b"] = diff(sw[0]["sg_state"].params, sw[1]["sg_state"].params)
  res["sweep_lr_b"] = float(np.asarray(sw[1]["sg_state"].opt_state.hyperparams["lr"]))
  try:
    iteration.make_phase(dataclasses.replace(cfg, num_envs=6, env_groups=0), 1)
    res["divisible_error"] = None
  except ValueError as e:
    res["divisible_error"] = str(e)
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
  # Cheaper XLA:CPU compiles (the programs here are compiled once and run for a few tiny iterations); the fusion
  # emitters off take ~25 % off a phase's compile.
  env["XLA_FLAGS"] = (f"--xla_force_host_platform_device_count={devices} --xla_backend_optimization_level=0 "
                      "--xla_llvm_disable_expensive_passes=true --xla_cpu_use_fusion_emitters=false")
  return env


def _run_all(cmds, env, timeout):
  """Start the commands at once; wait for all (a failure stops the others). -> [(returncode, stdout, stderr)]."""
  procs = [subprocess.Popen(c, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
           for c in cmds]
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


@pytest.fixture(scope="module")
def dp_dir(tmp_path_factory):
  return tmp_path_factory.mktemp("dp")


@pytest.fixture(scope="module")
def dp(dp_dir):
  t = time.time()
  outs = _run_all([[sys.executable, "-c", s, str(dp_dir)] for s in (ONE, FOUR)], _env(4), timeout=900)
  one, four = (_result(*o) for o in outs)
  res = {**one, **{k: v for k, v in four.items() if k not in ("wall", "cpu")}}
  res["part_wall_cpu"] = {"one": (one["wall"], one["cpu"]), "four": (four["wall"], four["cpu"]),
                          "both": time.time() - t}
  print("\n[multidevice] " + json.dumps({k: v for k, v in res.items() if k.startswith(("wall", "part"))}))
  return res


def test_one_and_four_devices_train_the_same_params(dp, dp_dir):
  d1, d4 = np.load(dp_dir / "d1.npz"), np.load(dp_dir / "d4.npz")
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
  assert n1 == 1 and shards1 == [[4, 2, 24]]
  assert n4 == 4 and shards4 == [[1, 2, 24]] * 4   # one env group of 2 envs per device
  assert dp["b1_restored_devices"] == 4            # a 1-device checkpoint restored onto 4 devices


def test_vmapped_sweep_equals_single_runs(dp):
  assert dp["sweep_devices"] == 2                          # 2 members over 2 of the 4 devices
  assert dp["sweep_a_vs_b"] > 1e-3                         # the members really differ
  assert dp["sweep_lr_b"] == pytest.approx(2e-3)           # member b's step size is data in its optimizer state
  assert dp["sweep_diff_a"] < 1e-4 and dp["sweep_diff_b"] < 1e-4, (dp["sweep_diff_a"], dp["sweep_diff_b"])


def test_env_count_not_divisible_by_devices_is_one_line_error(dp):
  err = dp["divisible_error"]
  assert err is not None and "\n" not in err and "divisible by the device count (4)" in err


def _gloo_ok():
  import jax
  return hasattr(jax.config, "jax_cpu_collectives_implementation")   # set to 'gloo' in the child processes


@pytest.mark.slow
@pytest.mark.skipif(not _gloo_ok(), reason="this jaxlib has no CPU collectives (gloo) for a 2-process CPU run")
def test_two_processes_with_jax_distributed_train_like_one(dp, dp_dir, tmp_path):
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
  t = time.time()
  outs = _run_all([[sys.executable, "-c", MULTIHOST, str(tmp_path), f"127.0.0.1:{port}", str(i)] for i in (0, 1)],
                  _env(1), timeout=600)
  r0, r1 = (_result(*o) for o in outs)
  print(f"\n[multidevice] 2 processes: {time.time() - t:.1f} s wall, cpu {r0['cpu']:.1f} + {r1['cpu']:.1f} s")
  assert r0["processes"] == 2 and r0["devices"] == 2 and r0["restored_devices"] == 2
  p0, p1, ref = (np.load(f) for f in (tmp_path / "p0.npz", tmp_path / "p1.npz", dp_dir / "a1.npz"))
  assert len(p0.files) == len(ref.files) > 0
  for k in ref.files:
    np.testing.assert_array_equal(p0[k], p1[k])                    # both processes hold the same replicas
    np.testing.assert_allclose(p0[k], ref[k], rtol=0, atol=1e-4)   # and they equal the single-process run
  run = tmp_path / "run"
  lines = (run / "metrics.jsonl").read_text().splitlines()
  assert len(lines) == 2 and json.loads(lines[1])["aa_loss"] != 0   # only process 0 logged; both agents updated
  assert (run / "policy.onnx").exists() and json.loads((run / "summary.json").read_text())["processes"] == 2
