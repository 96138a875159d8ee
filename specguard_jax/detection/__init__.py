"""Attack detection, diagnosis and recovery switching (issue 4): model-based residual CUSUM detector + oracle."""

from specguard_jax.detection.detector import (  # noqa: F401
    CHANNEL_SENSOR, CHANNELS, N_CHANNELS, DetectorConfig, DetectorState, calibrate, consistency, cusum_step,
    detector_init, detector_update, diagnose, diagnose_mask, oracle_update, residuals)
