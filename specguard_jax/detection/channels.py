"""The residual detector's channels: the EKF's aiding-sensor innovation channels, then the IMU model's six.

Its own module so that the preset files (detection.preset_file) can check a file's channels without importing the
detector, which reads its shipped preset through them.
"""

from specguard_jax import ekf as ekf_lib

CHANNELS = ekf_lib.CHANNELS + ("accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z")
N_CHANNELS = len(CHANNELS)
