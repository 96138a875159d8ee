"""train.py --tune (specguard_jax/ppo/tune.py): bad space files are one-line errors; a tiny study on the CPU asks its
trials in vmapped batches, prunes members at a host call (a batch whose members are all pruned stops there), asks a
trial left RUNNING by a killed process again, resumes from its storage, writes a best config that --config reads, and
runs multi-objective."""

import json
import math
import os

import pytest

optuna = pytest.importorskip("optuna")   # the [test] extra installs it; a bare install skips

from specguard_jax.cli import train as train_cli  # noqa: E402
from specguard_jax.ppo import config, tune  # noqa: E402

TINY_PPO = config.PPOConfig(num_minibatches=2, update_epochs=2, lr=1e-3)


def tiny(**kw):
  """tests/test_train.py's tiny phase-1 run (2 host calls of 2 iterations of 8 steps), with one held-out mission per
  setting and 1 s episodes (training returns from the first call on, quick held-out rollouts)."""
  base = dict(num_envs=8, unroll_length=8, iters_per_call=2, phase1_steps=256, phase2_steps=0, hidden=(32, 32),
              sg=TINY_PPO, aa=TINY_PPO, checkpoint_every_s=0.0, seed=3, eval_missions=1)
  base.update(kw)
  return config.TrainConfig(**base).with_env(worlds=("suburban_residential",), max_episode_s=1.0).validate()


SPACE = {"sg.lr": {"type": "log_uniform", "low": 1e-4, "high": 3e-3},
         "sg.ent_coef": {"type": "uniform", "low": 0.0, "high": 0.02}}


def _write(tmp_path, obj, name="space.json"):
  p = tmp_path / name
  p.write_text(obj if isinstance(obj, str) else json.dumps(obj))
  return str(p)


@pytest.mark.parametrize("space, message", [
    (None, "cannot read tune space"),
    ("{not json", "cannot read tune space"),
    ([1, 2], "must hold a non-empty JSON object"),
    ({}, "must hold a non-empty JSON object"),
    ({"sg.lr": 1e-3}, "sg.lr: expected an object"),
    ({"sg.lr": {"type": "normal", "low": 0, "high": 1}}, "type 'normal' is not one of log_uniform"),
    ({"sg.lr": {"type": "log_uniform", "low": 0, "high": 1e-3}}, "needs 0 < low < high"),
    ({"sg.lr": {"type": "uniform", "low": 1e-3, "high": 1e-3}}, "needs low < high"),
    ({"sg.lr": {"type": "uniform", "low": "a", "high": 1}}, "needs numeric"),
    ({"sg.lr": {"type": "uniform", "low": 0, "high": 1, "step": 1}}, "uniform takes high, low, not step"),
    ({"seed": {"type": "int", "low": 0.5, "high": 3}}, "int needs integer"),
    ({"seed": {"type": "int", "low": 3, "high": 1}}, "int needs low <= high"),
    ({"env.clearance": {"type": "categorical", "choices": []}}, "needs \"choices\": a non-empty list"),
    ({"no_such_key": {"type": "uniform", "low": 0, "high": 1}}, "no_such_key"),
    ({"sg.num_minibatches": {"type": "int", "low": 0, "high": 4}}, "sg.num_minibatches = 0 is not allowed"),
    ({"action": {"type": "categorical", "choices": ["gaussian", "wobbly"]}}, "wobbly"),
])
def test_bad_space_files_are_one_line_errors(tmp_path, space, message):
  path = str(tmp_path / "missing.json") if space is None else _write(tmp_path, space)
  with pytest.raises(ValueError) as e:
    tune.load_space(path, config.TrainConfig())
  assert message in str(e.value) and "\n" not in str(e.value), str(e.value)
  assert path in str(e.value)


def test_tune_flags_are_one_line_errors(tmp_path, capsys):
  bad = _write(tmp_path, {"sg.lr": {"type": "uniform", "low": 1, "high": 0}})
  cases = [(["--tune", "2"], "--tune needs --tune-space FILE"),
           (["--tune", "0", "--tune-space", bad], "must be >= 1"),
           (["--tune", "2", "--tune-space", bad, "--sweep", "seed=1,2"], "--tune and --sweep exclude each other"),
           (["--tune", "2", "--tune-space", bad, "--out", str(tmp_path / "o")], "needs low < high")]
  for argv, message in cases:
    assert train_cli.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err, (argv, err)


