"""apose_studio: 6D assembly pose estimation by point-cloud registration, with a browser studio."""

__version__ = "0.1.0"
