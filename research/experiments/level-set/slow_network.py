"""A slow network for `falsify bench map --timed`: the bundled SqueezeSeg's answers, each frame
held back `DELAY_S` seconds, as a heavy network (RangeNet++, a sparse-convolution net on a CPU)
would take. Run it as `--model research/experiments/level-set/slow_network.py:factory` (or `:drive`
for `squeezeseg-drive`)."""

import time

import numpy as np

from falsify.models.runners import load_segmenter

DELAY_S = 0.25   # seconds a frame: a heavy network's cost on a CPU, or a busy GPU's share


class Slow:
    def __init__(self, model=None, threads=None):
        self.net = load_segmenter(model, threads=threads)
        self.spec = {"name": f"{self.net.spec.name}-slow", "height": 64, "width": 512,
                     "output_kind": "logits", "num_classes": 4,
                     "classes": {"unknown": 0, "car": 1, "pedestrian": 2, "cyclist": 3}}

    def predict(self, batch):
        time.sleep(DELAY_S * len(batch))
        return np.asarray(self.net.predict(np.stack(batch)).classes, np.int64)


def factory(threads=None):
    """The bundled network, slowed."""
    return Slow(None, threads)


def drive(threads=None):
    """`squeezeseg-drive` (the network with blind spots on our streets), slowed."""
    return Slow("squeezeseg-drive", threads)
