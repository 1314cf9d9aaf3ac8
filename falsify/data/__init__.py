"""Data on disk: KITTI and SemanticKITTI scans, KITTI object frames, SqueezeSeg range images,
sets of labelled scans, and the synthetic training scenes written in those layouts."""
