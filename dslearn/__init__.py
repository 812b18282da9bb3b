"""dslearn: learning motion models while tracking with a network of sensors."""

__version__ = "0.1.0"
