"""Bad input to train.py and evaluate.py: each case ends with exit code 2 and exactly one line on stderr that names the
problem, before any env is built or compiled, and writes nothing (no --out directory, a resumed run untouched).

The CLIs run in-process (their main(argv)) with the trainer and the evaluation's env builder replaced by a tripwire,
so a case that got through would fail at once instead of training; the cases that need a fresh process (no warp
notice before an error, a coordinator that cannot be reached) run as subprocesses.
"""

import json
import os
import socket
import subprocess
import sys

import pytest

from specguard_jax import evaluation
from specguard_jax.cli import evaluate as evaluate_cli
from specguard_jax.cli import train as train_cli
from specguard_jax.ppo import config, runner

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TINY = config.TrainConfig(num_envs=8, unroll_length=4, phase1_steps=64, phase2_steps=64, eval_missions=0)

# (argv; $T = the case's temporary directory, $OUT = its --out, $RUN = a valid run dir), a substring of the error
TRAIN_CASES = [
    (["--envs", "0"], "num_envs = 0 is not allowed; allowed: an integer [1, 67108864]"),
    (["--envs", "1000000000000"], "num_envs = 1000000000000 is not allowed"),
    (["--envs", "abc"], "argument --envs: invalid int value: 'abc'"),
    (["--set", "sg.num_minibatches=0"], "sg.num_minibatches = 0 is not allowed; allowed: an integer >= 1"),
    (["--set", "aa.num_minibatches=3"], "must be divisible by aa.num_minibatches (3)"),
    (["--set", "sg.lr=-1"], "sg.lr = -1.0 is not allowed; allowed: a finite number > 0"),
    (["--set", "sg.lr=NaN"], "sg.lr = nan is not allowed"),
    (["--set", "aa.lr=Infinity"], "aa.lr = inf is not allowed"),
    (["--set", "sg.update_epochs=0"], "sg.update_epochs = 0 is not allowed"),
    (["--set", "sg.clip_eps=-0.2"], "sg.clip_eps = -0.2 is not allowed"),
    (["--set", "sg.max_grad_norm=0"], "sg.max_grad_norm = 0.0 is not allowed"),
    (["--set", "sg.lr_end_frac=2"], "sg.lr_end_frac = 2.0 is not allowed; allowed: a finite number [0, 1]"),
    (["--set", "sg.gamma=NaN"], "sg.gamma = nan is not allowed; allowed: a finite number (0, 1]"),
    (["--set", "obs_clip=-1"], "obs_clip = -1.0 is not allowed; allowed: a finite number > 0"),
    (["--set", "hidden=[]"], "hidden = () is not allowed; allowed: a list of at least 1 item(s)"),
    (["--set", "hidden=[256,\"x\"]"], "hidden[1] = 'x' is not allowed; allowed: an integer >= 1"),
    (["--set", "speeds=[1,\"a\",2]"], "speeds[1] = 'a' is not allowed"),
    (["--set", "speeds=[NaN,1,1]"], "speeds[0] = nan is not allowed"),
    (["--set", "activation=nosuch"], "activation = 'nosuch' is not allowed; allowed: one of tanh, relu"),
    (["--set", "eval_detector=nosuch"], "unknown eval_detector 'nosuch'"),
    (["--set", "attack_max_duration_s=-1"], "attack_max_duration_s = -1.0 is not allowed"),
    (["--set", "checkpoint_every_s=NaN"], "checkpoint_every_s = nan is not allowed"),
    (["--set", "seed=-1"], "seed = -1 is not allowed; allowed: an integer [0, 4294967295]"),
    (["--set", "env.tick_dt=NaN"], "env.tick_dt = nan is not allowed"),
    (["--set", "env.max_episode_s=0"], "env.max_episode_s = 0.0 is not allowed"),
    (["--set", "env.clearance=-1"], "env.clearance = -1.0 is not allowed"),
    (["--sweep", "seed="], "config key 'seed' must be int, got ''"),
    (["--sweep", "sg.num_minibatches=0,8"], "sg.num_minibatches = 0 is not allowed"),
    (["--config", "$T/list.json"], "must hold a JSON object, got a JSON list"),
    (["--config", "$T/nan.json"], "config file $T/nan.json: sg.lr = nan is not allowed"),
    (["--config", "$T/latin1.json"], "cannot read config file $T/latin1.json"),
    (["--out", "$T/afile"], "--out $T/afile is a file; give a directory"),
    (["--out", "$T/afile/sub"], "lies under the file $T/afile"),
    (["--resume", "$RUN", "--envs", "8"], "--envs would change the run"),
    (["--resume", "$RUN", "--steps", "100", "--config", "$T/nan.json"], "--steps, --config would change the run"),
    (["--resume", "$RUN", "--set", "seed=1"], "--set would change the run"),
    (["--resume", "$RUN", "--sweep", "seed=1,2"], "--sweep would change the run"),
    (["--resume", "$RUN", "--out", "$OUT"], "--out would change the run"),
    (["--resume", "$T/run_corrupt"], "cannot resume: cannot read config file $T/run_corrupt/config.json"),
    (["--resume", "$T/run_list"], "config.json must hold a JSON object, got a JSON list"),
    (["--resume", "$T/run_foreign"], "config.json: unknown config key 'foo'"),
    (["--resume", "$T/run_badvalue"], "config.json: sg.num_minibatches = 0 is not allowed"),
    (["--coordinator", "garbage", "--num-processes", "2", "--process-id", "0"],
     "--coordinator 'garbage' is not a coordinator address; expected HOST:PORT"),
    (["--coordinator", "host0:99999", "--num-processes", "2", "--process-id", "1"], "port '99999' is not in 1-65535"),
    (["--coordinator", "host0:1234", "--num-processes", "0", "--process-id", "0"], "--num-processes must be >= 1"),
    (["--coordinator", "127.0.0.1:$BUSY", "--num-processes", "2", "--process-id", "0"], "is in use on this host"),
    (["--params", "$T/afile"], "$T/afile:1: cannot parse 'x'"),
    (["--mission", "$T/list.json"], "list.json: not a .plan object"),
]

