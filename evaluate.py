"""`python evaluate.py ...`: the evaluation's command line, specguard_jax.cli.evaluate (installed as
`specguard-evaluate`).

Its public names (main, plan, Progress, ...) are re-exported for callers that import `evaluate`."""

import sys

from specguard_jax.cli.evaluate import *  # noqa: F403
from specguard_jax.cli.evaluate import main

if __name__ == "__main__":
  sys.exit(main())
