"""evseg: real-time motion segmentation with event cameras from learned normal flow.

Stages, each a subpackage: readers (:mod:`evseg.io`), simulator (:mod:`evseg.simulator`),
normal flow (:mod:`evseg.veckm_flow`), segmentation (:mod:`evseg.segmentation`), training
(:mod:`evseg.train`), export (:mod:`evseg.export`).
"""

from evseg.events import EVENT_DTYPE, EventStream, make_events

__version__ = "0.1.0"
__all__ = ["EVENT_DTYPE", "EventStream", "make_events", "__version__"]
