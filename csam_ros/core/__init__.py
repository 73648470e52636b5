"""The pure core of csam_ros: models, smoothing, alignment, association, joining and
simulation. Nothing under this package imports ROS."""