EVALUATE_CASES = [
    (["--out", "$T/afile"], "--out $T/afile is a file; give a directory"),
    (["--out", "$T/afile/sub"], "lies under the file $T/afile"),
    (["--run", "$T/run_list"], "config.json must hold a JSON object, got a JSON list"),
    (["--run", "$T/run_corrupt"], "cannot read config file $T/run_corrupt/config.json"),
    (["--run", "$T/run_foreign"], "unknown config key 'foo'"),
    (["--runs", "specguard_pc=$T/run_corrupt"], "--runs specguard_pc: cannot read config file"),
    (["--controllers", "specguard_rc"], "--controllers specguard_rc cannot run: no SpecGuard-RC run given"),
    (["--controllers", "no_protection,specguard_pc", "--run", "$RUN"], "--controllers specguard_pc cannot run"),
    (["--max-s", "nan"], "--max-s nan must be a finite number"),
    (["--mission-s", "inf,inf"], "--mission-s 'inf,inf' must be finite seconds"),
    (["--missions", "100000000000"], "--missions 100000000000 is not allowed"),
    (["--traj", "-1"], "--traj must be >= 0"),
    (["--controllers", ","], "--controllers ',' names none"),
    (["--mission", "$T/none.plan"], "--mission: file not found: $T/none.plan"),
    (["--params", "$T/afile"], "$T/afile:1: cannot parse 'x'"),
    (["--mission", "$T/list.json"], "list.json: not a .plan object"),
]


@pytest.fixture
def tmp(tmp_path, monkeypatch):
  """The case's directory: a file, a valid run dir and broken ones; the trainer and the env builder are tripwires."""
  def tripwire(*a, **k):
    raise AssertionError("a bad input got past the checks")
  for mod, names in ((runner, ("train", "train_sweep")),
                     (evaluation, ("make_env", "precompile", "rollout_key", "rollout"))):
    for name in names:
      monkeypatch.setattr(mod, name, tripwire)
  (tmp_path / "afile").write_text("x")
  (tmp_path / "list.json").write_text("[1]")
  (tmp_path / "nan.json").write_text('{"sg": {"lr": NaN}}')
  (tmp_path / "latin1.json").write_bytes('{"vehicle": "dr\xf6ne"}'.encode("latin-1"))
  configs = {"run": json.dumps(TINY.to_dict()), "run_corrupt": "{not json", "run_list": "[1, 2]",
             "run_foreign": '{"foo": 1}', "run_badvalue": json.dumps({**TINY.to_dict(), "sg": {"num_minibatches": 0}})}
  for name, text in configs.items():
    (tmp_path / name).mkdir()
    (tmp_path / name / "config.json").write_text(text)
  return tmp_path


