"""Data-parallel training on 4 CPU devices (--xla_force_host_platform_device_count, set before jax starts, so the
checks run in a subprocess): the same global batch, seed and env groups on 1 and on 4 devices train the same params
(phase 1 + a phase-2 iteration of each agent), the env state is sharded over the devices, checkpoints of sharded
carries restore, a non-divisible env count is a one-line error, and a vmapped sweep equals its single runs."""

import json
import os
import subprocess
import sys
import textwrap

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SCRIPT = textwrap.dedent("""
  import dataclasses, json, os, sys, time
  import jax, numpy as np
  from specguard_jax.ppo import attacker, config, distributed, iteration, runner
  assert len(jax.devices()) == 4, jax.devices()
  TINY = config.PPOConfig(num_minibatches=2, update_epochs=2, lr=1e-3)
  cfg = config.TrainConfig(num_envs=8, unroll_length=8, iters_per_call=2, phase1_steps=128, phase2_steps=128,
                           hidden=(32, 32), worlds=("suburban_residential",), sg=TINY, aa=TINY, seed=3,
                           env_groups=4, alternate_iters=1, checkpoint_every_s=0.0).validate()
  out, res = sys.argv[1], {}
  finals = {}
  for n in (1, 4):
    t = time.time()
    s = runner.train(dataclasses.replace(cfg, num_devices=n), f"{out}/d{n}", progress=False,
                     export=False)
    res[f"wall_{n}"] = time.time() - t
    ph = iteration.make_phase(cfg, 2, distributed.make_mesh(n))
    k = jax.random.PRNGKey(0)
    abstract = runner.abstract_carry(ph, k, ph.sg.init(k, 24), ph.aa.init(k, attacker.N_OBS))
    mgr = runner._checkpointer(f"{out}/d{n}")
    carry = runner._restore_carry(mgr, mgr.latest_step(), abstract)
    mgr.close()
    leaf = carry.env_state.obs
    res[f"sharding_{n}"] = [len(leaf.sharding.device_set), [list(x.data.shape) for x in leaf.addressable_shards]]
    finals[n] = jax.tree.map(np.asarray, (carry.sg.params, carry.aa.params, carry.sg.normalizer.mean,
                                          carry.sg.normalizer.std, carry.aa.normalizer.mean))
    res[f"losses_{n}"] = [json.loads(l)["sg_loss"] for l in open(f"{out}/d{n}/metrics.jsonl")]
    res[f"aa_losses_{n}"] = [json.loads(l).get("aa_loss", 0.0) for l in open(f"{out}/d{n}/metrics.jsonl")]
  a, b = jax.tree.leaves(finals[1]), jax.tree.leaves(finals[4])
  res["max_abs_diff"] = max(float(np.max(np.abs(x - y))) for x, y in zip(a, b))
  res["max_param_change"] = max(float(np.max(np.abs(x))) for x in jax.tree.leaves(
      jax.tree.map(lambda x, y: x - y, finals[1][0], jax.tree.map(np.asarray, iteration.make_agents(cfg)[0].init(
          jax.random.split(jax.random.PRNGKey(cfg.seed), 3)[0], 24).params))))
  np.savez(f"{out}/d1_params.npz", *jax.tree.leaves(finals[1]))
  # A vmapped sweep of 2 members (seed and hyperparameters as data; members spread over 2 of the 4 devices) equals
  # the 2 single runs: member a is the run above, member b runs alone on 1 device (same compiled phases).
  cb = dataclasses.replace(cfg, seed=4, sg=dataclasses.replace(TINY, lr=2e-3, clip_eps=0.1),
                           aa=dataclasses.replace(TINY, ent_coef=0.02))
  t = time.time()
  sw = runner.train_sweep([cfg, cb], ["a", "b"], f"{out}/sweep", progress=False, export=False)
  res["wall_sweep"] = time.time() - t
  res["sweep_devices"] = sw[0]["devices"]
  runner.train(dataclasses.replace(cb, num_devices=1), f"{out}/b1", progress=False, export=False)
  mgr = runner._checkpointer(f"{out}/b1")   # a 1-device checkpoint restored onto the 4-device layout
  cb1 = runner._restore_carry(mgr, mgr.latest_step(), abstract)
  mgr.close()
  single_b = jax.tree.map(np.asarray, cb1.sg.params)
  diff = lambda x, y: max(float(np.max(np.abs(np.asarray(u) - np.asarray(v)))) for u, v in zip(
      jax.tree.leaves(x), jax.tree.leaves(y)))
  res["sweep_diff_a"] = diff(sw[0]["sg_state"].params, finals[1][0])
  res["sweep_diff_b"] = diff(sw[1]["sg_state"].params, single_b)
  res["sweep_a_vs_b"] = diff(sw[0]["sg_state"].params, sw[1]["sg_state"].params)
  res["sweep_lr_b"] = float(np.asarray(sw[1]["sg_state"].opt_state.hyperparams["lr"]))
  try:
    iteration.make_phase(dataclasses.replace(cfg, num_envs=6, env_groups=0), 1)
    res["divisible_error"] = None
  except ValueError as e:
    res["divisible_error"] = str(e)
  print("RESULT " + json.dumps(res))
""")


