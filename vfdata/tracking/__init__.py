"""3D tracking of tissue points: the paper's geometry-constrained SIREN tracker and baselines.

`GeometryTracker` (geometry.py) is the paper's method (`mode="geometry+"` adds an image-flow term);
`KLTTracker` (klt.py) lifts OpenCV Lucas-Kanade tracks with the depth map; `CoTrackerTracker`
(cotracker.py) does the same with CoTracker3 from a local checkpoint; `GroundTruthTracker`
(groundtruth.py) carries the simulator's material points along, the upper bound and the reference of
the error metrics. `make_tracker` (registry.py) builds any of them by name (`TRACKERS`) behind one
interface, `Tracker`, fed one `FrameInputs` per frame.
"""

from vfdata.tracking.cotracker import CoTrackerTracker, load_cotracker
from vfdata.tracking.geometry import GeometryTracker, TrackerOptions
from vfdata.tracking.groundtruth import GroundTruthTracker, ground_truth_tracks
from vfdata.tracking.klt import KLTTracker
from vfdata.tracking.registry import TRACKERS, FrameInputs, Tracker, make_tracker
from vfdata.tracking.sampling import farthest_point_sampling, isolated_points, select_reference_points

__all__ = [
    "TRACKERS",
    "CoTrackerTracker",
    "FrameInputs",
    "GeometryTracker",
    "GroundTruthTracker",
    "KLTTracker",
    "Tracker",
    "TrackerOptions",
    "farthest_point_sampling",
    "isolated_points",
    "select_reference_points",
    "ground_truth_tracks",
    "load_cotracker",
    "make_tracker",
]
