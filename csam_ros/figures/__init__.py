"""A run's figures: :mod:`~csam_ros.figures.draw` draws them (it imports matplotlib),
:mod:`~csam_ros.figures.worker` draws them in a forked process while the run computes."""

# a run's figures, in this order
FIGURES = ("local_maps.png", "heading_sigma.png", "joined_map.png")
