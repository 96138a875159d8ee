"""Physical sensor attacks (spoofing) as data: y_a(t) = y(t) + b(t) on one or several sensors, before the EKF.

`AttackSchedule` is a jittable pytree (target mask, bias vectors, onset, duration, profile), so scripted campaigns,
random sampling (`sample_attack`) and the learned attack agent all drive the same `apply_attack`. Stealthy ramps
designed against a calibrated detector, by flying the env, are built above the envs: specguard_jax.calibration.stealthy.
"""

from specguard_jax.attacks.attacks import (  # noqa: F401
    BIAS_DIMS, BIAS_RANGES, PROFILES, SENSOR_NAMES, AttackConfig, AttackSchedule, apply_attack, attack_active, bias_at,
    no_attack, sample_attack, schedule_for)
