"""falsify: find the blind spots of LiDAR segmentation networks in synthetic driving scenes."""

__version__ = "0.1.0"
