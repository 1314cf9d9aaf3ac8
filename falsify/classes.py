"""The classes of every label, metric and model output, by id: defined here once."""

CLASSES = ("unknown", "car", "pedestrian", "cyclist")
UNKNOWN, CAR, PEDESTRIAN, CYCLIST = range(len(CLASSES))
