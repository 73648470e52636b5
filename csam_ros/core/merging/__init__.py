"""The merger's work on held maps, without ROS: joins of the latest maps. Imports the layers
below."""
