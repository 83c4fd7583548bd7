"""The shared 2-D occupancy mapper: depth frames and laser scans → a floor-plane grid.

depth_points / scan_points turn sensor data into walker-frame `PlanarObservation`s,
grid holds the log-odds or view-count map, mapper ties them to poses and keyframes,
export writes PNG and ROS map_server files.
"""
