"""bench/gpu_profile.py's trace bookkeeping (HLO op_name map, stage of a name stack, GPU busy time, perfetto events)
and the named scopes of a compiled training iteration it charges kernels to."""

import gzip
import json
import os
import sys

import jax
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "bench"))
import gpu_profile  # noqa: E402

HLO = """
HloModule jit_run
%fused_computation.3 (p: f32[4]) -> f32[4] {
  ROOT %tanh.1 = f32[4]{0} tanh(f32[4]{0} %p), metadata={op_name="jit(run)/while/body/ppo_update/jvp(MLP)/tanh"}
}
ENTRY %main {
  %fusion.3 = f32[4]{0} fusion(f32[4]{0} %x), kind=kLoop, calls=%fused_computation.3, metadata={op_name="jit(run)/while/body/env_step/vmap(autoreset)/jit(_where)/select_n" source_file="w.py" source_line=3}
  ROOT %copy.1 = f32[4]{0} copy(f32[4]{0} %fusion.3)
}
"""


def test_op_names_and_stages():
  names = gpu_profile.op_names(HLO)
  assert names["fusion.3"].endswith("autoreset)/jit(_where)/select_n")
  assert names["tanh.1"].endswith("/ppo_update/jvp(MLP)/tanh")
  assert "copy.1" not in names                                   # no metadata
  assert gpu_profile.stage_of(names["fusion.3"]) == "autoreset"   # innermost known scope wins over env_step
  assert gpu_profile.stage_of(names["tanh.1"]) == "ppo_update"
  assert gpu_profile.stage_of("jit(run)/while/body/env_step/vmap()/autopilot/physics/step/euler") == "physics"
  assert gpu_profile.stage_of("jit(run)/while/body/closed_call") == "other"
  assert gpu_profile.stage_of("jit(run)/env_step/vmap()/reconstruction/shadow_ekf/add") == "shadow_ekf"
  assert gpu_profile.stage_of("jit(run)/env_step/vmap()/reconstruction/recon_replay/mul") == "recon_replay"
  assert gpu_profile.stage_of("jit(run)/env_step/vmap()/reconstruction/scatter") == "reconstruction"
  assert gpu_profile.stage_of("jit(run)/ekfish/x") == "other"     # whole scope names only


def test_kernels_without_metadata_get_the_scope_of_their_computation_or_operands():
  hlo = HLO + """
%fused_computation.9 (q: f32[4]) -> f32[4] {
  %n.1 = f32[4]{0} negate(f32[4]{0} %q), metadata={op_name="jit(run)/while/body/ppo_update/neg"}
  ROOT %n.2 = f32[4]{0} negate(f32[4]{0} %n.1)
}
ENTRY %other {
  %fusion.9 = f32[4]{0} fusion(f32[4]{0} %x), kind=kLoop, calls=%fused_computation.9
  %copy.7 = f32[4]{0} copy(f32[4]{0} %fusion.3)
  ROOT %copy.8 = f32[4]{0} copy(f32[4]{0} %y)
}
"""
  names = gpu_profile.attributed_op_names(hlo)
  assert gpu_profile.stage_of(names["fusion.9"]) == "ppo_update"    # from its fused computation
  assert gpu_profile.stage_of(names["copy.7"]) == "autoreset"       # from its operand
  assert names["copy.8"] == ""                                      # nothing to go by
  assert names["fusion.3"] == gpu_profile.op_names(hlo)["fusion.3"]  # metadata wins


def test_busy_time_counts_overlaps_once():
  ev = [("a", "", 10.0, 0.0), ("b", "", 5.0, 5.0), ("c", "", 4.0, 20.0), ("d", "", 1.0, 21.0)]
  assert gpu_profile.busy_us(ev) == pytest.approx(14.0)   # [0, 10] u [5, 10] u [20, 24] u [21, 22]


def test_idle_gaps_are_charged_to_the_kernels_around_them(capsys):
  # busy [0, 10] (a, b overlapping), idle 10 us, [20, 24] (c, d), idle 1 us, [25, 26] (a again), idle 30 us, e
  ev = [("a", "k1", 10.0, 0.0), ("b", "k2", 5.0, 5.0), ("c", "k3", 4.0, 20.0), ("d", "k4", 1.0, 21.0),
        ("a", "k1", 1.0, 25.0), ("e", "", 2.0, 56.0)]
  res = gpu_profile.idle_gaps(ev, {"k1": "jit(run)/while/body/ppo_update/dot"})
  assert res["idle_us"] == pytest.approx(41.0)
  assert res["idle_bins_us"] == pytest.approx({"5-20 us": 10.0, "<5 us": 1.0, "20-100 us": 30.0})
  out = capsys.readouterr().out
  assert "| k1 (ppo_update) | e (?) | 30 | 1 |" in out    # the kernel ending the busy interval, then the next one
  assert "| k1 (ppo_update) | k3 (?) | 10 | 1 |" in out   # k1 ends [0, 10] (b ended earlier)
  assert "| k3 (?) | k1 (ppo_update) | 1 | 1 |" in out


def test_gpu_events_read_from_the_perfetto_trace(tmp_path):
  d = tmp_path / "plugins" / "profile" / "run1"
  d.mkdir(parents=True)
  trace = {"traceEvents": [
      {"ph": "M", "pid": 1, "name": "process_name", "args": {"name": "/device:GPU:0"}},
      {"ph": "M", "pid": 2, "name": "process_name", "args": {"name": "/host:CPU"}},
      {"ph": "X", "pid": 1, "ts": 3.0, "dur": 2.5, "name": "loop_fusion", "args": {"hlo_op": "fusion.3"}},
      {"ph": "X", "pid": 2, "ts": 1.0, "dur": 9.0, "name": "host work", "args": {}}]}
  with gzip.open(d / "perfetto_trace.json.gz", "wt") as f:
    json.dump(trace, f)
  assert gpu_profile.gpu_events(str(tmp_path)) == [("loop_fusion", "fusion.3", 2.5, 3.0)]
  with pytest.raises(FileNotFoundError):
    gpu_profile.gpu_events(str(tmp_path / "plugins" / "nothing"))


def test_a_compiled_training_iteration_carries_the_stage_scopes():
  """Every stage of a phase-1 iteration reaches the optimised HLO's op_names (a renamed or dropped scope would leave
  the profile charging its kernels to 'other')."""
  from specguard_jax.ppo import attacker, config, distributed, iteration
  tiny = config.PPOConfig(num_minibatches=2, update_epochs=1)
  cfg = config.TrainConfig(num_envs=8, unroll_length=2, iters_per_call=1, hidden=(16, 16), sg=tiny, aa=tiny,
                           num_devices=1).with_env(worlds=("suburban_residential",)).validate()
  ph = iteration.make_phase(cfg, 1, distributed.make_mesh(1))
  k = jax.random.PRNGKey(0)
  carry = jax.eval_shape(ph.init, k, ph.sg.init(k, cfg.n_obs), ph.aa.init(k, attacker.N_OBS))
  text = jax.jit(ph.run.__wrapped__).lower(carry).compile().as_text()
  stages = {gpu_profile.stage_of(v) for v in gpu_profile.op_names(text).values()}
  want = {"policy", "env_step", "sensors", "ekf", "navigator", "autopilot", "physics", "stl_reward", "autoreset",
          "values", "episode_stats", "pool_refresh", "gae", "ppo_update"}
  assert want <= stages, want - stages
