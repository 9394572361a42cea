"""Generic MCAP I/O, whoever wrote the file: the record layout (`records`), the index (`index`, built by
`index_builder`), random access through it (`file`: McapFile) and ROS 2's CDR encoding (`cdr`). The
VisionForce layout on top of it is `vfdata.recording`."""
