"""specguard-jax: JAX/MJX trainer for specification-aware attack recovery of robotic autonomous vehicles."""

__version__ = "0.1.0"
