"""Per-frame camera pose against a landmark model (brief, section 4.3): the `Tracker`, split
by concern into mixins (flow.py: optical flow; schedule.py: detection scheduling on the
worker thread; search.py: search boxes and guided matching; patching.py: points placed by
their keyframe patches; relocalise.py: relocalisation;
gating.py: the gate and the covariances), its settings (settings.py), the frame loop
(`track_frames`) and the smoother (smooth.py). Pure core: no click, no printing.

The smoother is composed with the tracker in one place, `pipelines.track`.
"""

from .settings import TrackSettings
from .tracker import Tracker, track_frames, warm_up

__all__ = ["TrackSettings", "Tracker", "track_frames", "warm_up"]
