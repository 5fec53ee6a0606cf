"""Learned stages of mateqa (PyTorch only): shape completion and relation networks.

Completion: ``completion`` (the paper's generator and critic, the ``ae`` variant), ``baselines``
(3D-R2N2), ``data`` (the data pipeline's example contract, shards, seeded batches),
``synthetic`` (boxes and cylinders for tests), ``train`` (``train_completion``, ``predict``) and
``checkpoint`` (self-describing, weights-only checkpoints).

Relations: ``relations`` (the Logic Tensor Network over the ten relations of a part pair, its
fuzzy operators and knowledge base, consistent decisions, violations) and
``relations_train`` (``train_relations``, ``predict_relations``, relation checkpoints),
``relation_data`` (the pair-view dataset) and ``relate`` (every method on every input of the
captures: the relation stage's harness).
"""
