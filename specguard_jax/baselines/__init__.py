"""Prior-work recovery baselines, re-implemented in our simulator and trained by our code (docs/BASELINES.md).

Registered with specguard_jax.controllers: 'ssr' (software sensors, Choi et al. RAID 2020), 'ftc' (RL recovery policy
trained only to survive), 'pid_piper' (feed-forward controller imitating the autopilot, Dash et al. DSN 2021),
'unrocker' (denoising autoencoder + original controller). 'delorean' is registered by controllers itself.
Builders import their modules lazily (importing this package stays cheap and never imports envs).
"""

from specguard_jax import controllers


def _lazy(module: str):
  def builder(ctx):
    import importlib
    return importlib.import_module(f"specguard_jax.baselines.{module}").build(ctx)
  builder.__name__ = f"build_{module}"
  return builder


controllers.register("ssr", _lazy("ssr"), "SSR: software sensors replace the compromised sensor (Choi et al.)")
controllers.register("ftc", _lazy("ftc"), "FTC: RL recovery policy trained only to avoid crashes (no specs)")
controllers.register("pid_piper", _lazy("pid_piper"), "PID-Piper: feed-forward controller imitating the autopilot")
controllers.register("unrocker", _lazy("unrocker"), "UnRocker: denoising autoencoder + original controller")