# Two processes (one CPU device each) joined by jax.distributed with gloo collectives: the same config as SCRIPT.
MULTIHOST = textwrap.dedent("""
  import sys
  import jax, numpy as np
  jax.config.update("jax_cpu_collectives_implementation", "gloo")
  from specguard_jax.ppo import distributed    # before anything starts the backend
  addr, pid, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
  distributed.initialize(addr, 2, pid)
  from specguard_jax.ppo import attacker, config, iteration, runner
  assert len(jax.devices()) == 2 and len(jax.local_devices()) == 1
  TINY = config.PPOConfig(num_minibatches=2, update_epochs=2, lr=1e-3)
  cfg = config.TrainConfig(num_envs=8, unroll_length=8, iters_per_call=2, phase1_steps=128, phase2_steps=128,
                           hidden=(32, 32), worlds=("suburban_residential",), sg=TINY, aa=TINY, seed=3,
                           env_groups=4, alternate_iters=1, checkpoint_every_s=0.0).validate()
  runner.train(cfg, f"{out}/run", progress=False, export=False)
  ph = iteration.make_phase(cfg, 2)
  k = jax.random.PRNGKey(0)
  abstract = runner.abstract_carry(ph, k, ph.sg.init(k, 24), ph.aa.init(k, attacker.N_OBS))
  mgr = runner._checkpointer(f"{out}/run")
  carry = runner._restore_carry(mgr, mgr.latest_step(), abstract)
  mgr.close()
  final = distributed.to_host((carry.sg.params, carry.aa.params, carry.sg.normalizer.mean, carry.sg.normalizer.std,
                               carry.aa.normalizer.mean))
  np.savez(f"{out}/p{pid}.npz", *jax.tree.leaves(final))
  print("RESULT {}")
""")


def _env(devices):
  env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
  # Cheaper XLA:CPU compiles (the programs here are compiled once and run for a few tiny iterations).
  env["XLA_FLAGS"] = (f"--xla_force_host_platform_device_count={devices} --xla_backend_optimization_level=0 "
                      "--xla_llvm_disable_expensive_passes=true")
  return env


def _run_4dev(script, *args, timeout=900):
  p = subprocess.run([sys.executable, "-c", script, *args], cwd=ROOT, env=_env(4), capture_output=True, text=True,
                     timeout=timeout)
  lines = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
  assert p.returncode == 0 and lines, p.stderr[-3000:]
  return json.loads(lines[-1][len("RESULT "):])


@pytest.fixture(scope="module")
def dp_dir(tmp_path_factory):
  return tmp_path_factory.mktemp("dp")


@pytest.fixture(scope="module")
def dp(dp_dir):
  return _run_4dev(SCRIPT, str(dp_dir))


def test_one_and_four_devices_train_the_same_params(dp):
  assert dp["max_param_change"] > 1e-4            # training moved the params (so equality below means something)
  assert dp["max_abs_diff"] < 1e-4, dp["max_abs_diff"]
  assert len(dp["losses_1"]) == 4 and any(x != 0 for x in dp["aa_losses_1"][2:])   # phase 2 updated the attacker
  assert dp["losses_1"] == pytest.approx(dp["losses_4"], rel=1e-3, abs=1e-5)


def test_env_state_is_sharded_over_the_devices(dp):
  n1, shards1 = dp["sharding_1"]
  n4, shards4 = dp["sharding_4"]
  assert n1 == 1 and shards1 == [[4, 2, 24]]
  assert n4 == 4 and shards4 == [[1, 2, 24]] * 4   # one env group of 2 envs per device


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
@pytest.mark.skip(reason="not working yet: in the 2-process gloo run (2026-11-22) process 0 never reached the "
                  "shutdown barrier after training; plain gloo collectives across the 2 processes do work")
@pytest.mark.skipif(not _gloo_ok(), reason="this jaxlib has no CPU collectives (gloo) for a 2-process CPU run")
def test_two_processes_with_jax_distributed_train_like_one(dp, dp_dir, tmp_path):
  import socket

  import numpy as np
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
  procs = [subprocess.Popen([sys.executable, "-c", MULTIHOST, f"127.0.0.1:{port}", str(i), str(tmp_path)], cwd=ROOT,
                            env=_env(1), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in (0, 1)]
  outs = [p.communicate(timeout=900) for p in procs]
  for p, (o, e) in zip(procs, outs):
    assert p.returncode == 0 and "RESULT" in o, e[-3000:]
  p0, p1, ref = (np.load(tmp_path / f) for f in ("p0.npz", "p1.npz", dp_dir / "d1_params.npz"))
  assert len(p0.files) == len(ref.files) > 0
  for k in ref.files:
    np.testing.assert_array_equal(p0[k], p1[k])                    # both processes hold the same replicas
    np.testing.assert_allclose(p0[k], ref[k], rtol=0, atol=1e-4)   # and they equal the single-process run
  lines = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
  assert len(lines) == 4                                          # only process 0 logged
