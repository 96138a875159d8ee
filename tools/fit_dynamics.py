"""Regenerate the reconstruction's shipped dynamics model: assets/dynamics_<vehicle>.json.

  python tools/fit_dynamics.py --vehicle drone --missions 16 --seconds 40
  python tools/fit_dynamics.py --vehicle rover --missions 16 --seconds 40

See specguard_jax/calibration/dynamics_fit.py; --help for the options.
"""

from specguard_jax.calibration import dynamics_fit

if __name__ == "__main__":
  dynamics_fit.main()
