"""The frames a recording's clouds and tracks can be written in: one option set for the engine and the
commands (light: no OpenCV or torch, so `vfdata --help` stays fast)."""

# "tissue": the tube's object frame as the product decides it (the paper's axis search on several fits,
# the clamped end by independent cues, a verdict: vfdata.recon.tissue_frame); "paper": the paper's search
# on the first cloud alone (vfdata.recon.object_frame.estimate_object_frame); "board": a flat organ on a
# board (normal = up, vfdata.recon.plane); "camera": the left camera's; "auto": tissue for stereo
# recordings, board for RGB-D ones (vfdata.processing).
OBJECT_FRAMES = ("auto", "tissue", "paper", "board", "camera")
TUBE_FRAMES = ("tissue", "paper")  # the frames of a tube-like tissue (not for a flat organ's RGB-D recording)

OBJECT_FRAME_HELP = ("frame of clouds and tracks: tissue (the tube's object frame with its checks; auto for stereo), "
                     "paper (the paper's search alone, to reproduce it), board (a flat organ's board, normal = up; "
                     "auto for RGB-D) or camera")
