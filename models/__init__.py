"""Learned stages of mateqa (PyTorch only): shape completion and relation networks."""
