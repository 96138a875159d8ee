"""Calibration and design against flown missions, built on the envs (`envs.record`).

- `detector_presets`: the residual detector's thresholds from attack-free missions (assets/detector_<vehicle>.json;
  `python tools/calibrate_detector.py`).
- `dynamics_fit`: the system-ID dynamics model the reconstruction rolls forward (assets/dynamics_<vehicle>.json;
  `python tools/fit_dynamics.py`).
- `stealthy`: stealthy ramp attacks designed against a calibrated detector (the fastest ramp that stays hidden).
The core modules they feed (specguard_jax.detection, specguard_jax.estimation) only read the files these write.
"""
