"""Regenerate the residual detector's shipped preset: assets/detector_<vehicle>.json.

  python tools/calibrate_detector.py --vehicle drone --missions 1024
  python tools/calibrate_detector.py --vehicle rover --missions 1024

See specguard_jax/calibration/detector_presets.py for the recipe; --help for the options.
"""

from specguard_jax.calibration import detector_presets

if __name__ == "__main__":
  detector_presets.main()
