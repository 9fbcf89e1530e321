"""Engine tests run in one process like ``python -m engine``: its process-wide torch
settings (deterministic CPU kernels for bitwise resume) are applied once here."""

from engine.runtime import configure_torch

configure_torch(deterministic=True)
