"""Pictures of rollouts: ray-traced videos (GIF/MP4), time-sampled USD animations, tactile plots."""

from d3grasp.viz.tactile_plot import TactileTrace
from d3grasp.viz.usd_animation import UsdRecorder
from d3grasp.viz.video import VideoRecorder

__all__ = ["TactileTrace", "UsdRecorder", "VideoRecorder"]