def _listing(root):
  return sorted((d, tuple(sorted(f))) for d, _, f in os.walk(root))


def _run_case(cli, argv, needle, tmp, capsys, prog):
  busy = socket.socket()
  busy.bind(("0.0.0.0", 0))
  busy.listen()
  subs = {"$T": str(tmp), "$OUT": str(tmp / "out"), "$RUN": str(tmp / "run"),
          "$BUSY": str(busy.getsockname()[1])}

  def sub(s):
    for k, v in subs.items():
      s = s.replace(k, v)
    return s
  argv = [sub(x) for x in argv]
  if "--out" not in argv and "--resume" not in argv:
    argv += ["--out", str(tmp / "out")]
  before = _listing(tmp)
  capsys.readouterr()
  try:
    with pytest.raises(SystemExit) as e:
      sys.exit(cli.main(argv + ["--no-progress"]))
  finally:
    busy.close()
  err = capsys.readouterr().err.splitlines()
  assert e.value.code == 2, (argv, err)
  assert len(err) == 1 and err[0].startswith(f"{prog}: error: ") and sub(needle) in err[0], (argv, err)
  assert _listing(tmp) == before, argv          # nothing written: no --out, the run dirs untouched


@pytest.mark.parametrize("argv,needle", TRAIN_CASES, ids=[" ".join(a) for a, _ in TRAIN_CASES])
def test_train_bad_input_is_one_line_exit_2_nothing_written(argv, needle, tmp, capsys):
  _run_case(train_cli, argv, needle, tmp, capsys, "train.py")


@pytest.mark.parametrize("argv,needle", EVALUATE_CASES, ids=[" ".join(a) for a, _ in EVALUATE_CASES])
def test_evaluate_bad_input_is_one_line_exit_2_nothing_written(argv, needle, tmp, capsys):
  _run_case(evaluate_cli, argv, needle, tmp, capsys, "evaluate.py")


def test_default_suite_still_skips_a_controller_without_its_run(tmp, monkeypatch, capsys):
  """Not asked for by name, SpecGuard without a run is reported as not run (the report says why) and the evaluation
  goes on: it reaches the compile of the controllers that can run."""
  class Reached(Exception):
    pass

  def reached(jobs):   # precompile (an accelerator) or rollout_key (the CPU): the first call after the builds
    raise Reached(jobs)
  monkeypatch.setattr(evaluation, "make_env", lambda *a, **k: "env")
  monkeypatch.setattr(evaluation, "precompile", reached)
  monkeypatch.setattr(evaluation, "rollout_key", reached)
  with pytest.raises(Reached):
    evaluate_cli.main(["--out", str(tmp / "out"), "--no-progress"])
  assert capsys.readouterr().err == ""
  assert not (tmp / "out").exists()


def test_activations_are_the_networks():
  from specguard_jax.ppo import networks
  assert tuple(networks.ACTIVATIONS) == config.ACTIVATIONS


def _cli(*args, timeout=300):
  return subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=ROOT, timeout=timeout,
                        env=dict(os.environ, JAX_PLATFORMS="cpu"))


def test_train_envs_0_prints_exactly_one_line_and_no_warp_notice(tmp_path):
  p = _cli("train.py", "--envs", "0", "--out", str(tmp_path / "out"))
  assert p.returncode == 2
  assert p.stderr.splitlines() == ["train.py: error: num_envs = 0 is not allowed; allowed: an integer [1, 67108864]"]
  assert p.stdout == ""                         # no "Failed to import warp" lines before it
  assert not (tmp_path / "out").exists()


def test_unreachable_coordinator_waits_then_gives_up_in_one_line(tmp_path):
  with socket.socket() as s:                    # a port nobody listens on
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
  p = _cli("train.py", "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", "1",
           "--coordinator-timeout", "2", "--out", str(tmp_path / "out"))
  assert p.returncode == 2
  assert f"[train] waiting for coordinator 127.0.0.1:{port} (1 s)" in p.stdout.splitlines()
  err = p.stderr.splitlines()
  assert len(err) == 1 and f"coordinator 127.0.0.1:{port} not reached within 2 s" in err[0], err
  assert not (tmp_path / "out").exists()
