"""State reconstruction (SpecGuard Sec. 4.5, issue 4): checkpointer, system-identification estimator, selective
reconstruction, and the EKF / denoising-autoencoder baselines. See recon.py for the API."""

from specguard_jax.estimation.checkpointer import (CheckpointState, ckpt_get, ckpt_init, ckpt_ordered,
                                                   ckpt_update)
from specguard_jax.estimation.dynamics import DynParams, DynState, fit_dynamics
from specguard_jax.estimation.recon import (INPUT_NAMES, SENSOR_DEPS, ReconConfig, ReconState, dependent_components,
                                            input_vector, recon_init, recon_scan, recon_update, true_input_vector)
