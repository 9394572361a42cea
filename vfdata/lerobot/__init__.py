"""LeRobot datasets (docs/lerobot.md), read and written with pyarrow and PyAV, without the `lerobot`
package: `folder` (a dataset's meta/ and where its episodes live, v2.x and v3.0), `columns` (Parquet
columns <-> arrays), `video` (MP4 encode and decode), `features` (which features are the views, the
force, the pose; the features our export writes), `windows` (native-rate force samples per frame
interval), and for the export `episodes` (a recording's rows), `writers` (the v3.0 and v2.1 file
layouts), `stats`, `card` (the dataset card) and `export` itself. The other direction, dataset ->
recording MCAPs, is a converter: `vfdata.conversion.lerobot_episodes` and `lerobot_dataset`."""