def test_space_values_reach_the_config(tmp_path):
  """Every kind suggests values in its range, under the config key; list choices go through Optuna as JSON text."""
  dims = tune.load_space(_write(tmp_path, {**SPACE, "seed": {"type": "int", "low": 0, "high": 9, "step": 3},
                                           "hidden": {"type": "categorical", "choices": [[32, 32], [16]]},
                                           "env.detector": {"type": "categorical", "choices": ["oracle"]}}),
                         config.TrainConfig())
  study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
  for _ in range(5):
    point = tune.suggest(study.ask(), dims)
    cfg = config.from_dict(config.nested(point), config.TrainConfig()).validate()
    assert 1e-4 <= cfg.sg.lr <= 3e-3 and 0 <= cfg.sg.ent_coef <= 0.02 and cfg.seed in (0, 3, 6, 9)
    assert cfg.hidden in ((32, 32), (16,)) and cfg.env.detector == "oracle"


class _PruneSome(optuna.pruners.BasePruner):
  """Prunes trials 1, 3 and 4 at their first report: batch (1, 2) keeps one member, batch (3, 4) loses both."""

  def prune(self, study, trial):
    return trial.number in (1, 3, 4)


def test_study_prunes_resumes_and_writes_the_best_config(tmp_path):
  """The pruned study scores training return (no held-out rollouts: quick); the multi-objective one at the end
  scores the held-out evaluation after the last host call."""
  out = tmp_path / "study"
  out.mkdir()
  storage = f"sqlite:///{out / 'study.db'}"
  cfg = tiny()
  dims = tune.load_space(_write(tmp_path, SPACE), cfg)
  # A process killed mid-trial leaves trial 0 RUNNING in the storage.
  killed = optuna.create_study(storage=storage, study_name="s", direction="maximize")
  lost = tune.suggest(killed.ask(), dims)
  spec = tune.StudySpec(trials=4, batch=2, storage=storage, name="s", objective="return", pruner=_PruneSome())
  res = tune.run_study(cfg, dims, spec, str(out), progress=False, log=lambda m: None)
  trials = {t.number: t for t in optuna.load_study(storage=storage, study_name="s").get_trials()}
  S = optuna.trial.TrialState
  assert {n: t.state for n, t in trials.items()} == {0: S.FAIL, 1: S.PRUNED, 2: S.COMPLETE, 3: S.PRUNED, 4: S.PRUNED}
  assert trials[1].params == lost                                  # the killed trial's point, asked again
  assert sorted(trials[2].intermediate_values) == [0, 1]          # reported at both host calls
  assert sorted(trials[1].intermediate_values) == [0]             # pruned at the first; its lane ran on
  assert all(trials[n].user_attrs["program_members"] == 2 for n in (1, 2, 3, 4))   # each batch: one program
  iters = lambda n: len(open(out / f"trial_{n}" / "metrics.jsonl").readlines())  # noqa: E731
  assert iters(1) == iters(2) == 4 and iters(3) == iters(4) == 2    # batch (3, 4) stopped after its first call
  assert trials[2].value == trials[2].user_attrs["scores"]["return"] == trials[2].intermediate_values[1]
  returns = [json.loads(x)["return"] for x in open(out / "trial_2" / "metrics.jsonl")]
  assert trials[2].value == pytest.approx([r for r in returns if math.isfinite(r)][-1])   # the latest finite training return
  best = config.load_config_file(str(out / "best_config.json"), config.TrainConfig())
  assert best.sg.lr == pytest.approx(trials[2].params["sg.lr"]) and best.num_envs == 8
  assert res["best"]["sg"]["lr"] == best.sg.lr
  rows = json.load(open(out / "tune.json"))
  assert [r["state"] for r in rows] == ["FAIL", "PRUNED", "COMPLETE", "PRUNED", "PRUNED"]
  assert [r["best"] for r in rows] == [False, False, True, False, False]

  # The same command again: the study already holds 4 finished trials, so nothing trains.
  again = tune.run_study(cfg, dims, spec, str(out), progress=False, log=lambda m: None)
  assert len(again["trials"]) == 5 and again["best"] == res["best"]

  # The study's objective's direction is fixed by its storage.
  with pytest.raises(ValueError, match="optimises"):
    tune.run_study(cfg, dims, tune.StudySpec(trials=5, batch=2, storage=storage, name="s", objective="svr"),
                   str(out), progress=False, log=lambda m: None)

  # Multi-objective (svr, rsr), in the same storage: no pruning, both values told, a Pareto trial's config written.
  multi = tune.StudySpec(trials=2, batch=2, storage=storage, name="m", objective="svr+rsr")
  res = tune.run_study(cfg, dims, multi, str(tmp_path / "multi"), progress=False, log=lambda m: None)
  trials = optuna.load_study(storage=storage, study_name="m").get_trials()
  assert [t.state for t in trials] == [S.COMPLETE, S.COMPLETE]
  assert all(len(t.values) == 2 and not t.intermediate_values for t in trials)
  for t in trials:   # the held-out SVR and RSR, averaged over the settings
    assert all(0.0 <= v <= 1.0 for v in t.values) and t.values == [t.user_attrs["scores"][k] for k in ("svr", "rsr")]
  assert os.path.exists(tmp_path / "multi" / "best_config.json") and res["best"] is not None
