"""evseg: real-time motion segmentation with event cameras from learned normal flow.

Stages, each a subpackage: readers (:mod:`evseg.io`), simulator (:mod:`evseg.simulator`),
normal flow (:mod:`evseg.veckm_flow`), segmentation (:mod:`evseg.segmentation`), training
(:mod:`evseg.train`), export (:mod:`evseg.export`).
"""

import os as _os

# OpenMP (numba's threading layer for the normal-flow encoder) keeps its threads spinning for
# a while after each parallel loop, and onnxruntime's threads, which run the network right
# after the encoder, then compete with them for the cores: on 2 cores the network took 5.6
# instead of 3.8 ms for 10 k targets (`evseg bench flow`). Threads wait passively unless the
# user chose otherwise; OpenMP reads this when it starts, so it is set on import.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from evseg.events import EVENT_DTYPE, EventStream, make_events  # noqa: E402

__version__ = "0.1.0"
__all__ = ["EVENT_DTYPE", "EventStream", "make_events", "__version__"]
