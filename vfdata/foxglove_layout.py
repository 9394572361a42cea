"""The Foxglove layout of our topics (docs/foxglove_layout.json): the left image with the tissue mask
laid over it and the tracked points projected, the tissue cloud and tracked points in 3D in the object
frame, Fx, Fy, Fz of `/force/estimate` over time, and below them how sure each is: the half-width of
its calibrated band (`/force/estimate/band`) and how far it lies beyond the training range
(`/force/estimate/beyond`), N, and how unlike training's its input is (`/force/estimate/unlike`,
> 1: unlike). The same layout serves `vfdata live` and the
files (a recording opened with its derived and force files), since both have the same topics.

    python -m vfdata.foxglove_layout > docs/foxglove_layout.json      # Foxglove: Layouts -> Import
    python -m vfdata.foxglove_layout --rgbd > docs/foxglove_layout_rgbd.json   # the depth image instead

Built with the `foxglove-sdk` package's layout types (the extra `live`)."""

from __future__ import annotations

import json
import sys

from vfdata.foxglove_server import import_foxglove
from vfdata.recording import layout


def layout_json(rgbd: bool = False) -> str:
    """The layout as Foxglove imports it (indented JSON); `rgbd`: an RGB-D recording's, whose image
    panel shows the depth camera's image (`/camera/depth/image`) instead of the left view."""
    import_foxglove()
    import foxglove.layouts as fl  # foxglove-sdk: the `live` extra

    view, info, name = ((layout.DEPTH_IMAGE, layout.DEPTH_INFO, "depth image") if rgbd else
                        (layout.LEFT_IMAGE, layout.LEFT_INFO, "left image"))
    image = fl.ImagePanel(title=f"{name}, tissue mask, tracked points", config=fl.ImageConfig(
        image_mode=fl.ImageModeConfig(
            image_topic=view, calibration_topic=info,
            overlay_topics=[fl.ImageOverlayTopicConfig(id="mask", topic=layout.TISSUE_MASK, visible=True,
                                                        opacity=0.35, pixel_alpha_mode="none")]),
        topics={layout.TRACKING_POINTS: fl.BaseRendererPointCloudTopicSettings(visible=True, point_size=6.0,
                                                                                flat_color="#ffd400ff",
                                                                                color_mode="flat")}))
    scene = fl.ThreeDeePanel(title="tissue cloud and tracked points (object frame)", config=fl.ThreeDeeConfig(
        follow_tf=layout.OBJECT_FRAME,
        topics={layout.TISSUE_POINTS: fl.BaseRendererPointCloudTopicSettings(visible=True, point_size=2.0,
                                                                              color_mode="colormap",
                                                                              color_field="z"),
                layout.TRACKING_POINTS: fl.BaseRendererPointCloudTopicSettings(visible=True, point_size=6.0,
                                                                                color_mode="flat",
                                                                                flat_color="#ffd400ff")}))
    force = fl.PlotPanel(title="force on the tissue (object frame, N)", config=fl.PlotConfig(
        paths=[fl.PlotSeries(value=f"{layout.FORCE_ESTIMATE}.wrench.force.{axis}", label=f"F{axis}",
                             timestamp_method="headerStamp", enabled=True) for axis in "xyz"],
        show_legend=True))
    # The unlike-training number has no header: its log time is the estimate's stamp.
    sure = fl.PlotPanel(title="how sure: 90% band half-width (solid), beyond training (dashed), N; "
                              "unlike training (dotted, right axis, > 1: unlike)",
                        config=fl.PlotConfig(paths=[
                            *(fl.PlotSeries(value=f"{layout.FORCE_BAND}.wrench.force.{axis}", label=f"band F{axis}",
                                            timestamp_method="headerStamp", enabled=True) for axis in "xyz"),
                            *(fl.PlotSeries(value=f"{layout.FORCE_BEYOND}.wrench.force.{axis}",
                                            label=f"beyond F{axis}", timestamp_method="headerStamp", enabled=True,
                                            line_style="dashed") for axis in "xyz"),
                            fl.PlotSeries(value=f"{layout.FORCE_UNLIKE}.data", label="unlike training",
                                          timestamp_method="receiveTime", enabled=True, line_style="dotted",
                                          use_right_y_axis=True)],
                            show_legend=True))
    content = fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=1.2, content=image),
        fl.SplitItem(proportion=1.0, content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(content=scene), fl.SplitItem(content=force), fl.SplitItem(proportion=0.6, content=sure)]))])
    return json.dumps(json.loads(fl.Layout(content=content).to_json()), indent=2) + "\n"


if __name__ == "__main__":
    sys.stdout.write(layout_json(rgbd="--rgbd" in sys.argv[1:]))
