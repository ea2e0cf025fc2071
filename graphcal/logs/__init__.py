"""Robot logs in: ROS 1 bags, ROS 2 bags (sqlite3, MCAP), bare MCAP files and CSV exports become
graphcal datasets (docs/import.md).

* ``reader``: one streaming reader over every log format rosbags reads (messages one at a time).
* ``mapping``: which topic is what (detected by message type), as an editable ``import_map.yaml``.
* ``messages``: ROS messages -> numbers (joints, IMU, points, foot loads, transforms).
* ``stations``: still windows with every foot loaded, found while streaming.
* ``csv_log``: CSV exports with a column-mapping YAML.
* ``assemble``: the passes over a log and the dataset written atomically.
"""
