"""SqueezeSeg network, its recurrent CRF, ONNX export, runners and training.

Importing ``models`` or ``models.runner`` does not import torch; ``models.squeezeseg``,
``models.crf``, ``models.export`` and ``models.train`` do.
"""
