"""`python train.py ...`: the trainer's command line, specguard_jax.cli.train (installed as `specguard-train`).

Its public names (main, parse_args, build_config, ...) are re-exported for callers that import `train`."""

import sys

from specguard_jax.cli.train import *  # noqa: F403
from specguard_jax.cli.train import main

if __name__ == "__main__":
  sys.exit(main())
