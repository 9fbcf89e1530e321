"""``python -m engine`` entry point."""

import os
import sys

# The training step is hundreds of small torch ops plus Numba's thread pool in the
# rasteriser; with OpenMP's default spin-waiting the two pools starve each other on a
# busy 2-core machine (throughput measured to drop ~5x). Passive waiting keeps both
# pools usable. Must be set before torch/numba initialise OpenMP.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .cli import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
