"""The trade-off's knob names, apart from its measuring code so that the command line lists
them without importing it (pandas, the samplers)."""

KNOBS = ("resolution", "lod", "precision", "crf", "step", "budget", "preset")
