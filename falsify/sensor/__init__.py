"""The sensors: the LiDAR (presets, rays, Embree casting, return model, scans, the Simulator that
composes cached streets with windowed cars) and the camera that renders the same scene."""
