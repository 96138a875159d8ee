"""Every command-line entry point prints its --help (argparse expands '%' in help texts, so a stray one crashes it)."""

import importlib

import pytest


@pytest.mark.parametrize("module", ["train", "evaluate", "specguard_jax.cli.train", "specguard_jax.cli.evaluate",
                                    "envs.fly", "specguard_jax.calibration.dynamics_fit",
                                    "specguard_jax.calibration.detector_presets"])
def test_help_prints_usage_and_exits_0(module, capsys):
  main = importlib.import_module(module).main
  with pytest.raises(SystemExit) as e:
    main(["--help"])
  assert e.value.code == 0
  assert capsys.readouterr().out.startswith("usage:")
