"""Prior-work recovery baselines, re-implemented in our simulator and trained by our code (docs/BASELINES.md).

Registered with specguard_jax.controllers: 'ssr' (software sensors, Choi et al. RAID 2020), 'ftc' (fault-tolerant
flight envelope at the attitude loop), 'ftc_rl' (RL recovery policy trained only to survive, velocity setpoint),
'pid_piper' (LSTM feed-forward controller predicting the PID's output at the attitude loop, Dash et al. DSN 2021),
'unrocker' (temporal denoising of the IMU readings), 'unrocker_dae' (state denoising autoencoder + original
controller). 'delorean' is registered by controllers itself.
Builders import their modules lazily (importing this package stays cheap and never imports envs).
"""

from specguard_jax import controllers

TRAINED = ("ssr", "unrocker_dae", "pid_piper", "ftc_rl")
"""The baselines that train or fit (the others are rules): each leaves a cache whose build record
common.build_meta reads (held-out errors, monitor threshold, FTC-RL's return curve)."""


def _lazy(module: str):
  def builder(ctx):
    import importlib
    return importlib.import_module(f"specguard_jax.baselines.{module}").build(ctx)
  builder.__name__ = f"build_{module}"
  return builder


controllers.register("ssr", _lazy("ssr"), "SSR: software sensors replace the compromised sensor (Choi et al.)")
controllers.register("ftc", _lazy("ftc_attitude"), "FTC: fault-tolerant flight envelope at the attitude loop (drone)")
controllers.register("ftc_rl", _lazy("ftc"), "FTC-RL: RL recovery policy trained only to avoid crashes (no specs)")
controllers.register("pid_piper", _lazy("pid_piper"),
                     "PID-Piper: LSTM feed-forward controller at the attitude loop, switched by its monitor (drone)")
controllers.register("unrocker", _lazy("unrocker"), "UnRocker: temporal denoising of the IMU readings before the EKF")
controllers.register("unrocker_dae", _lazy("unrocker_dae"), "state denoising autoencoder + original controller")
