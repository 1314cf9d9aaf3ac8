"""falsify: find the blind spots of LiDAR segmentation networks in synthetic driving scenes."""

__version__ = "0.2.0"
