"""Object-centred reconstruction, the first half of the pipeline (the paper's Fig. 2 a-e): stereo
depth, tissue segmentation, tissue point cloud and the object frame. Each stage is a pure
array-in, array-out module usable without MCAP."""

from vfdata.recon.cloud import tissue_cloud
from vfdata.recon.depth import DEPTH_BACKENDS, DepthEstimator, make_depth_estimator
from vfdata.recon.object_frame import ObjectFrame, estimate_object_frame, up_in_camera
from vfdata.recon.segment import (
    SEGMENT_BACKENDS,
    DetectorPrompt,
    Prompt,
    Segmenter,
    make_segmenter,
    mask_iou,
    segment_video,
)

__all__ = [
    "DEPTH_BACKENDS",
    "SEGMENT_BACKENDS",
    "DepthEstimator",
    "DetectorPrompt",
    "ObjectFrame",
    "Prompt",
    "Segmenter",
    "estimate_object_frame",
    "make_depth_estimator",
    "make_segmenter",
    "mask_iou",
    "segment_video",
    "tissue_cloud",
    "up_in_camera",
]
