"""VisionForce data: recordings (MCAP), conversion, simulation, reconstruction, tracking, datasets."""

__version__ = "0.1.0"
