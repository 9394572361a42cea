"""Object-centred reconstruction, the first half of the pipeline (the paper's Fig. 2 a-e): stereo
depth, tissue segmentation, tissue point cloud and the object frame. Each stage is a pure
array-in, array-out module usable without MCAP."""

from vfdata.recon.depth import DepthEstimator, make_depth_estimator

__all__ = ["DepthEstimator", "make_depth_estimator"]
