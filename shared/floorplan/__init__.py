"""Buildings from the maps robots already have: a ROS occupancy grid (map_server's map.yaml and
image, ``occupancy``) segmented into rooms and areas joined by passages (``rooms``), written as
the fleet's graph file with a regions image and a preview (``graph_file``); synthetic office floors
with their true rooms (``floors``) to measure the segmentation by. Needs the ``maps`` extra
(SciPy, scikit-image, Pillow, PyYAML); importing this package alone loads none of them."""

MAX_REGION_M = 8.0  # the widest region a node stands for: a robot at its centre sees it (metres)
MIN_DOOR_M = 0.6  # the narrowest passage a robot drives through (metres)
MAX_DOOR_M = 1.6  # openings narrower than this separate rooms (metres)
