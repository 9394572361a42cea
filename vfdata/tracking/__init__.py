"""3D tracking of tissue points: the paper's geometry-constrained SIREN tracker and baselines.

`GeometryTracker` (geometry.py) is the paper's method (`mode="geometry+"` adds an image-flow term);
`KLTTracker` (klt.py) lifts OpenCV Lucas-Kanade tracks with the depth map; `CoTrackerTracker`
(cotracker.py) does the same with CoTracker3 from a local checkpoint; groundtruth.py carries the
simulator's material points along as an upper bound and as the reference of the error metrics.
"""

from vfdata.tracking.geometry import GeometryTracker, TrackerOptions
from vfdata.tracking.sampling import farthest_point_sampling

__all__ = ["GeometryTracker", "TrackerOptions", "farthest_point_sampling"]
