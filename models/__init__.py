"""SqueezeSeg network, its recurrent CRF, ONNX export, runners and training.

Installed as ``falsify.models``. Importing it or ``falsify.models.runners`` does not import torch;
``squeezeseg``, ``crf``, ``export`` and ``train`` do.
"""
