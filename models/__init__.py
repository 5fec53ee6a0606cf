"""Learned stages of mateqa (PyTorch only): shape completion and relation networks.

Completion: ``completion`` (the paper's generator and critic, the ``ae`` variant), ``baselines``
(3D-R2N2), ``data`` (the data pipeline's example contract, shards, seeded batches),
``synthetic`` (boxes and cylinders for tests), ``train`` (``train_completion``, ``predict``) and
``checkpoint`` (self-describing, weights-only checkpoints).
"""
