"""What a region worker needs, loaded once in the fork server that starts the workers.

:class:`lfcam.distance._RegionPool` starts its workers from a ``forkserver`` that imports
this module first: the measurement modules (numpy, SciPy, OpenCV, lfcam) and the compiled
kernels (:func:`lfcam.measure.kernels.warm_up`) are then loaded once and inherited by every
worker, instead of once in each spawned interpreter while the parent prepares the geometry
(two workers cost ~2 s of CPU on the 2-core machine, which the parent's geometry and region
detection waited for).
"""

from __future__ import annotations

import lfcam.measure.fastfit  # noqa: F401
import lfcam.measure.lightfield  # noqa: F401
from lfcam.measure.kernels import warm_up

warm_up()
